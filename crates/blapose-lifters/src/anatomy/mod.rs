//! Anatomy3D (Chen et al., TCSVT 2021, "Anatomy-aware 3D Human Pose
//! Estimation with Bone-based Pose Decomposition").
//!
//! The pose is predicted as bone directions (per frame) and bone lengths
//! (per video), then mapped to joints:
//!
//! * **Bone-length network** ([`BoneLengthBranch`]): see that module.
//! * **Bone-direction network**, two sub-networks built from VideoPose3D's
//!   blocks, in the reference's single-output-frame (strided) form:
//!   1. an expanding convolution on the 2D keypoints and one on the
//!      detector's per-joint visibility scores (each `fw0` taps, no bias,
//!      batch norm, ReLU); their features `x` and `score * x` are
//!      concatenated (`2C`) and run through VideoPose3D's residual blocks
//!      (the first takes `2C` channels); the input of every level is kept;
//!   2. the last level's feature, repeated over the first level's frames,
//!      is concatenated with each kept level in turn and run through a
//!      second stack of residual blocks (all `2C -> C`).
//!
//!   The second stack's output gives 16 bone directions (`Conv1d(C -> 48)`,
//!   each 3-vector normalized).
//! * **Joints**: `shrink(directlinear(directions) * lengthlinear(lengths))`,
//!   `Conv1d(48 -> C)`, `Linear(16 -> C)`, `Conv1d(C -> 51)`.
//!
//! The reference also builds training-only heads (a direction head on the
//! first sub-network, two relative-joint-shift heads and their
//! embeddings). They are part of the published parameter count
//! ([`PARAMS`] = 59,177,580), so they are loaded — checkpoints load
//! unchanged — and then dropped, since no output uses them at inference.
//!
//! Inputs: normalized 2D keypoints `(B, F, 17, 2)` and, optionally, the
//! detector's visibility scores `(B, F, 17)`; without scores every joint
//! counts as fully visible (score 1).

mod bone_length;

pub use bone_length::{BoneLengthBranch, OnlineBoneLengths, PARAMS_BONE_LENGTH, REFERENCE_BONES};

use candle_core::{Device, Tensor, D};
use candle_nn::VarBuilder;

use blapose_core::{NUM_BONES, NUM_JOINTS};

use crate::error::{expect_dims, LifterError, Result};
use crate::layers::{BatchNorm, Dense, RawAffine, ResidualBlock, TemporalConv};
use crate::params::ParamLoader;
use crate::{Lifter, RandomInit, INPUT_FEATURES};

/// Parameters of the 243-frame reference model, bone-length branch included.
pub const PARAMS: usize = 59_177_580;

/// Architecture hyper-parameters.
#[derive(Debug, Clone, PartialEq)]
pub struct Anatomy3dConfig {
    /// Filter widths (odd); their product is the receptive field.
    pub filter_widths: Vec<usize>,
    /// Channels of every layer.
    pub channels: usize,
    /// Causal residual alignment (outputs depend on past frames only).
    pub causal: bool,
    /// Temperature of the bone-length attention (reference default 10).
    pub temperature: f64,
}

impl Anatomy3dConfig {
    /// The paper's 243-frame model (`3,3,3,3,3`, 1024 channels).
    pub fn receptive_field_243() -> Self {
        Self {
            filter_widths: vec![3; 5],
            channels: 1024,
            causal: false,
            temperature: 10.0,
        }
    }

    /// The same configuration with causal alignment on or off.
    pub fn with_causal(mut self, causal: bool) -> Self {
        self.causal = causal;
        self
    }

    /// Frames one output depends on.
    pub fn receptive_field(&self) -> usize {
        self.filter_widths.iter().product()
    }

    fn validate(&self) -> Result<()> {
        if self.filter_widths.len() < 2
            || self.filter_widths.iter().any(|w| w % 2 == 0)
            || self.channels == 0
        {
            return Err(LifterError::Config(format!(
                "Anatomy3D needs >= 2 odd filter widths and channels > 0; got {:?}, {}",
                self.filter_widths, self.channels
            )));
        }
        Ok(())
    }
}

impl Default for Anatomy3dConfig {
    fn default() -> Self {
        Self::receptive_field_243()
    }
}

/// Anatomy3D at inference (batch norm folded, dropout off).
pub struct Anatomy3d {
    config: Anatomy3dConfig,
    bone_length: BoneLengthBranch,
    expand: TemporalConv,
    expand_score: TemporalConv,
    first_stack: Vec<ResidualBlock>,
    second_stack: Vec<ResidualBlock>,
    shrink_direction: Dense,
    direction_embed: Dense,
    shrink: Dense,
    params: usize,
}

impl Anatomy3d {
    /// Build from weights under the reference names.
    pub fn new(config: Anatomy3dConfig, vb: VarBuilder) -> Result<Self> {
        config.validate()?;
        let l = ParamLoader::new(vb);
        let c = config.channels;
        let fw0 = config.filter_widths[0];
        let rest = &config.filter_widths[1..];
        let bone_length = BoneLengthBranch::load(&l, c, rest.len(), config.temperature)?;
        let expand = RawAffine::conv1d(
            &l.pp("expand_conv"),
            NUM_JOINTS * INPUT_FEATURES,
            c,
            fw0,
            false,
        )?
        .with_bn(&BatchNorm::load(&l.pp("expand_bn"), c)?)?
        .into_conv()?;
        let expand_score = RawAffine::conv1d(&l.pp("expand_convscore"), NUM_JOINTS, c, fw0, false)?
            .with_bn(&BatchNorm::load(&l.pp("expand_bnscore"), c)?)?
            .into_conv()?;
        // Residual stacks; `c_in(i)` is the input width of block `i`.
        let stack =
            |convs: &str, bns: &str, c_in: &dyn Fn(usize) -> usize| -> Result<Vec<ResidualBlock>> {
                let (convs, bns) = (l.pp(convs), l.pp(bns));
                rest.iter()
                    .enumerate()
                    .map(|(i, &w)| ResidualBlock::load(&convs, &bns, i, c_in(i), c, w))
                    .collect()
            };
        let first_stack = stack("layers_conv", "layers_bn", &|i| {
            if i == 0 {
                2 * c
            } else {
                c
            }
        })?;
        let second_stack = stack("layers_conv1", "layers_bn1", &|_| 2 * c)?;
        let directions = NUM_BONES * 3;
        let shrink_direction =
            RawAffine::conv1d(&l.pp("shrink_direct_2"), c, directions, 1, true)?.into_dense()?;
        let direction_embed =
            RawAffine::conv1d(&l.pp("directlinear"), directions, c, 1, true)?.into_dense()?;
        let shrink =
            RawAffine::conv1d(&l.pp("shrink"), c, NUM_JOINTS * 3, 1, true)?.into_dense()?;
        // Training-only heads: loaded so checkpoints match, then dropped.
        let joint_shifts = 3 * (NUM_JOINTS * (NUM_JOINTS + 1) / 2 - NUM_BONES);
        RawAffine::conv1d(&l.pp("shrink_direct_1"), c, directions, 1, true)?;
        for name in ["directlinear_1", "directlinear_2"] {
            RawAffine::conv1d(&l.pp(name), directions, c, 1, true)?;
        }
        for name in ["shrink_js_1", "shrink_js_2"] {
            RawAffine::conv1d(&l.pp(name), c, joint_shifts, 1, true)?;
        }
        Ok(Self {
            config,
            bone_length,
            expand,
            expand_score,
            first_stack,
            second_stack,
            shrink_direction,
            direction_embed,
            shrink,
            params: l.total(),
        })
    }

    /// Build with PyTorch-style random weights (for timing and tests).
    pub fn random(config: Anatomy3dConfig, seed: u64) -> Result<Self> {
        Self::new(config, RandomInit::new(seed).var_builder())
    }

    /// The configuration.
    pub fn config(&self) -> &Anatomy3dConfig {
        &self.config
    }

    /// The bone-length branch (for online length tracking).
    pub fn bone_length(&self) -> &BoneLengthBranch {
        &self.bone_length
    }

    /// Unit bone directions `(B, 16, 3)` ([`REFERENCE_BONES`] order) for the
    /// frame a `(B, RF, 17, 2)` window stands for (centre, or last frame
    /// when causal); `scores` `(B, RF, 17)` default to 1.
    pub fn bone_directions(&self, window: &Tensor, scores: Option<&Tensor>) -> Result<Tensor> {
        let rf = self.config.receptive_field();
        expect_dims(
            window,
            "Anatomy3D window",
            &[None, Some(rf), Some(NUM_JOINTS), Some(INPUT_FEATURES)],
        )?;
        let b = window.dim(0)?;
        let scores = match scores {
            Some(s) => {
                expect_dims(
                    s,
                    "Anatomy3D scores",
                    &[Some(b), Some(rf), Some(NUM_JOINTS)],
                )?;
                s.clone()
            }
            None => Tensor::ones((b, rf, NUM_JOINTS), window.dtype(), &Device::Cpu)?,
        };
        let causal = self.config.causal;
        let x0 = self
            .expand
            .strided(&window.reshape((b, rf, NUM_JOINTS * INPUT_FEATURES))?)?
            .relu()?;
        let s0 = self.expand_score.strided(&scores)?.relu()?;
        let mut levels = vec![x0.clone()];
        let mut x = Tensor::cat(&[&x0, &s0.mul(&x0)?], D::Minus1)?;
        for block in &self.first_stack {
            x = block.strided(&x, causal)?;
            levels.push(x.clone());
        }
        // Second sub-network: the top feature over the first level's frames,
        // joined with each kept level in turn.
        let mut x = x.broadcast_as(x0.dims())?.contiguous()?;
        for (block, level) in self.second_stack.iter().zip(&levels) {
            x = block.strided(&Tensor::cat(&[&x, level], D::Minus1)?, causal)?;
        }
        let d = self
            .shrink_direction
            .forward(&x)?
            .reshape((b, NUM_BONES, 3))?;
        Ok(d.broadcast_div(&d.sqr()?.sum_keepdim(D::Minus1)?.sqrt()?)?)
    }

    /// The pose `(B, 17, 3)` for a `(B, RF, 17, 2)` window, given bone
    /// lengths `(B, 16)` in [`REFERENCE_BONES`] order (e.g. from
    /// [`BoneLengthBranch::step`] on a stream) and optional scores.
    pub fn predict_frame_with(
        &self,
        window: &Tensor,
        scores: Option<&Tensor>,
        lengths: &Tensor,
    ) -> Result<Tensor> {
        let b = window.dim(0)?;
        expect_dims(
            lengths,
            "Anatomy3D bone lengths",
            &[Some(b), Some(NUM_BONES)],
        )?;
        let directions = self
            .bone_directions(window, scores)?
            .reshape((b, NUM_BONES * 3))?;
        let features = self
            .direction_embed
            .forward(&directions)?
            .mul(&self.bone_length.embed(lengths)?)?;
        Ok(self
            .shrink
            .forward(&features)?
            .reshape((b, NUM_JOINTS, 3))?)
    }
}

impl Lifter for Anatomy3d {
    fn name(&self) -> &'static str {
        "Anatomy3D"
    }

    fn receptive_field(&self) -> usize {
        self.config.receptive_field()
    }

    fn params(&self) -> usize {
        self.params
    }

    /// Stateless: the bone lengths come from the window's own frames (the
    /// branch's attention over all of them). Streams should track lengths
    /// with [`BoneLengthBranch::step`] and call
    /// [`Anatomy3d::predict_frame_with`] instead.
    fn predict_frame(&self, window: &Tensor) -> Result<Tensor> {
        let lengths = self.bone_length.predict_lengths(window)?;
        self.predict_frame_with(window, None, &lengths)
    }
}

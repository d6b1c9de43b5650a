//! VideoPose3D (Pavllo et al., CVPR 2019): dilated temporal convolutions.
//!
//! The architecture, as in the reference `TemporalModel`: an expanding
//! convolution (`34 -> C` channels, `filter_widths[0]` taps, no bias) with
//! batch norm and ReLU, then one residual block per further filter width
//! (a `width`-tap convolution with dilation = product of the earlier
//! widths, and a pointwise convolution, each with batch norm and ReLU;
//! both convolutions without bias), then a pointwise `C -> 51` convolution
//! with bias. Dropout is the identity at inference. With widths `3,3,3,3,3`
//! and `C = 1024` the receptive field is 243 frames and the model has
//! [`PARAMS_243`] parameters.
//!
//! Two evaluations of the same weights, as in the reference:
//!
//! * [`VideoPose3d::forward_window`]: the *optimized single-frame* form
//!   (`TemporalModelOptimized1f`), convolutions with stride = width on
//!   exactly one receptive field of frames, one output frame. This is the
//!   online path.
//! * [`VideoPose3d::forward_sequence`] / [`VideoPose3d::predict_sequence`]:
//!   the dilated form over a whole sequence, one output per window.
//!
//! The *causal* variant ([`VideoPose3dConfig::causal`]) aligns every
//! residual with the last tap of its window instead of the centre, so the
//! output for frame `t` depends on frames `t-242 ..= t` only.
//!
//! Tensor names are the reference state dict's (`expand_conv`,
//! `expand_bn`, `layers_conv.{i}`, `layers_bn.{i}`, `shrink`).

use candle_core::Tensor;
use candle_nn::VarBuilder;

use blapose_core::NUM_JOINTS;

use crate::error::{expect_dims, LifterError, Result};
use crate::layers::{BatchNorm, Dense, RawAffine, ResidualBlock, TemporalConv};
use crate::params::ParamLoader;
use crate::{Lifter, RandomInit, INPUT_FEATURES};

/// Parameters of the 243-frame reference model (`3,3,3,3,3`, 1024 channels).
pub const PARAMS_243: usize = 16_952_371;

/// Architecture hyper-parameters.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct VideoPose3dConfig {
    /// Filter width of each layer (odd); their product is the receptive field.
    pub filter_widths: Vec<usize>,
    /// Convolution channels.
    pub channels: usize,
    /// Causal convolutions (real-time use): outputs depend on past frames only.
    pub causal: bool,
}

impl VideoPose3dConfig {
    /// The paper's model: widths `3,3,3,3,3`, 1024 channels, 243 frames.
    pub fn receptive_field_243() -> Self {
        Self {
            filter_widths: vec![3; 5],
            channels: 1024,
            causal: false,
        }
    }

    /// The same configuration with causal convolutions on or off.
    pub fn with_causal(mut self, causal: bool) -> Self {
        self.causal = causal;
        self
    }

    /// Frames one output depends on.
    pub fn receptive_field(&self) -> usize {
        self.filter_widths.iter().product()
    }

    fn validate(&self) -> Result<()> {
        if self.filter_widths.is_empty() || self.filter_widths.iter().any(|w| w % 2 == 0) {
            return Err(LifterError::Config(format!(
                "VideoPose3D needs at least one filter width, all odd; got {:?}",
                self.filter_widths
            )));
        }
        if self.channels == 0 {
            return Err(LifterError::Config("VideoPose3D needs channels > 0".into()));
        }
        Ok(())
    }
}

impl Default for VideoPose3dConfig {
    fn default() -> Self {
        Self::receptive_field_243()
    }
}

/// VideoPose3D at inference (batch norm folded, dropout off).
pub struct VideoPose3d {
    config: VideoPose3dConfig,
    expand: TemporalConv,
    blocks: Vec<ResidualBlock>,
    shrink: Dense,
    params: usize,
}

impl VideoPose3d {
    /// Build from weights under the reference names (a checkpoint, or a
    /// `VarMap` for a future trainer).
    pub fn new(config: VideoPose3dConfig, vb: VarBuilder) -> Result<Self> {
        config.validate()?;
        let l = ParamLoader::new(vb);
        let c = config.channels;
        let in_dim = NUM_JOINTS * INPUT_FEATURES;
        let expand = RawAffine::conv1d(
            &l.pp("expand_conv"),
            in_dim,
            c,
            config.filter_widths[0],
            false,
        )?
        .with_bn(&BatchNorm::load(&l.pp("expand_bn"), c)?)?
        .into_conv()?;
        let (convs, bns) = (l.pp("layers_conv"), l.pp("layers_bn"));
        let blocks = config.filter_widths[1..]
            .iter()
            .enumerate()
            .map(|(i, &w)| ResidualBlock::load(&convs, &bns, i, c, c, w))
            .collect::<Result<_>>()?;
        let shrink =
            RawAffine::conv1d(&l.pp("shrink"), c, NUM_JOINTS * 3, 1, true)?.into_dense()?;
        Ok(Self {
            config,
            expand,
            blocks,
            shrink,
            params: l.total(),
        })
    }

    /// Build with PyTorch-style random weights (for timing and tests).
    pub fn random(config: VideoPose3dConfig, seed: u64) -> Result<Self> {
        Self::new(config, RandomInit::new(seed).var_builder())
    }

    /// The configuration.
    pub fn config(&self) -> &VideoPose3dConfig {
        &self.config
    }

    /// One output frame from exactly one receptive field of frames:
    /// `(B, RF, 17, 2)` -> `(B, 17, 3)`. The output is aligned with the
    /// centre frame, or with the last frame in the causal variant.
    pub fn forward_window(&self, window: &Tensor) -> Result<Tensor> {
        let rf = self.config.receptive_field();
        expect_dims(
            window,
            "VideoPose3D window",
            &[None, Some(rf), Some(NUM_JOINTS), Some(INPUT_FEATURES)],
        )?;
        let b = window.dim(0)?;
        let mut x = self
            .expand
            .strided(&window.reshape((b, rf, NUM_JOINTS * INPUT_FEATURES))?)?
            .relu()?;
        for block in &self.blocks {
            x = block.strided(&x, self.config.causal)?;
        }
        Ok(self.shrink.forward(&x)?.reshape((b, NUM_JOINTS, 3))?)
    }

    /// The dilated form over a whole sequence, without padding:
    /// `(B, T, 17, 2)` -> `(B, T - RF + 1, 17, 3)`; output `i` comes from
    /// input frames `i .. i + RF`.
    pub fn forward_sequence(&self, seq: &Tensor) -> Result<Tensor> {
        expect_dims(
            seq,
            "VideoPose3D sequence",
            &[None, None, Some(NUM_JOINTS), Some(INPUT_FEATURES)],
        )?;
        let (b, t) = (seq.dim(0)?, seq.dim(1)?);
        let rf = self.config.receptive_field();
        if t < rf {
            return Err(LifterError::Shape {
                what: "VideoPose3D sequence",
                expected: format!("(B, T >= {rf}, {NUM_JOINTS}, {INPUT_FEATURES})"),
                got: seq.dims().to_vec(),
            });
        }
        let mut x = self
            .expand
            .dilated(&seq.reshape((b, t, NUM_JOINTS * INPUT_FEATURES))?, 1)?
            .relu()?;
        let mut dilation = self.config.filter_widths[0];
        for (block, &w) in self.blocks.iter().zip(&self.config.filter_widths[1..]) {
            x = block.dilated(&x, dilation, self.config.causal)?;
            dilation *= w;
        }
        let out = x.dim(1)?;
        Ok(self.shrink.forward(&x)?.reshape((b, out, NUM_JOINTS, 3))?)
    }

    /// One pose per input frame, as the reference evaluates: the sequence
    /// is padded by repeating its first and last frames (all padding in
    /// front for the causal variant), then run through the dilated form.
    /// `(B, T, 17, 2)` -> `(B, T, 17, 3)`.
    pub fn predict_sequence(&self, seq: &Tensor) -> Result<Tensor> {
        expect_dims(
            seq,
            "VideoPose3D sequence",
            &[None, None, Some(NUM_JOINTS), Some(INPUT_FEATURES)],
        )?;
        let pad = (self.config.receptive_field() - 1) / 2;
        let (front, back) = if self.config.causal {
            (2 * pad, 0)
        } else {
            (pad, pad)
        };
        self.forward_sequence(&pad_edges(seq, front, back)?)
    }
}

/// Repeat the first frame `front` times and the last frame `back` times
/// (numpy's `edge` padding along time) of a `(B, T, ...)` tensor.
pub(crate) fn pad_edges(seq: &Tensor, front: usize, back: usize) -> Result<Tensor> {
    let t = seq.dim(1)?;
    if t == 0 {
        return Err(LifterError::Shape {
            what: "sequence",
            expected: "(B, T > 0, ...)".into(),
            got: seq.dims().to_vec(),
        });
    }
    let repeat = |frame: Tensor, n: usize| -> candle_core::Result<Tensor> {
        let mut dims = frame.dims().to_vec();
        dims[1] = n;
        frame.broadcast_as(dims)
    };
    let mut parts = Vec::with_capacity(3);
    if front > 0 {
        parts.push(repeat(seq.narrow(1, 0, 1)?, front)?);
    }
    parts.push(seq.clone());
    if back > 0 {
        parts.push(repeat(seq.narrow(1, t - 1, 1)?, back)?);
    }
    Ok(Tensor::cat(&parts, 1)?)
}

impl Lifter for VideoPose3d {
    fn name(&self) -> &'static str {
        "VideoPose3D"
    }

    fn receptive_field(&self) -> usize {
        self.config.receptive_field()
    }

    fn params(&self) -> usize {
        self.params
    }

    fn predict_frame(&self, window: &Tensor) -> Result<Tensor> {
        self.forward_window(window)
    }
}

//! Anatomy3D's bone-length network and its online accumulator.
//!
//! Chen et al. predict one set of bone lengths per *video*: a per-frame
//! MLP lifts each frame's 2D keypoints to a 3D pose independently
//! (`Linear(34 -> C)`, then residual pairs of `Linear(C -> C)`, all with
//! batch norm and ReLU, then `Linear(C -> 51)`), the bone lengths of that
//! pose are measured, and an attention module (`Linear(102 -> 16)` on the
//! pose and its absolute values, times a temperature) weighs the frames
//! with a softmax over time, per bone. Three `Linear(16 -> C)` layers embed
//! the predicted lengths for the rest of the model (`lengthlinear`, used at
//! inference, and `lengthlinear_1/_2`, which only feed training-time joint-
//! shift losses); they belong to this branch's parameter count, which is
//! then exactly the paper's 8,557,219 (= 8,504,995 for MLP, norms and
//! attention + 3 × 17,408).
//!
//! Because frames are processed independently, an online stream needs the
//! MLP once per new frame; [`OnlineBoneLengths`] keeps the softmax-weighted
//! average over every frame seen so far in O(1) memory (a streaming
//! softmax, exact up to floating-point rounding). The reference's causal
//! mode instead averages a random sample of 50 past frames; using all of
//! them is deterministic and no cheaper to get wrong.

use candle_core::{Device, Tensor, D};

use blapose_core::{BoneLengths, NUM_BONES, NUM_JOINTS};

use crate::error::{expect_dims, Result};
use crate::layers::{BatchNorm, Dense, RawAffine};
use crate::params::ParamLoader;
use crate::INPUT_FEATURES;

/// Parameters of the reference branch (1024 channels, 4 residual pairs).
pub const PARAMS_BONE_LENGTH: usize = 8_557_219;

/// The reference's bone list (`--boneindex` default): joint pairs in
/// Human3.6M joint order. The *order* is the order of the network's length
/// and direction outputs, so it is kept as the checkpoints have it.
pub const REFERENCE_BONES: [(usize, usize); NUM_BONES] = [
    (16, 15),
    (15, 14),
    (13, 12),
    (12, 11),
    (10, 9),
    (9, 8),
    (8, 7),
    (8, 11),
    (8, 14),
    (7, 0),
    (3, 2),
    (2, 1),
    (6, 5),
    (5, 4),
    (1, 0),
    (4, 0),
];

/// Anatomy3D's bone-length branch at inference.
pub struct BoneLengthBranch {
    first: Dense,
    blocks: Vec<[Dense; 2]>,
    joints: Dense,
    attention: Dense,
    length_embed: Dense,
    temperature: f64,
    bone_a: Tensor,
    bone_b: Tensor,
    params: usize,
}

impl BoneLengthBranch {
    /// Load under the reference names (`layers_convbone.{i}`,
    /// `layers_bnbone.{i}`, `boneatt`, `lengthlinear`, `lengthlinear_1/_2`);
    /// `pairs` residual pairs (the reference uses one per filter width
    /// after the first).
    pub(crate) fn load(
        l: &ParamLoader,
        channels: usize,
        pairs: usize,
        temperature: f64,
    ) -> Result<Self> {
        let before = l.total();
        let (lin, bns) = (l.pp("layers_convbone"), l.pp("layers_bnbone"));
        let layer = |i: usize, c_in: usize| -> Result<Dense> {
            RawAffine::linear(&lin.pp(i), c_in, channels, true)?
                .with_bn(&BatchNorm::load(&bns.pp(i), channels)?)?
                .into_dense()
        };
        let first = layer(0, NUM_JOINTS * INPUT_FEATURES)?;
        let blocks = (1..=pairs)
            .map(|i| Ok([layer(2 * i - 1, channels)?, layer(2 * i, channels)?]))
            .collect::<Result<_>>()?;
        let joints = RawAffine::linear(&lin.pp(2 * pairs + 1), channels, NUM_JOINTS * 3, true)?
            .into_dense()?;
        let attention =
            RawAffine::linear(&l.pp("boneatt"), NUM_JOINTS * 6, NUM_BONES, true)?.into_dense()?;
        let length_embed =
            RawAffine::linear(&l.pp("lengthlinear"), NUM_BONES, channels, true)?.into_dense()?;
        // Training-only embeddings: loaded so checkpoints match, then dropped.
        for aux in ["lengthlinear_1", "lengthlinear_2"] {
            RawAffine::linear(&l.pp(aux), NUM_BONES, channels, true)?;
        }
        let (a, b): (Vec<u32>, Vec<u32>) = REFERENCE_BONES
            .iter()
            .map(|&(a, b)| (a as u32, b as u32))
            .unzip();
        Ok(Self {
            first,
            blocks,
            joints,
            attention,
            length_embed,
            temperature,
            bone_a: Tensor::new(a, &Device::Cpu)?,
            bone_b: Tensor::new(b, &Device::Cpu)?,
            params: l.total() - before,
        })
    }

    /// Parameters of this branch.
    pub fn params(&self) -> usize {
        self.params
    }

    /// Per-frame outputs for `(N, 17, 2)` keypoints: the bone lengths of
    /// each frame's lifted pose and their attention logits (temperature
    /// applied), both `(N, 16)` in [`REFERENCE_BONES`] order.
    pub fn frame_outputs(&self, keypoints: &Tensor) -> Result<(Tensor, Tensor)> {
        expect_dims(
            keypoints,
            "bone-length frames",
            &[None, Some(NUM_JOINTS), Some(INPUT_FEATURES)],
        )?;
        let n = keypoints.dim(0)?;
        let mut h = self
            .first
            .forward(&keypoints.reshape((n, NUM_JOINTS * INPUT_FEATURES))?)?
            .relu()?;
        for [a, b] in &self.blocks {
            let r = h.clone();
            h = b.forward(&a.forward(&h)?.relu()?)?.relu()?.add(&r)?;
        }
        let joints = self.joints.forward(&h)?;
        let logits = (self
            .attention
            .forward(&Tensor::cat(&[&joints, &joints.abs()?], 1)?)?
            * self.temperature)?;
        let joints = joints.reshape((n, NUM_JOINTS, 3))?;
        let bones = joints
            .index_select(&self.bone_a, 1)?
            .sub(&joints.index_select(&self.bone_b, 1)?)?;
        let lengths = bones.sqr()?.sum(D::Minus1)?.sqrt()?;
        Ok((lengths, logits))
    }

    /// Attention-weighted bone lengths over all frames of each sequence:
    /// `(B, N, 17, 2)` -> `(B, 16)`.
    pub fn predict_lengths(&self, keypoints: &Tensor) -> Result<Tensor> {
        expect_dims(
            keypoints,
            "bone-length sequence",
            &[None, None, Some(NUM_JOINTS), Some(INPUT_FEATURES)],
        )?;
        let (b, n) = (keypoints.dim(0)?, keypoints.dim(1)?);
        let (lengths, logits) =
            self.frame_outputs(&keypoints.reshape((b * n, NUM_JOINTS, INPUT_FEATURES))?)?;
        let weights = candle_nn::ops::softmax(&logits.reshape((b, n, NUM_BONES))?, 1)?;
        Ok(lengths.reshape((b, n, NUM_BONES))?.mul(&weights)?.sum(1)?)
    }

    /// One online step: run the MLP on one new frame (`(17, 2)` or
    /// `(1, 17, 2)`), fold it into `state`, and return the current lengths.
    pub fn step(&self, frame: &Tensor, state: &mut OnlineBoneLengths) -> Result<BoneLengths> {
        let frame = frame.reshape((1, NUM_JOINTS, INPUT_FEATURES))?;
        let (lengths, logits) = self.frame_outputs(&frame)?;
        let lengths: Vec<f32> = lengths.flatten_all()?.to_vec1()?;
        let logits: Vec<f32> = logits.flatten_all()?.to_vec1()?;
        let mut l = [0.0; NUM_BONES];
        let mut g = [0.0; NUM_BONES];
        l.copy_from_slice(&lengths);
        g.copy_from_slice(&logits);
        state.push(&l, &g);
        Ok(state.lengths().unwrap_or(l))
    }

    /// `Linear(16 -> C)` embedding of `(B, 16)` lengths (`lengthlinear`).
    pub(crate) fn embed(&self, lengths: &Tensor) -> Result<Tensor> {
        self.length_embed.forward(lengths)
    }
}

/// The attention-weighted average of per-frame bone lengths over every
/// frame of a stream so far, updated one frame at a time.
#[derive(Debug, Clone)]
pub struct OnlineBoneLengths {
    max_logit: [f64; NUM_BONES],
    weight_sum: [f64; NUM_BONES],
    weighted_lengths: [f64; NUM_BONES],
    frames: usize,
}

impl Default for OnlineBoneLengths {
    fn default() -> Self {
        Self::new()
    }
}

impl OnlineBoneLengths {
    /// No frames seen.
    pub fn new() -> Self {
        Self {
            max_logit: [f64::NEG_INFINITY; NUM_BONES],
            weight_sum: [0.0; NUM_BONES],
            weighted_lengths: [0.0; NUM_BONES],
            frames: 0,
        }
    }

    /// Fold in one frame's lengths and attention logits. Weights are kept
    /// relative to the largest logit seen, so no `exp` ever overflows.
    pub fn push(&mut self, lengths: &BoneLengths, logits: &[f32; NUM_BONES]) {
        for b in 0..NUM_BONES {
            let g = logits[b] as f64;
            if g > self.max_logit[b] {
                let rescale = (self.max_logit[b] - g).exp();
                self.weight_sum[b] *= rescale;
                self.weighted_lengths[b] *= rescale;
                self.max_logit[b] = g;
            }
            let w = (g - self.max_logit[b]).exp();
            self.weight_sum[b] += w;
            self.weighted_lengths[b] += w * lengths[b] as f64;
        }
        self.frames += 1;
    }

    /// The current estimate, `None` before the first frame.
    pub fn lengths(&self) -> Option<BoneLengths> {
        (self.frames > 0).then(|| {
            std::array::from_fn(|b| (self.weighted_lengths[b] / self.weight_sum[b]) as f32)
        })
    }

    /// Frames folded in so far.
    pub fn frames(&self) -> usize {
        self.frames
    }
}

//! PoseFormer (Zheng et al., ICCV 2021): a spatial transformer over the
//! joints of each frame, then a temporal transformer over the frames.
//!
//! The architecture, as in the reference `PoseTransformer`:
//!
//! 1. *Spatial*: each joint's `(x, y)` is embedded by `Linear(2 -> 32)`, a
//!    learned per-joint positional embedding is added, 4 pre-norm
//!    transformer blocks run over the 17 joint tokens of every frame, then
//!    a LayerNorm; the 17 tokens of a frame are concatenated (joint-major)
//!    into one 544-wide frame token.
//! 2. *Temporal*: a learned per-frame positional embedding is added, 4
//!    blocks of width 544 run over the frame tokens, then a LayerNorm.
//! 3. *Head*: a weighted mean over frames (the reference's
//!    `Conv1d(frames -> 1, kernel 1)`, i.e. one learned weight per frame
//!    plus a bias), `LayerNorm(544)`, `Linear(544 -> 51)`: the pose of the
//!    centre frame.
//!
//! Blocks: `x + proj(attention(norm1(x)))`, then
//! `x + fc2(GELU(fc1(norm2(x))))`; 8 heads, qkv with bias, scale
//! `head_dim^-0.5`, MLP ratio 2, *exact* (erf) GELU. Epsilons as in the
//! reference: the blocks' norms and the spatial/temporal norms are built
//! with `partial(nn.LayerNorm, eps=1e-6)`; the head's norm is a plain
//! `nn.LayerNorm` (eps 1e-5). Dropout and drop-path are the identity at
//! inference. With 81 frames the model has [`PARAMS_81`] parameters.
//!
//! Tensor names are the reference state dict's (`Spatial_patch_to_embedding`,
//! `Spatial_pos_embed`, `Temporal_pos_embed`, `Spatial_blocks.{i}`,
//! `blocks.{i}`, `Spatial_norm`, `Temporal_norm`, `weighted_mean`,
//! `head.0`, `head.1`).

use candle_core::{Tensor, D};
use candle_nn::VarBuilder;

use blapose_core::NUM_JOINTS;

use crate::error::{expect_dims, LifterError, Result};
use crate::layers::{Dense, LayerNorm, RawAffine};
use crate::params::ParamLoader;
use crate::{Lifter, RandomInit, INPUT_FEATURES};

/// Parameters of the 81-frame reference model.
pub const PARAMS_81: usize = 9_602_885;

/// Epsilon of the transformer blocks' and the spatial/temporal norms.
pub const BLOCK_NORM_EPS: f32 = 1e-6;
/// Epsilon of the head's norm (PyTorch's default).
pub const HEAD_NORM_EPS: f32 = 1e-5;

/// Architecture hyper-parameters.
#[derive(Debug, Clone, PartialEq)]
pub struct PoseFormerConfig {
    /// Input frames (9, 27 or 81 in the paper); the output is the centre frame.
    pub frames: usize,
    /// Spatial embedding width per joint (the temporal width is 17 times it).
    pub embed_dim_ratio: usize,
    /// Blocks in each of the two transformers.
    pub depth: usize,
    /// Attention heads.
    pub num_heads: usize,
    /// MLP hidden width as a multiple of the block width.
    pub mlp_ratio: f64,
}

impl PoseFormerConfig {
    /// The paper's 81-frame model.
    pub fn frames_81() -> Self {
        Self {
            frames: 81,
            embed_dim_ratio: 32,
            depth: 4,
            num_heads: 8,
            mlp_ratio: 2.0,
        }
    }

    fn validate(&self) -> Result<()> {
        let temporal = self.embed_dim_ratio * NUM_JOINTS;
        if self.frames == 0 || self.depth == 0 || self.num_heads == 0 {
            return Err(LifterError::Config(format!(
                "PoseFormer needs frames, depth and heads > 0: {self:?}"
            )));
        }
        if !self.embed_dim_ratio.is_multiple_of(self.num_heads)
            || !temporal.is_multiple_of(self.num_heads)
        {
            return Err(LifterError::Config(format!(
                "PoseFormer widths {} and {temporal} must be multiples of {} heads",
                self.embed_dim_ratio, self.num_heads
            )));
        }
        Ok(())
    }
}

impl Default for PoseFormerConfig {
    fn default() -> Self {
        Self::frames_81()
    }
}

/// One pre-norm transformer block.
struct Block {
    norm1: LayerNorm,
    qkv: Dense,
    proj: Dense,
    norm2: LayerNorm,
    fc1: Dense,
    fc2: Dense,
    heads: usize,
    scale: f64,
}

impl Block {
    fn load(l: &ParamLoader, dim: usize, heads: usize, mlp_ratio: f64) -> Result<Self> {
        let hidden = (dim as f64 * mlp_ratio) as usize;
        let attn = l.pp("attn");
        let mlp = l.pp("mlp");
        Ok(Self {
            norm1: LayerNorm::load(&l.pp("norm1"), dim, BLOCK_NORM_EPS)?,
            qkv: RawAffine::linear(&attn.pp("qkv"), dim, 3 * dim, true)?.into_dense()?,
            proj: RawAffine::linear(&attn.pp("proj"), dim, dim, true)?.into_dense()?,
            norm2: LayerNorm::load(&l.pp("norm2"), dim, BLOCK_NORM_EPS)?,
            fc1: RawAffine::linear(&mlp.pp("fc1"), dim, hidden, true)?.into_dense()?,
            fc2: RawAffine::linear(&mlp.pp("fc2"), hidden, dim, true)?.into_dense()?,
            heads,
            scale: ((dim / heads) as f64).powf(-0.5),
        })
    }

    /// `(B, N, C)` tokens -> `(B, N, C)`.
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let (b, n, c) = x.dims3()?;
        let hd = c / self.heads;
        let qkv = self
            .qkv
            .forward(&self.norm1.forward(x)?)?
            .reshape((b, n, 3, self.heads, hd))?
            .permute((2, 0, 3, 1, 4))?
            .contiguous()?;
        let (q, k, v) = (qkv.get(0)?, qkv.get(1)?, qkv.get(2)?);
        let attn = (q.matmul(&k.t()?)? * self.scale)?;
        let attn = candle_nn::ops::softmax_last_dim(&attn)?;
        let y = attn.matmul(&v)?.transpose(1, 2)?.reshape((b, n, c))?;
        let x = x.add(&self.proj.forward(&y)?)?;
        let h = self.fc1.forward(&self.norm2.forward(&x)?)?.gelu_erf()?;
        Ok(x.add(&self.fc2.forward(&h)?)?)
    }
}

/// PoseFormer at inference (dropout and drop-path off).
pub struct PoseFormer {
    config: PoseFormerConfig,
    patch: Dense,
    spatial_pos: Tensor,
    temporal_pos: Tensor,
    spatial_blocks: Vec<Block>,
    temporal_blocks: Vec<Block>,
    spatial_norm: LayerNorm,
    temporal_norm: LayerNorm,
    weighted_mean: Dense,
    head_norm: LayerNorm,
    head: Dense,
    params: usize,
}

impl PoseFormer {
    /// Build from weights under the reference names.
    pub fn new(config: PoseFormerConfig, vb: VarBuilder) -> Result<Self> {
        config.validate()?;
        let l = ParamLoader::new(vb);
        let (ratio, f) = (config.embed_dim_ratio, config.frames);
        let dim = ratio * NUM_JOINTS;
        let blocks = |name: &str, width: usize| -> Result<Vec<Block>> {
            (0..config.depth)
                .map(|i| Block::load(&l.pp(name).pp(i), width, config.num_heads, config.mlp_ratio))
                .collect()
        };
        let zero = candle_nn::init::ZERO;
        let head = l.pp("head");
        Ok(Self {
            patch: RawAffine::linear(
                &l.pp("Spatial_patch_to_embedding"),
                INPUT_FEATURES,
                ratio,
                true,
            )?
            .into_dense()?,
            spatial_pos: l.param(&[1, NUM_JOINTS, ratio], "Spatial_pos_embed", zero)?,
            temporal_pos: l.param(&[1, f, dim], "Temporal_pos_embed", zero)?,
            spatial_blocks: blocks("Spatial_blocks", ratio)?,
            temporal_blocks: blocks("blocks", dim)?,
            spatial_norm: LayerNorm::load(&l.pp("Spatial_norm"), ratio, BLOCK_NORM_EPS)?,
            temporal_norm: LayerNorm::load(&l.pp("Temporal_norm"), dim, BLOCK_NORM_EPS)?,
            weighted_mean: RawAffine::conv1d(&l.pp("weighted_mean"), f, 1, 1, true)?
                .into_dense()?,
            head_norm: LayerNorm::load(&head.pp(0), dim, HEAD_NORM_EPS)?,
            head: RawAffine::linear(&head.pp(1), dim, NUM_JOINTS * 3, true)?.into_dense()?,
            params: l.total(),
            config,
        })
    }

    /// Build with PyTorch-style random weights (for timing and tests).
    pub fn random(config: PoseFormerConfig, seed: u64) -> Result<Self> {
        Self::new(config, RandomInit::new(seed).var_builder())
    }

    /// The configuration.
    pub fn config(&self) -> &PoseFormerConfig {
        &self.config
    }

    /// The pose of the centre frame of `(B, F, 17, 2)` keypoints, `(B, 17, 3)`.
    pub fn forward_window(&self, window: &Tensor) -> Result<Tensor> {
        let f = self.config.frames;
        expect_dims(
            window,
            "PoseFormer window",
            &[None, Some(f), Some(NUM_JOINTS), Some(INPUT_FEATURES)],
        )?;
        let b = window.dim(0)?;
        let ratio = self.config.embed_dim_ratio;
        // Spatial transformer: (B·F, 17, ratio) joint tokens.
        let mut x = self
            .patch
            .forward(&window.reshape((b * f, NUM_JOINTS, INPUT_FEATURES))?)?
            .broadcast_add(&self.spatial_pos)?;
        for block in &self.spatial_blocks {
            x = block.forward(&x)?;
        }
        let x = self.spatial_norm.forward(&x)?;
        // Temporal transformer: (B, F, 17·ratio) frame tokens.
        let mut x = x
            .reshape((b, f, NUM_JOINTS * ratio))?
            .broadcast_add(&self.temporal_pos)?;
        for block in &self.temporal_blocks {
            x = block.forward(&x)?;
        }
        let x = self.temporal_norm.forward(&x)?;
        // Weighted mean over frames: (B, C, F) · (F, 1).
        let x = self
            .weighted_mean
            .forward(&x.transpose(1, 2)?)?
            .squeeze(D::Minus1)?;
        let x = self.head.forward(&self.head_norm.forward(&x)?)?;
        Ok(x.reshape((b, NUM_JOINTS, 3))?)
    }
}

impl Lifter for PoseFormer {
    fn name(&self) -> &'static str {
        "PoseFormer"
    }

    fn receptive_field(&self) -> usize {
        self.config.frames
    }

    fn params(&self) -> usize {
        self.params
    }

    fn predict_frame(&self, window: &Tensor) -> Result<Tensor> {
        self.forward_window(window)
    }
}

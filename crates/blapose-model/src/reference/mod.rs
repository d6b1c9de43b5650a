//! The paper's two bone-length networks in candle, trainable with autograd.
//!
//! Both share the frame embedding (`Linear(34→256)`, ReLU, dropout while
//! training) and the head (`σ` of 1024 concatenated GRU states →
//! `Linear(1024→16, no bias)` → symmetric-pair averaging); they differ in
//! the recurrent part:
//!
//! * [`BoneLengthGru`] (online): GRUs `gru.0` and `gru.1` both read the
//!   stream forwards; features are `[h_0, h_1]`.
//! * [`BoneLengthBiGru`] (offline): one bidirectional GRU; features are
//!   `[h_backward, h_forward]` (backward first, as the reference code
//!   concatenates `h_n[-1], h_n[-2]`).
//!
//! Models are built from a `VarBuilder`: over a training `VarMap` the
//! tensors are created with PyTorch's initialization, over
//! [`crate::LoadedWeights::var_builder`] they are the loaded weights.

mod fused;
mod gru;

pub use gru::{GruImpl, GruParams};

use candle_core::{bail, DType, Device, Result, Tensor, D};
use candle_nn::VarBuilder;

use crate::init::init_for;
use crate::names::{GruNames, EMBED_BIAS, EMBED_WEIGHT, FC_WEIGHT};
use crate::symmetry::averaging_matrix;
use crate::{ModelKind, DROPOUT, EMBED_DIM, FEATURES, HIDDEN, INPUT_DIM, OUTPUT_DIM};
use blapose_core::skeleton::NUM_BONES;

/// Parts both models share.
#[derive(Debug, Clone)]
struct Shared {
    embed_w: Tensor,
    embed_b: Tensor,
    grus: [GruParams; 2],
    fc_w: Tensor,
    sym: Tensor,
    imp: GruImpl,
}

impl Shared {
    fn new(vb: &VarBuilder, kind: ModelKind) -> Result<Self> {
        let get =
            |shape: &[usize], name: &str| vb.get_with_hints(shape.to_vec(), name, init_for(name));
        let [na, nb] = GruNames::for_kind(kind);
        let sym: Vec<f32> = averaging_matrix().iter().flatten().copied().collect();
        Ok(Self {
            embed_w: get(&[EMBED_DIM, INPUT_DIM], EMBED_WEIGHT)?,
            embed_b: get(&[EMBED_DIM], EMBED_BIAS)?,
            grus: [GruParams::new(vb, &na)?, GruParams::new(vb, &nb)?],
            fc_w: get(&[OUTPUT_DIM, FEATURES], FC_WEIGHT)?,
            sym: Tensor::from_vec(sym, (NUM_BONES, NUM_BONES), &Device::Cpu)?
                .to_dtype(vb.dtype())?
                .to_device(vb.device())?,
            imp: GruImpl::default(),
        })
    }

    /// `(B, T, 34)` keypoints -> `(B, T, 256)` embeddings.
    fn embed(&self, x: &Tensor, train: bool) -> Result<Tensor> {
        let (batch, steps, width) = x.dims3()?;
        if width != INPUT_DIM || steps == 0 {
            bail!("expected input (B, T>0, {INPUT_DIM}), got {:?}", x.dims());
        }
        let e = x
            .reshape((batch * steps, width))?
            .matmul(&self.embed_w.t()?)?
            .broadcast_add(&self.embed_b)?
            .relu()?;
        let e = if train {
            candle_nn::ops::dropout(&e, DROPOUT)?
        } else {
            e
        };
        e.reshape((batch, steps, EMBED_DIM))
    }

    /// `(..., 1024)` GRU states -> `(..., 16)` symmetric bone lengths.
    fn head(&self, features: &Tensor) -> Result<Tensor> {
        let dims = features.dims().to_vec();
        let rows: usize = dims[..dims.len() - 1].iter().product();
        let y = candle_nn::ops::sigmoid(&features.reshape((rows, FEATURES))?)?
            .matmul(&self.fc_w.t()?)?
            .matmul(&self.sym)?;
        let mut out = dims;
        *out.last_mut().expect("features have a last dim") = OUTPUT_DIM;
        y.reshape(out)
    }
}

/// The online model: two unidirectional GRUs over the same stream.
#[derive(Debug, Clone)]
pub struct BoneLengthGru {
    shared: Shared,
}

impl BoneLengthGru {
    /// The same model computing its recurrence with `imp` (default: fused).
    pub fn with_gru_impl(mut self, imp: GruImpl) -> Self {
        self.shared.imp = imp;
        self
    }

    /// Build from `vb` (tensor names in [`crate::names`]).
    pub fn new(vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            shared: Shared::new(&vb, ModelKind::Gru)?,
        })
    }

    /// The tensors of the two GRUs (`gru.0`, `gru.1`).
    pub fn grus(&self) -> &[GruParams; 2] {
        &self.shared.grus
    }

    /// Bone lengths `(B, 16)` from the final states after `x` (`(B, T, 34)`).
    /// Dropout is applied only when `train`.
    pub fn forward(&self, x: &Tensor, train: bool) -> Result<Tensor> {
        let e = self.shared.embed(x, train)?;
        let [a, b] = &self.shared.grus;
        let run = gru::run_pair(a, b, &e, false, false, self.shared.imp)?;
        let (_, batch, hidden) = run.last.dims3()?;
        let features = run.last.transpose(0, 1)?.reshape((batch, 2 * hidden))?;
        self.shared.head(&features)
    }

    /// The prediction after every frame, `(B, T, 16)`, in eval mode. Frame
    /// `t`'s row is what an online session answers after frame `t`; the
    /// reference averages these rows over the frames seen so far.
    pub fn forward_per_frame(&self, x: &Tensor) -> Result<Tensor> {
        self.forward_per_frame_with(x, false)
    }

    /// A candle stepper for online inference one frame at a time (the
    /// unoptimized baseline of the fast engine). It snapshots the weights:
    /// build a new one after the model's variables change.
    pub fn stepper(&self) -> Result<ReferenceStepper> {
        let [a, b] = &self.shared.grus;
        Ok(ReferenceStepper {
            shared: self.shared.clone(),
            w_ih_t: Tensor::cat(&[&a.weight_ih, &b.weight_ih], 0)?
                .t()?
                .contiguous()?,
            b_ih: Tensor::cat(&[&a.bias_ih, &b.bias_ih], 0)?,
            rec: gru::Recurrent::new(a, b)?,
        })
    }

    /// [`Self::forward_per_frame`] with dropout when `train` (per-frame losses).
    pub fn forward_per_frame_with(&self, x: &Tensor, train: bool) -> Result<Tensor> {
        let e = self.shared.embed(x, train)?;
        let [a, b] = &self.shared.grus;
        let run = gru::run_pair(a, b, &e, false, true, self.shared.imp)?;
        let all = match run.all {
            Some(all) => all,
            None => bail!("GRU run kept no per-step states"),
        };
        let (steps, _, batch, hidden) = all.dims4()?;
        let features = all
            .permute((2, 0, 1, 3))?
            .reshape((batch, steps, 2 * hidden))?;
        self.shared.head(&features)
    }
}

/// The offline model: one bidirectional GRU over the whole sequence.
#[derive(Debug, Clone)]
pub struct BoneLengthBiGru {
    shared: Shared,
}

impl BoneLengthBiGru {
    /// The same model computing its recurrence with `imp` (default: fused).
    pub fn with_gru_impl(mut self, imp: GruImpl) -> Self {
        self.shared.imp = imp;
        self
    }

    /// Build from `vb` (tensor names in [`crate::names`]).
    pub fn new(vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            shared: Shared::new(&vb, ModelKind::BiGru)?,
        })
    }

    /// The tensors of the forward and backward directions.
    pub fn grus(&self) -> &[GruParams; 2] {
        &self.shared.grus
    }

    /// Bone lengths `(B, 16)` from the whole sequence `x` (`(B, T, 34)`).
    /// Dropout is applied only when `train`.
    pub fn forward(&self, x: &Tensor, train: bool) -> Result<Tensor> {
        let e = self.shared.embed(x, train)?;
        let [fwd, bwd] = &self.shared.grus;
        let run = gru::run_pair(fwd, bwd, &e, true, false, self.shared.imp)?;
        // backward direction's final state first, as in the reference code
        let features = Tensor::cat(&[run.last.get(1)?, run.last.get(0)?], D::Minus1)?;
        self.shared.head(&features)
    }
}

/// Online inference in candle, one frame per call; see [`BoneLengthGru::stepper`].
pub struct ReferenceStepper {
    shared: Shared,
    w_ih_t: Tensor,
    b_ih: Tensor,
    rec: gru::Recurrent,
}

impl ReferenceStepper {
    /// Frames `x` `(B, 34)` and states `(B, 1024)` (`gru.0` then `gru.1`,
    /// zeros at the start) -> `(new states, lengths (B, 16))`.
    pub fn step(&self, x: &Tensor, state: &Tensor) -> Result<(Tensor, Tensor)> {
        let (batch, width) = x.dims2()?;
        let e = self
            .shared
            .embed(&x.reshape((batch, 1, width))?, false)?
            .reshape((batch, EMBED_DIM))?;
        let gi = e
            .matmul(&self.w_ih_t)?
            .broadcast_add(&self.b_ih)?
            .reshape((batch, 2, 3 * HIDDEN))?
            .transpose(0, 1)?; // (2, B, 1536)
        let [gr, gz, gn] = gru::split_gates(&gi)?;
        let h = state
            .reshape((batch, 2, HIDDEN))?
            .transpose(0, 1)?
            .contiguous()?;
        let h = self.rec.cell([&gr, &gz, &gn], &h)?;
        let features = h.transpose(0, 1)?.reshape((batch, 2 * HIDDEN))?;
        let y = self.shared.head(&features)?;
        Ok((features, y))
    }
}

/// Number of scalar parameters in a model's tensors.
pub fn count_parameters<'a>(tensors: impl IntoIterator<Item = &'a Tensor>) -> usize {
    tensors.into_iter().map(|t| t.elem_count()).sum()
}

/// A `(B, T, 34)` f32 input tensor from row-major frames (helper for callers
/// holding plain slices).
pub fn frames_tensor(frames: &[f32], batch: usize, steps: usize) -> Result<Tensor> {
    if frames.len() != batch * steps * INPUT_DIM {
        bail!(
            "expected {} values for ({batch}, {steps}, {INPUT_DIM}), got {}",
            batch * steps * INPUT_DIM,
            frames.len()
        );
    }
    Tensor::from_slice(frames, (batch, steps, INPUT_DIM), &Device::Cpu)?.to_dtype(DType::F32)
}

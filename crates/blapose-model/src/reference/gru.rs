//! A GRU layer in plain candle ops, two directions at a time.
//!
//! Both models run exactly two GRU directions over one embedded sequence
//! (the online model's two GRUs see the same frames; the Bi-GRU's backward
//! direction sees them reversed). Running the pair in lockstep lets every
//! time step be *one* batched matmul of shape `(2, B, 512) x (2, 512, 1536)`
//! and one set of element-wise ops on `(2, B, ...)` instead of two, which
//! halves the number of autograd nodes. The input projection does not
//! depend on the state, so it is one big matmul over all frames before the
//! time loop. The cell follows PyTorch exactly (gate order r, z, n):
//!
//! ```text
//! r = σ(W_ir x + b_ir + W_hr h + b_hr)
//! z = σ(W_iz x + b_iz + W_hz h + b_hz)
//! n = tanh(W_in x + b_in + r ⊙ (W_hn h + b_hn))
//! h' = (1 - z) ⊙ n + z ⊙ h
//! ```

use candle_core::{DType, Result, Tensor, D};
use candle_nn::VarBuilder;

use crate::init::init_for;
use crate::names::GruNames;
use crate::{EMBED_DIM, GATES, HIDDEN};

/// The four tensors of one GRU direction, PyTorch layout.
#[derive(Debug, Clone)]
pub struct GruParams {
    /// `[1536, 256]`, rows r | z | n.
    pub weight_ih: Tensor,
    /// `[1536, 512]`, rows r | z | n.
    pub weight_hh: Tensor,
    /// `[1536]`.
    pub bias_ih: Tensor,
    /// `[1536]`.
    pub bias_hh: Tensor,
}

impl GruParams {
    /// Fetch (or create, for a training `VarMap`) the tensors named `names`.
    pub fn new(vb: &VarBuilder, names: &GruNames) -> Result<Self> {
        let get =
            |shape: &[usize], name: &str| vb.get_with_hints(shape.to_vec(), name, init_for(name));
        Ok(Self {
            weight_ih: get(&[GATES, EMBED_DIM], &names.weight_ih)?,
            weight_hh: get(&[GATES, HIDDEN], &names.weight_hh)?,
            bias_ih: get(&[GATES], &names.bias_ih)?,
            bias_hh: get(&[GATES], &names.bias_hh)?,
        })
    }
}

/// How the recurrence is computed; both give the same values and gradients.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum GruImpl {
    /// One custom candle op with a hand-written backward pass (CPU, f32;
    /// other devices or dtypes fall back to [`GruImpl::Autograd`]).
    #[default]
    Fused,
    /// Plain candle ops per time step, differentiated by candle (slow; the
    /// transparent definition the fused op is tested against).
    Autograd,
}

/// Result of running a GRU pair over a sequence.
pub(crate) struct PairRun {
    /// States after the last step, `(2, B, 512)`: `[a, b]`.
    pub last: Tensor,
    /// Every step's states `(T, 2, B, 512)` when requested. For a reversed
    /// `b`, index `t` holds `b`'s state after it consumed frame `T-1-t`.
    pub all: Option<Tensor>,
}

/// Input pre-activations for both directions, `(T, 2, B, 1536)`, with `b`'s
/// time axis reversed when `reverse_b`.
pub(crate) fn input_projection(
    a: &GruParams,
    b: &GruParams,
    e: &Tensor,
    reverse_b: bool,
) -> Result<Tensor> {
    let (batch, steps, width) = e.dims3()?;
    let w = Tensor::cat(&[&a.weight_ih, &b.weight_ih], 0)?; // (3072, 256)
    let bias = Tensor::cat(&[&a.bias_ih, &b.bias_ih], 0)?;
    let gi = e
        .reshape((batch * steps, width))?
        .matmul(&w.t()?)?
        .broadcast_add(&bias)?
        .reshape((batch, steps, 2, GATES))?
        .permute((1, 2, 0, 3))?
        .contiguous()?; // (T, 2, B, 1536)
    if !reverse_b {
        return Ok(gi);
    }
    let rev: Vec<u32> = (0..steps as u32).rev().collect();
    let rev = Tensor::new(rev.as_slice(), e.device())?;
    let fwd = gi.narrow(1, 0, 1)?;
    let bwd = gi.narrow(1, 1, 1)?.contiguous()?.index_select(&rev, 0)?;
    Tensor::cat(&[&fwd, &bwd], 1)
}

/// Run GRUs `a` and `b` from zero state over the embedded sequence `e`
/// (`(B, T, 256)`); `b` reads it backwards when `reverse_b`.
pub(crate) fn run_pair(
    a: &GruParams,
    b: &GruParams,
    e: &Tensor,
    reverse_b: bool,
    keep_all: bool,
    imp: GruImpl,
) -> Result<PairRun> {
    let (batch, steps, _) = e.dims3()?;
    let gi = input_projection(a, b, e, reverse_b)?;
    if imp == GruImpl::Fused && e.device().is_cpu() && e.dtype() == DType::F32 {
        let gi = gi.contiguous()?;
        let w = Tensor::stack(&[&a.weight_hh, &b.weight_hh], 0)?.contiguous()?;
        let bias = Tensor::stack(&[&a.bias_hh, &b.bias_hh], 0)?.contiguous()?;
        let save = gi.track_op() || w.track_op() || bias.track_op();
        let all = gi.apply_op3(&w, &bias, super::fused::GruPairSeq::new(save))?;
        return Ok(PairRun {
            last: all.get(steps - 1)?,
            all: keep_all.then_some(all),
        });
    }
    let rec = Recurrent::new(a, b)?;
    // per-gate contiguous input pre-activations, so every step's element-wise
    // ops run on contiguous tensors (candle's strided paths are slow)
    let gi = split_gates(&gi)?;
    let mut h = Tensor::zeros((2, batch, HIDDEN), e.dtype(), e.device())?;
    let mut all = Vec::with_capacity(if keep_all { steps } else { 0 });
    for t in 0..steps {
        h = rec.cell([&gi[0].get(t)?, &gi[1].get(t)?, &gi[2].get(t)?], &h)?;
        if keep_all {
            all.push(h.clone());
        }
    }
    let all = if keep_all {
        Some(Tensor::stack(&all, 0)?)
    } else {
        None
    };
    Ok(PairRun { last: h, all })
}

/// The r, z, n blocks of the last dimension (1536) of `g`, each contiguous.
pub(crate) fn split_gates(g: &Tensor) -> Result<[Tensor; 3]> {
    let part = |i: usize| g.narrow(D::Minus1, i * HIDDEN, HIDDEN)?.contiguous();
    Ok([part(0)?, part(1)?, part(2)?])
}

/// The recurrent weights of both directions, per gate: `W_h·ᵀ` `(2, 512,
/// 512)` and `b_h·` `(2, 1, 512)`.
pub(crate) struct Recurrent {
    w_t: [Tensor; 3],
    b: [Tensor; 3],
}

impl Recurrent {
    pub(crate) fn new(a: &GruParams, b: &GruParams) -> Result<Self> {
        let w_t = Tensor::stack(&[&a.weight_hh, &b.weight_hh], 0)?.transpose(1, 2)?; // (2, 512, 1536)
        let bias = Tensor::stack(&[&a.bias_hh, &b.bias_hh], 0)?.unsqueeze(1)?; // (2, 1, 1536)
        let [wr, wz, wn] = split_gates(&w_t)?;
        let [br, bz, bn] = split_gates(&bias)?;
        Ok(Self {
            w_t: [wr, wz, wn],
            b: [br, bz, bn],
        })
    }

    /// One step of both directions: input pre-activations per gate
    /// `(2, B, 512)` (including `b_ih`), states `h` `(2, B, 512)` -> new states.
    pub(crate) fn cell(&self, gi: [&Tensor; 3], h: &Tensor) -> Result<Tensor> {
        let gh = |g: usize| h.matmul(&self.w_t[g])?.broadcast_add(&self.b[g]);
        let r = candle_nn::ops::sigmoid(&(gi[0] + gh(0)?)?)?;
        let z = candle_nn::ops::sigmoid(&(gi[1] + gh(1)?)?)?;
        let n = (gi[2] + r.mul(&gh(2)?)?)?.tanh()?;
        &n + z.mul(&(h - &n)?)?
    }
}

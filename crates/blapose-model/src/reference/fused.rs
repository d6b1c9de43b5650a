//! The GRU recurrence as one candle op with a hand-written backward pass.
//!
//! Built from plain candle ops (see `gru.rs`), a training step creates a
//! dozen autograd nodes per frame and candle's generic backward of `narrow`,
//! broadcasting and element-wise ops spends most of its time allocating and
//! copying: 64x64 frames trained at ~440 frames/s. This op runs the whole
//! recurrence of both directions over all frames in one node:
//!
//! * forward: per frame the serving kernel (`crate::fast::kernel`: `h ·
//!   W_hhᵀ` with the gate math fused into its epilogue) per direction; the
//!   two directions are independent and run on two threads. The gate
//!   activations `r, z, n, W_hn h + b_hn` are kept for the backward pass
//!   (only when a gradient can flow).
//! * backward (back-propagation through time): per frame one GEMM
//!   `dgh · W_hh` per direction for the state gradient; the weight
//!   gradient is a single large GEMM `dGHᵀ · H_prev` over all frames after
//!   the loop, and the bias gradient a column sum.
//!
//! Inputs: `gi` `(T, 2, B, 1536)` input pre-activations (`W_ih x + b_ih`,
//! computed by candle so their gradient flows on to `W_ih` and the
//! embedding), `w_hh` `(2, 1536, 512)`, `b_hh` `(2, 1536)`. Output: every
//! state `(T, 2, B, 512)` from a zero initial state. The math is PyTorch's
//! GRU, identical to `gru::cell` (tested against it, values and gradients).

use std::sync::Mutex;

use candle_core::{bail, CpuStorage, CustomOp3, DType, Layout, Result, Shape, Tensor};

use crate::fast::kernel::{self, TileArgs};
use crate::fast::linalg::matmul_t;
use crate::fast::pack::{PackedGru, LANES, PANELS};
use crate::fast::{Isa, Precision};
use crate::{GATES, HIDDEN};

/// Per direction, per frame and row: `[r | z | n | W_hn h + b_hn]`.
const SAVED: usize = 4 * HIDDEN;

/// The op; one instance per forward call (it owns that call's saved gates).
pub(crate) struct GruPairSeq {
    isa: Isa,
    save: bool,
    saved: Mutex<Option<[Vec<f32>; 2]>>,
}

impl GruPairSeq {
    /// `save`: keep gate activations for a backward pass.
    pub(crate) fn new(save: bool) -> Self {
        Self {
            isa: Isa::detect(),
            save,
            saved: Mutex::new(None),
        }
    }
}

/// Problem sizes of one call.
#[derive(Clone, Copy)]
struct Dims {
    steps: usize,
    batch: usize,
}

/// GEMM threads per direction when the two directions run concurrently.
fn threads_per_direction() -> usize {
    (rayon::current_num_threads() / 2).max(1)
}

fn contiguous_f32<'a>(s: &'a CpuStorage, l: &Layout, what: &str) -> Result<&'a [f32]> {
    let Some((start, end)) = l.contiguous_offsets() else {
        bail!("{what} must be contiguous");
    };
    Ok(&s.as_slice::<f32>()?[start..end])
}

/// Forward of direction `d`: all states `(T, B, 512)` and, if `save`, the
/// gate activations `(T, B, 2048)`. Runs the serving kernel (fused gates,
/// weights packed once per call) with the input pre-activations `gi`.
fn forward_direction(
    isa: Isa,
    dims: Dims,
    d: usize,
    gi: &[f32],
    w: &[f32],
    b: &[f32],
    save: bool,
) -> (Vec<f32>, Option<Vec<f32>>) {
    let Dims { steps, batch } = dims;
    let packed = PackedGru::new(None, w, b, Precision::F32);
    let mut states = vec![0.0f32; steps * batch * HIDDEN];
    let mut saved = save.then(|| vec![0.0f32; steps * batch * SAVED]);
    let zeros = vec![0.0f32; batch * HIDDEN];
    let mut x = vec![0.0f32; batch * HIDDEN];
    for t in 0..steps {
        let (done, rest) = states.split_at_mut(t * batch * HIDDEN);
        let h_prev: &[f32] = if t == 0 {
            &zeros
        } else {
            &done[(t - 1) * batch * HIDDEN..]
        };
        let h = &mut rest[..batch * HIDDEN];
        kernel::pack_rows(
            isa,
            batch,
            0,
            |_| &[],
            |row| &h_prev[row * HIDDEN..(row + 1) * HIDDEN],
            &mut x,
        );
        let gi_t = &gi[(t * 2 + d) * batch * GATES..(t * 2 + d + 1) * batch * GATES];
        let save_t = saved.as_mut().map_or(std::ptr::null_mut(), |s| {
            s[t * batch * SAVED..].as_mut_ptr()
        });
        for p in 0..PANELS {
            let args = TileArgs {
                w: packed.panel_ptr(p),
                half: false,
                k_in: 0,
                bias: packed.bias(p).as_ptr(),
                x: x.as_ptr(),
                h: h_prev.as_ptr(),
                h_stride: HIDDEN,
                unit0: p * LANES,
                pre: gi_t.as_ptr(),
                pre_stride: GATES,
                out: h[p * LANES..].as_mut_ptr(),
                out_stride: HIDDEN,
                save: save_t,
                save_stride: SAVED,
                fc: std::ptr::null(),
                y: std::ptr::null_mut(),
                y_stride: 0,
            };
            // SAFETY: `batch` rows each: `x` packed from `h_prev` by
            // `pack_rows` for `isa`, `h_prev`/`h` rows of 512, `gi_t` rows of
            // 1536, `save_t` (if any) rows of 2048 inside `saved[t]`; the
            // panel and biases come from `PackedGru` (k_in = 0); `isa` is
            // what `Isa::detect` found.
            unsafe { kernel::run(isa, batch, &args) };
        }
    }
    (states, saved)
}

/// Gradients of direction `d`: `(d gi (T, B, 1536), d W_hh, d b_hh)`.
fn backward_direction(
    dims: Dims,
    states: &[f32],
    saved: &[f32],
    d_states: &[f32],
    w: &[f32],
) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
    let Dims { steps, batch } = dims;
    let threads = threads_per_direction();
    let rows = steps * batch;
    let mut d_gi = vec![0.0f32; rows * GATES];
    let mut d_gh = vec![0.0f32; rows * GATES];
    let mut dh = vec![0.0f32; batch * HIDDEN];
    let mut dh_prev = vec![0.0f32; batch * HIDDEN];
    let zeros = vec![0.0f32; batch * HIDDEN];
    for t in (0..steps).rev() {
        for (v, g) in dh
            .iter_mut()
            .zip(&d_states[t * batch * HIDDEN..(t + 1) * batch * HIDDEN])
        {
            *v += g;
        }
        let h_prev: &[f32] = if t == 0 {
            &zeros
        } else {
            &states[(t - 1) * batch * HIDDEN..t * batch * HIDDEN]
        };
        for row in 0..batch {
            let at = t * batch + row;
            let s = &saved[at * SAVED..(at + 1) * SAVED];
            let (r, z, n, ghn) = (
                &s[..HIDDEN],
                &s[HIDDEN..2 * HIDDEN],
                &s[2 * HIDDEN..3 * HIDDEN],
                &s[3 * HIDDEN..],
            );
            let dh_r = &dh[row * HIDDEN..(row + 1) * HIDDEN];
            let hp = &h_prev[row * HIDDEN..(row + 1) * HIDDEN];
            let dhp = &mut dh_prev[row * HIDDEN..(row + 1) * HIDDEN];
            let (gi_row, gh_row) = (
                &mut d_gi[at * GATES..(at + 1) * GATES],
                &mut d_gh[at * GATES..(at + 1) * GATES],
            );
            for j in 0..HIDDEN {
                let dn = dh_r[j] * (1.0 - z[j]);
                let dz = dh_r[j] * (hp[j] - n[j]);
                dhp[j] = dh_r[j] * z[j];
                let dan = dn * (1.0 - n[j] * n[j]);
                let dar = dan * ghn[j] * r[j] * (1.0 - r[j]);
                let daz = dz * z[j] * (1.0 - z[j]);
                gi_row[j] = dar;
                gi_row[HIDDEN + j] = daz;
                gi_row[2 * HIDDEN + j] = dan;
                gh_row[j] = dar;
                gh_row[HIDDEN + j] = daz;
                gh_row[2 * HIDDEN + j] = dan * r[j];
            }
        }
        // dh_{t-1} = dh ⊙ z + dgh · W_hh
        matmul_t(
            &mut dh_prev,
            (&d_gh[t * batch * GATES..(t + 1) * batch * GATES], false),
            (w, false),
            (batch, GATES, HIDDEN),
            true,
            threads,
        );
        std::mem::swap(&mut dh, &mut dh_prev);
    }
    // dW_hh = dGHᵀ · H_prev over all frames; H_prev is the states shifted by one frame
    let mut h_prev_all = vec![0.0f32; rows * HIDDEN];
    h_prev_all[batch * HIDDEN..].copy_from_slice(&states[..(steps - 1) * batch * HIDDEN]);
    let mut d_w = vec![0.0f32; GATES * HIDDEN];
    matmul_t(
        &mut d_w,
        (&d_gh, true),
        (&h_prev_all, false),
        (GATES, rows, HIDDEN),
        false,
        threads,
    );
    let mut d_b = vec![0.0f32; GATES];
    for row in d_gh.chunks_exact(GATES) {
        for (acc, v) in d_b.iter_mut().zip(row) {
            *acc += v;
        }
    }
    (d_gi, d_w, d_b)
}

impl GruPairSeq {
    fn dims(gi: &Layout, w: &Layout, b: &Layout) -> Result<Dims> {
        let (steps, two, batch, gates) = gi.shape().dims4()?;
        if two != 2 || gates != GATES || steps == 0 {
            bail!("gi must be (T>0, 2, B, {GATES}), got {:?}", gi.shape());
        }
        if w.shape().dims() != [2, GATES, HIDDEN] || b.shape().dims() != [2, GATES] {
            bail!("w_hh/b_hh must be (2, {GATES}, {HIDDEN})/(2, {GATES})");
        }
        Ok(Dims { steps, batch })
    }

    /// Both directions' forward; `(states (T, 2, B, 512), saved gates)`.
    fn run_forward(
        &self,
        dims: Dims,
        gi: &[f32],
        w: &[f32],
        b: &[f32],
        save: bool,
    ) -> (Vec<f32>, [Option<Vec<f32>>; 2]) {
        let w_of = |d: usize| &w[d * GATES * HIDDEN..(d + 1) * GATES * HIDDEN];
        let b_of = |d: usize| &b[d * GATES..(d + 1) * GATES];
        let ((s0, g0), (s1, g1)) = rayon::join(
            || forward_direction(self.isa, dims, 0, gi, w_of(0), b_of(0), save),
            || forward_direction(self.isa, dims, 1, gi, w_of(1), b_of(1), save),
        );
        let Dims { steps, batch } = dims;
        let block = batch * HIDDEN;
        let mut out = vec![0.0f32; steps * 2 * block];
        for t in 0..steps {
            out[(2 * t) * block..(2 * t + 1) * block]
                .copy_from_slice(&s0[t * block..(t + 1) * block]);
            out[(2 * t + 1) * block..(2 * t + 2) * block]
                .copy_from_slice(&s1[t * block..(t + 1) * block]);
        }
        (out, [g0, g1])
    }
}

impl CustomOp3 for GruPairSeq {
    fn name(&self) -> &'static str {
        "blapose-gru-pair-sequence"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let dims = Self::dims(l1, l2, l3)?;
        let gi = contiguous_f32(s1, l1, "gi")?;
        let w = contiguous_f32(s2, l2, "w_hh")?;
        let b = contiguous_f32(s3, l3, "b_hh")?;
        let (out, [g0, g1]) = self.run_forward(dims, gi, w, b, self.save);
        if let (Some(g0), Some(g1)) = (g0, g1) {
            match self.saved.lock() {
                Ok(mut slot) => *slot = Some([g0, g1]),
                Err(_) => bail!("saved-gates lock poisoned"),
            }
        }
        let shape = Shape::from((dims.steps, 2, dims.batch, HIDDEN));
        Ok((CpuStorage::F32(out), shape))
    }

    fn bwd(
        &self,
        gi: &Tensor,
        w: &Tensor,
        b: &Tensor,
        res: &Tensor,
        grad_res: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let dims = Self::dims(gi.layout(), w.layout(), b.layout())?;
        let Dims { steps, batch } = dims;
        let flat = |t: &Tensor| -> Result<Vec<f32>> {
            t.to_dtype(DType::F32)?
                .contiguous()?
                .flatten_all()?
                .to_vec1::<f32>()
        };
        let w_v = flat(w)?;
        let taken = match self.saved.lock() {
            Ok(mut slot) => slot.take(),
            Err(_) => bail!("saved-gates lock poisoned"),
        };
        let saved = match taken {
            Some(s) => s,
            None => {
                // forward ran without saving (or backward runs twice): recompute
                let (_, [g0, g1]) = self.run_forward(dims, &flat(gi)?, &w_v, &flat(b)?, true);
                match (g0, g1) {
                    (Some(g0), Some(g1)) => [g0, g1],
                    _ => bail!("recomputing GRU gates failed"),
                }
            }
        };
        let states = flat(res)?;
        let d_states = flat(grad_res)?;
        let block = batch * HIDDEN;
        let split = |all: &[f32], d: usize| -> Vec<f32> {
            (0..steps)
                .flat_map(|t| {
                    all[(2 * t + d) * block..(2 * t + d + 1) * block]
                        .iter()
                        .copied()
                })
                .collect()
        };
        let dir = |d: usize| {
            backward_direction(
                dims,
                &split(&states, d),
                &saved[d],
                &split(&d_states, d),
                &w_v[d * GATES * HIDDEN..(d + 1) * GATES * HIDDEN],
            )
        };
        let ((gi0, w0, b0), (gi1, w1, b1)) = rayon::join(|| dir(0), || dir(1));
        let gblock = batch * GATES;
        let mut d_gi = vec![0.0f32; steps * 2 * gblock];
        for t in 0..steps {
            d_gi[2 * t * gblock..(2 * t + 1) * gblock]
                .copy_from_slice(&gi0[t * gblock..(t + 1) * gblock]);
            d_gi[(2 * t + 1) * gblock..(2 * t + 2) * gblock]
                .copy_from_slice(&gi1[t * gblock..(t + 1) * gblock]);
        }
        let dev = gi.device();
        let d_gi = Tensor::from_vec(d_gi, (steps, 2, batch, GATES), dev)?.to_dtype(gi.dtype())?;
        let d_w =
            Tensor::from_vec([w0, w1].concat(), (2, GATES, HIDDEN), dev)?.to_dtype(w.dtype())?;
        let d_b = Tensor::from_vec([b0, b1].concat(), (2, GATES), dev)?.to_dtype(b.dtype())?;
        Ok((Some(d_gi), Some(d_w), Some(d_b)))
    }
}

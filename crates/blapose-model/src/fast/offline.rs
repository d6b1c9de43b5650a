//! The offline Bi-GRU over a whole sequence.
//!
//! Offline prediction sees all frames at once, so everything that does not
//! depend on the recurrent state is batched: the embedding of all frames is
//! one GEMM, and each direction's input projection `W_ih e + b_ih` is a
//! GEMM per chunk of frames (chunks keep the buffer small and hot in cache
//! instead of materializing 6 KB per frame for the whole sequence). Only the
//! recurrent `W_hh h` product remains sequential; it runs the same fused
//! panel kernel as the online step with the projection supplied as
//! pre-activations. The forward and backward directions are independent
//! until the final concatenation, so with two threads each runs on its own
//! core without any synchronization per frame.
//!
//! With [`crate::fast::Precision::Bf16`] the recurrent panels are bf16 and
//! each frame's state is rounded to bf16 for the product, which runs on
//! `vdpbf16ps` (one row: an AMX tile would be 1/16 used); the input
//! projection stays the f32 GEMM.

use super::kernel::{self, TileArgs};
use super::linalg::matmul;
use super::pack::{PackedEmbed, PackedGru, PackedHead, LANES, PANELS};
use super::{build_pool, check_finite, Bf16Unit, EngineOptions, Isa};
use crate::names::{GruNames, EMBED_BIAS, EMBED_WEIGHT, FC_WEIGHT};
use crate::{
    LoadedWeights, ModelError, ModelKind, EMBED_DIM, GATES, HIDDEN, INPUT_DIM, OUTPUT_DIM,
};

/// Frames per input-projection GEMM.
const CHUNK: usize = 256;

/// The fast offline (bidirectional GRU) model.
pub struct OfflineBiGruEngine {
    isa: Isa,
    /// Whether the recurrent panels are bf16 (run on `vdpbf16ps`).
    bf16: bool,
    threads: usize,
    pool: Option<rayon::ThreadPool>,
    embed: PackedEmbed,
    /// Per direction: `W_ih^T`, `[256][1536]`.
    proj: [Vec<f32>; 2],
    /// Per direction: `b_ih`.
    proj_bias: [Vec<f32>; 2],
    grus: [PackedGru; 2],
    head: PackedHead,
}

impl std::fmt::Debug for OfflineBiGruEngine {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("OfflineBiGruEngine")
            .field("isa", &self.isa)
            .field("threads", &self.threads)
            .finish_non_exhaustive()
    }
}

impl OfflineBiGruEngine {
    /// Build from offline (`bigru`) weights; `threads >= 2` runs the two
    /// directions in parallel. f32 weights, best instruction set of this CPU.
    pub fn new(weights: &LoadedWeights, threads: usize) -> Result<Self, ModelError> {
        Self::with_options(weights, EngineOptions::threads(threads))
    }

    /// As [`Self::new`] with an explicit instruction set.
    pub fn with_isa(weights: &LoadedWeights, threads: usize, isa: Isa) -> Result<Self, ModelError> {
        Self::with_options(
            weights,
            EngineOptions {
                isa: Some(isa),
                ..EngineOptions::threads(threads)
            },
        )
    }

    /// Build with explicit [`EngineOptions`] (the precision applies to the
    /// recurrent weights; the batched input projection stays f32).
    pub fn with_options(weights: &LoadedWeights, opts: EngineOptions) -> Result<Self, ModelError> {
        crate::expect_kind(ModelKind::BiGru, weights.kind())?;
        let isa = opts.resolved_isa()?;
        let bf16 = opts.resolved_bf16(isa)?.is_some();
        let threads = opts.threads;
        let names = GruNames::for_kind(ModelKind::BiGru);
        let mut proj = [Vec::new(), Vec::new()];
        let mut proj_bias = [Vec::new(), Vec::new()];
        let mut grus = Vec::with_capacity(2);
        for (d, n) in names.iter().enumerate() {
            let w_ih = weights.values(&n.weight_ih)?;
            let b_ih = weights.values(&n.bias_ih)?;
            let mut wt = vec![0.0; EMBED_DIM * GATES];
            for row in 0..GATES {
                for k in 0..EMBED_DIM {
                    wt[k * GATES + row] = w_ih[row * EMBED_DIM + k];
                }
            }
            proj[d] = wt;
            proj_bias[d] = b_ih;
            grus.push(PackedGru::new(
                None,
                &weights.values(&n.weight_hh)?,
                &weights.values(&n.bias_hh)?,
                opts.precision,
            ));
        }
        let [fwd, bwd]: [PackedGru; 2] = grus
            .try_into()
            .map_err(|_| ModelError::Config("expected two GRU directions".into()))?;
        Ok(Self {
            isa,
            bf16,
            threads: threads.max(1),
            pool: build_pool(threads, "blapose-offline")?,
            embed: PackedEmbed::new(&weights.values(EMBED_WEIGHT)?, &weights.values(EMBED_BIAS)?),
            proj,
            proj_bias,
            grus: [fwd, bwd],
            head: PackedHead::new(&weights.values(FC_WEIGHT)?),
        })
    }

    /// The instruction set in use.
    pub fn isa(&self) -> Isa {
        self.isa
    }

    /// The 16 (pair-averaged) bone lengths of the person in `frames`
    /// (`T x 34` normalized keypoints, `T >= 1`).
    pub fn predict(&self, frames: &[f32]) -> Result<[f32; OUTPUT_DIM], ModelError> {
        if frames.is_empty() {
            return Err(ModelError::EmptySequence);
        }
        if !frames.len().is_multiple_of(INPUT_DIM) {
            return Err(ModelError::BadLength {
                what: "frames (T x 34)",
                expected: frames.len().div_ceil(INPUT_DIM) * INPUT_DIM,
                found: frames.len(),
            });
        }
        check_finite(frames, INPUT_DIM)?;
        let run = || {
            let steps = frames.len() / INPUT_DIM;
            let (wt, b) = self.embed.parts();
            let mut embedded = vec![0.0; steps * EMBED_DIM];
            matmul(
                &mut embedded,
                frames,
                wt,
                (steps, INPUT_DIM, EMBED_DIM),
                false,
                self.threads,
            );
            for row in embedded.chunks_exact_mut(EMBED_DIM) {
                for (v, bias) in row.iter_mut().zip(b) {
                    *v = (*v + bias).max(0.0);
                }
            }
            if self.threads > 1 {
                rayon::join(
                    || self.direction(1, &embedded),
                    || self.direction(0, &embedded),
                )
            } else {
                (self.direction(1, &embedded), self.direction(0, &embedded))
            }
        };
        let (h_bwd, h_fwd) = match &self.pool {
            Some(pool) => pool.install(run),
            None => run(),
        };
        // backward final state first, as in the reference model
        let features: Vec<f32> = h_bwd
            .iter()
            .chain(&h_fwd)
            .map(|&h| super::math::scalar::sigmoid(h))
            .collect();
        let y = self.head.apply(&features);
        if y.iter().any(|v| !v.is_finite()) {
            return Err(ModelError::NonFiniteState { row: 0 });
        }
        Ok(y)
    }

    /// Final state of direction `d` (0 forward, 1 backward) over `embedded`
    /// (`T x 256`).
    fn direction(&self, d: usize, embedded: &[f32]) -> Vec<f32> {
        let steps = embedded.len() / EMBED_DIM;
        let gru = &self.grus[d];
        let mut pre = vec![0.0; CHUNK * GATES];
        let mut h = vec![0.0f32; HIDDEN];
        let mut h_next = vec![0.0f32; HIDDEN];
        let mut h16 = vec![0u16; if self.bf16 { HIDDEN } else { 0 }];
        let chunks = steps.div_ceil(CHUNK);
        let mut reverse = false;
        for c in 0..chunks {
            // the backward direction walks the chunks, and frames, from the end
            let c = if d == 0 { c } else { chunks - 1 - c };
            let start = c * CHUNK;
            let n = CHUNK.min(steps - start);
            let pre = &mut pre[..n * GATES];
            matmul(
                pre,
                &embedded[start * EMBED_DIM..(start + n) * EMBED_DIM],
                &self.proj[d],
                (n, EMBED_DIM, GATES),
                false,
                1,
            );
            for row in pre.chunks_exact_mut(GATES) {
                for (v, b) in row.iter_mut().zip(&self.proj_bias[d]) {
                    *v += b;
                }
            }
            for s in 0..n {
                let t = if d == 0 { s } else { n - 1 - s };
                let pre_t = &pre[t * GATES..(t + 1) * GATES];
                reverse = !reverse;
                #[cfg(target_arch = "x86_64")]
                if self.bf16 {
                    // SAFETY: `resolved_bf16` confirmed AVX512-BF16.
                    unsafe { kernel::bf16::pack_rows(1, 0, |_| &[][..], |_| &h[..], &mut h16) };
                }
                let mut run_panel = |p: usize| {
                    let args = TileArgs {
                        w: gru.panel_ptr(p),
                        half: gru.is_half(),
                        k_in: 0,
                        bias: gru.bias(p).as_ptr(),
                        x: h.as_ptr(),
                        h: h.as_ptr(),
                        h_stride: HIDDEN,
                        unit0: p * LANES,
                        pre: pre_t.as_ptr(),
                        pre_stride: GATES,
                        out: h_next[p * LANES..].as_mut_ptr(),
                        out_stride: HIDDEN,
                        save: std::ptr::null_mut(),
                        save_stride: 0,
                        fc: std::ptr::null(),
                        y: std::ptr::null_mut(),
                        y_stride: 0,
                    };
                    // SAFETY: one row: `h` holds 512 floats (for one row and
                    // k_in = 0 it is its own packed form), `pre_t` holds the
                    // 1536 pre-activations of this frame, `out`
                    // has 16 floats from `p * 16`; the panel holds
                    // `512 * 48` aligned floats (k_in = 0); no output layer.
                    // bf16: the panel is a paired bf16 one, `h16` the 512
                    // bf16 inputs of the one row, AVX512-BF16 confirmed.
                    unsafe {
                        if self.bf16 {
                            kernel::run_bf16(Bf16Unit::Avx512Bf16, 1, &args, h16.as_ptr(), HIDDEN);
                        } else {
                            kernel::run(self.isa, 1, &args);
                        }
                    }
                };
                if reverse {
                    (0..PANELS).rev().for_each(&mut run_panel);
                } else {
                    (0..PANELS).for_each(&mut run_panel);
                }
                std::mem::swap(&mut h, &mut h_next);
            }
        }
        h
    }
}

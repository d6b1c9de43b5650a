//! The training hot loop: both bone-length networks with a hand-written
//! backward pass (BPTT) on plain `f32` buffers and GEMMs (blapose-model's
//! `fast::linalg`, the one wrapper of the `gemm` crate).
//!
//! Why not candle autograd: the reference models in `blapose-model` build a
//! graph of ~15 small ops per time step; on this 2-core CPU a training step
//! of 32 x 64 frames took ~3 s (about 630 frames/s), dominated by op
//! overhead, allocations and the zero-padded gradients of `narrow`. Here each
//! GRU direction is one time loop over preallocated buffers: per step one
//! `(B x 512) x (512 x 1536)` GEMM and fused gate math forwards, one
//! `(B x 1536) x (1536 x 512)` GEMM backwards; everything that does not
//! depend on the recurrence (input projections, weight gradients) is one big
//! GEMM over all frames. The two GRU directions are independent given the
//! embedding, so they run on the two cores in parallel (`rayon::join`).
//!
//! Semantics are exactly the reference models' (same tensors, PyTorch gate
//! order r, z, n, backward state first for the Bi-GRU, sigmoid -> fc ->
//! symmetric averaging); `tests/integration/fastnet_matches_candle.rs` checks the outputs
//! and every gradient against candle autograd on the reference model.
//!
//! Dropout masks are drawn from an RNG the caller seeds, so a training run is
//! reproducible bit for bit for a given thread count.

use std::collections::HashMap;

use blapose_core::skeleton::NUM_BONES;
use blapose_model::fast::linalg::matmul_t;
use blapose_model::symmetry::averaging_matrix;
use blapose_model::{ModelKind, DROPOUT, EMBED_DIM, FEATURES, HIDDEN, INPUT_DIM};
use candle_core::{Device, Tensor};
use rand::Rng;

use crate::error::TrainError;

mod gru;
mod layout;

use gru::{sigmoid, GruCache};
pub use layout::{GruLayout, Layout};

/// Which loss a training step minimizes.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LossConfig {
    /// Weight of the L1 loss on the running mean of per-frame predictions
    /// (online GRU only; 0 = off). The final-state L1 always has weight 1.
    pub running_mean_weight: f32,
    /// Dropout probability after the embedding (0 = off).
    pub dropout: f32,
}

impl Default for LossConfig {
    fn default() -> Self {
        Self {
            running_mean_weight: 0.0,
            dropout: DROPOUT,
        }
    }
}

/// The network with a flat parameter vector.
#[derive(Debug, Clone)]
pub struct FastNet {
    /// Tensor placement.
    pub layout: Layout,
    /// All parameters.
    pub params: Vec<f32>,
    sym: [[f32; NUM_BONES]; NUM_BONES],
}

/// Result of [`FastNet::train_step`].
#[derive(Debug, Clone, PartialEq)]
pub struct StepResult {
    /// The minimized loss (metres).
    pub loss: f64,
    /// The final-state L1 alone (metres).
    pub final_l1: f64,
}

impl FastNet {
    /// A network of `kind` from named tensors (e.g.
    /// [`blapose_model::LoadedWeights::tensors`]).
    pub fn from_tensors(
        kind: ModelKind,
        tensors: &HashMap<String, Tensor>,
    ) -> Result<Self, TrainError> {
        let layout = Layout::new(kind);
        let mut params = vec![0.0f32; layout.len];
        for (name, range, shape) in layout.tensors() {
            let t = tensors
                .get(&name)
                .ok_or_else(|| TrainError::Data(format!("missing tensor {name}")))?;
            if t.dims() != shape.as_slice() {
                return Err(TrainError::Data(format!(
                    "tensor {name} has shape {:?}, expected {shape:?}",
                    t.dims()
                )));
            }
            let v: Vec<f32> = t.flatten_all()?.to_vec1()?;
            params[range].copy_from_slice(&v);
        }
        Ok(Self {
            layout,
            params,
            sym: averaging_matrix(),
        })
    }

    /// Start the output layer at `mean` lengths: with the fresh GRU states
    /// near zero every sigmoid feature is about 0.5, so setting each output
    /// row to `mean / 512` plus `noise` times its random init makes the
    /// initial prediction the mean instead of ±0.3 m of noise. The network
    /// then only has to learn deviations from the mean, which saves a long
    /// warm-up on a CPU budget (the architecture has no output bias).
    pub fn init_output_at(&mut self, mean: &[f32; NUM_BONES], noise: f32) {
        let fc = self.layout.fc_w.clone();
        let w = &mut self.params[fc];
        for (j, row) in w.chunks_exact_mut(FEATURES).enumerate() {
            for v in row.iter_mut() {
                *v = mean[j] / (0.5 * FEATURES as f32) + noise * *v;
            }
        }
    }

    /// The parameters as named tensors (for the weights file).
    pub fn to_tensors(&self) -> Result<HashMap<String, Tensor>, TrainError> {
        let mut out = HashMap::new();
        for (name, range, shape) in self.layout.tensors() {
            out.insert(
                name,
                Tensor::from_slice(&self.params[range], shape, &Device::Cpu)?,
            );
        }
        Ok(out)
    }

    /// Model kind.
    pub fn kind(&self) -> ModelKind {
        self.layout.kind
    }

    /// Final-state predictions `(B x 16)` for `x` (`B x T x 34`, batch-major),
    /// eval mode.
    pub fn predict(&self, x: &[f32], batch: usize, steps: usize) -> Vec<f32> {
        let fw = self.forward::<rand::rngs::StdRng>(x, batch, steps, None);
        let feats = self.final_features(&fw, batch, steps);
        self.head_forward(&feats, batch).1
    }

    /// Per-frame predictions `(B x T x 16)` of the online GRU, eval mode
    /// (frame `t`'s row uses the states after frame `t`).
    pub fn predict_per_frame(&self, x: &[f32], batch: usize, steps: usize) -> Vec<f32> {
        let fw = self.forward::<rand::rngs::StdRng>(x, batch, steps, None);
        let feats = self.per_frame_features(&fw, batch, steps);
        let y = self.head_forward(&feats, batch * steps).1; // rows t-major: (t, b)
        let mut out = vec![0.0f32; batch * steps * NUM_BONES];
        for t in 0..steps {
            for b in 0..batch {
                let src = (t * batch + b) * NUM_BONES;
                let dst = (b * steps + t) * NUM_BONES;
                out[dst..dst + NUM_BONES].copy_from_slice(&y[src..src + NUM_BONES]);
            }
        }
        out
    }

    /// One forward + backward pass; fills `grad` (same layout as `params`,
    /// overwritten) and returns the loss. `targets` is `B x 16`.
    #[allow(clippy::too_many_arguments)]
    pub fn train_step<R: Rng + ?Sized>(
        &self,
        x: &[f32],
        targets: &[f32],
        batch: usize,
        steps: usize,
        loss: LossConfig,
        rng: &mut R,
        grad: &mut [f32],
    ) -> StepResult {
        assert_eq!(grad.len(), self.params.len());
        assert_eq!(targets.len(), batch * NUM_BONES);
        grad.fill(0.0);
        let fw = self.forward(x, batch, steps, Some((loss.dropout, rng)));
        let per_frame = loss.running_mean_weight > 0.0 && self.kind() == ModelKind::Gru;
        let (bt, mut dh_ext_a, mut dh_ext_b);
        let mut total;
        let final_l1;
        if per_frame {
            // Per-frame head over all (t, b) rows; frame T-1 is the final prediction.
            let feats = self.per_frame_features(&fw, batch, steps);
            bt = batch * steps;
            let (act, y) = self.head_forward(&feats, bt);
            let mut dy = vec![0.0f32; bt * NUM_BONES];
            // Final-state L1.
            let last = (steps - 1) * batch;
            let mut l_final = 0.0f64;
            let scale_f = 1.0 / (batch * NUM_BONES) as f32;
            for b in 0..batch {
                for j in 0..NUM_BONES {
                    let d = y[(last + b) * NUM_BONES + j] - targets[b * NUM_BONES + j];
                    l_final += f64::from(d.abs());
                    dy[(last + b) * NUM_BONES + j] += d.signum() * scale_f;
                }
            }
            final_l1 = l_final * f64::from(scale_f);
            // Running-mean L1: rm_t = mean_{tau<=t} y_tau.
            let w = loss.running_mean_weight;
            let scale_r = w / (batch * steps * NUM_BONES) as f32;
            let mut l_run = 0.0f64;
            for b in 0..batch {
                for j in 0..NUM_BONES {
                    let mut sum = 0.0f32;
                    let mut d_rm = vec![0.0f32; steps];
                    for (t, d) in d_rm.iter_mut().enumerate() {
                        sum += y[(t * batch + b) * NUM_BONES + j];
                        let diff = sum / (t + 1) as f32 - targets[b * NUM_BONES + j];
                        l_run += f64::from(diff.abs());
                        *d = diff.signum() * scale_r / (t + 1) as f32;
                    }
                    // d y_tau = sum_{t >= tau} d_rm_t / (t + 1)  (already divided).
                    let mut acc = 0.0f32;
                    for t in (0..steps).rev() {
                        acc += d_rm[t];
                        dy[(t * batch + b) * NUM_BONES + j] += acc;
                    }
                }
            }
            total = final_l1 + l_run * f64::from(scale_r);
            let df = self.head_backward(&act, &dy, bt, grad);
            // Split dF rows (t, b) into the two GRUs' per-step state gradients.
            dh_ext_a = vec![0.0f32; steps * batch * HIDDEN];
            dh_ext_b = vec![0.0f32; steps * batch * HIDDEN];
            for row in 0..bt {
                dh_ext_a[row * HIDDEN..(row + 1) * HIDDEN]
                    .copy_from_slice(&df[row * FEATURES..row * FEATURES + HIDDEN]);
                dh_ext_b[row * HIDDEN..(row + 1) * HIDDEN]
                    .copy_from_slice(&df[row * FEATURES + HIDDEN..(row + 1) * FEATURES]);
            }
        } else {
            let feats = self.final_features(&fw, batch, steps);
            let (act, y) = self.head_forward(&feats, batch);
            let scale = 1.0 / (batch * NUM_BONES) as f32;
            let mut dy = vec![0.0f32; batch * NUM_BONES];
            let mut l = 0.0f64;
            for i in 0..batch * NUM_BONES {
                let d = y[i] - targets[i];
                l += f64::from(d.abs());
                dy[i] = d.signum() * scale;
            }
            final_l1 = l * f64::from(scale);
            total = final_l1;
            let df = self.head_backward(&act, &dy, batch, grad);
            // Only the last step gets an external gradient.
            dh_ext_a = vec![0.0f32; steps * batch * HIDDEN];
            dh_ext_b = vec![0.0f32; steps * batch * HIDDEN];
            let off = (steps - 1) * batch * HIDDEN;
            // Feature order: GRU [a, b]; Bi-GRU [b (backward), a (forward)].
            let (first, second) = match self.kind() {
                ModelKind::Gru => (&mut dh_ext_a, &mut dh_ext_b),
                ModelKind::BiGru => (&mut dh_ext_b, &mut dh_ext_a),
            };
            for b in 0..batch {
                first[off + b * HIDDEN..off + (b + 1) * HIDDEN]
                    .copy_from_slice(&df[b * FEATURES..b * FEATURES + HIDDEN]);
                second[off + b * HIDDEN..off + (b + 1) * HIDDEN]
                    .copy_from_slice(&df[b * FEATURES + HIDDEN..(b + 1) * FEATURES]);
            }
        }
        if !total.is_finite() {
            total = f64::NAN;
        }

        // BPTT through both directions in parallel.
        let reverse_b = self.kind() == ModelKind::BiGru;
        let (ga, gb) = self.split_gru_grads(grad);
        let (de_a, de_b) = rayon::join(
            || self.gru_backward(0, &fw.gru[0], &fw.e, &dh_ext_a, batch, steps, false, ga),
            || self.gru_backward(1, &fw.gru[1], &fw.e, &dh_ext_b, batch, steps, reverse_b, gb),
        );
        // Embedding backward: dE through dropout and ReLU.
        let rows = batch * steps;
        let mut de = de_a;
        for (d, o) in de.iter_mut().zip(&de_b) {
            *d += o;
        }
        for i in 0..rows * EMBED_DIM {
            de[i] *= fw.mask[i]; // dropout scale (0 or 1/(1-p)) and ReLU gate folded in
        }
        let (gw, gb_) = {
            let (w, rest) =
                grad[self.layout.embed_w.start..].split_at_mut(self.layout.embed_w.len());
            (w, &mut rest[..self.layout.embed_b.len()])
        };
        matmul_t(
            gw,
            (&de, true),
            (&fw.x, false),
            (EMBED_DIM, rows, INPUT_DIM),
            false,
            2,
        );
        for r in 0..rows {
            for (g, d) in gb_.iter_mut().zip(&de[r * EMBED_DIM..(r + 1) * EMBED_DIM]) {
                *g += d;
            }
        }
        StepResult {
            loss: total,
            final_l1,
        }
    }

    fn split_gru_grads<'a>(&self, grad: &'a mut [f32]) -> (&'a mut [f32], &'a mut [f32]) {
        let g0 = self.layout.gru[0].w_ih.start;
        let g1 = self.layout.gru[1].w_ih.start;
        let end = self.layout.gru[1].b_hh.end;
        let (_, rest) = grad.split_at_mut(g0);
        let (a, rest) = rest.split_at_mut(g1 - g0);
        let (b, _) = rest.split_at_mut(end - g1);
        (a, b)
    }

    /// Forward pass. `dropout`: `Some((p, rng))` in training.
    fn forward<R: Rng + ?Sized>(
        &self,
        x: &[f32],
        batch: usize,
        steps: usize,
        dropout: Option<(f32, &mut R)>,
    ) -> Forward {
        assert_eq!(
            x.len(),
            batch * steps * INPUT_DIM,
            "input must be B x T x 34"
        );
        let rows = batch * steps;
        // Time-major copy of the input: row t*B + b.
        let mut xt = vec![0.0f32; rows * INPUT_DIM];
        for b in 0..batch {
            for t in 0..steps {
                let src = (b * steps + t) * INPUT_DIM;
                let dst = (t * batch + b) * INPUT_DIM;
                xt[dst..dst + INPUT_DIM].copy_from_slice(&x[src..src + INPUT_DIM]);
            }
        }
        let p = &self.params;
        let mut e = vec![0.0f32; rows * EMBED_DIM];
        matmul_t(
            &mut e,
            (&xt, false),
            (&p[self.layout.embed_w.clone()], true),
            (rows, INPUT_DIM, EMBED_DIM),
            false,
            2,
        );
        let bias = &p[self.layout.embed_b.clone()];
        let mut mask = vec![1.0f32; rows * EMBED_DIM];
        let (prob, mut rng) = match dropout {
            Some((prob, rng)) if prob > 0.0 => (prob, Some(rng)),
            _ => (0.0, None),
        };
        let keep_scale = 1.0 / (1.0 - prob);
        for i in 0..rows * EMBED_DIM {
            let v = e[i] + bias[i % EMBED_DIM];
            let drop = match rng.as_deref_mut() {
                Some(r) => {
                    if r.random::<f32>() < prob {
                        0.0
                    } else {
                        keep_scale
                    }
                }
                None => 1.0,
            };
            // e = dropout(relu(v)); de/dv = relu gate * dropout scale.
            mask[i] = if v > 0.0 { drop } else { 0.0 };
            e[i] = v.max(0.0) * drop;
        }
        let reverse_b = self.kind() == ModelKind::BiGru;
        let (ca, cb) = rayon::join(
            || self.gru_forward(0, &e, batch, steps, false),
            || self.gru_forward(1, &e, batch, steps, reverse_b),
        );
        Forward {
            x: xt,
            e,
            mask,
            gru: [ca, cb],
        }
    }

    /// Final features `[B, 1024]`: GRU `[a, b]`, Bi-GRU `[b (backward), a]`.
    fn final_features(&self, fw: &Forward, batch: usize, steps: usize) -> Vec<f32> {
        let bh = batch * HIDDEN;
        let la = &fw.gru[0].hs[steps * bh..];
        let lb = &fw.gru[1].hs[steps * bh..];
        let (first, second) = match self.kind() {
            ModelKind::Gru => (la, lb),
            ModelKind::BiGru => (lb, la),
        };
        let mut f = vec![0.0f32; batch * FEATURES];
        for b in 0..batch {
            f[b * FEATURES..b * FEATURES + HIDDEN]
                .copy_from_slice(&first[b * HIDDEN..(b + 1) * HIDDEN]);
            f[b * FEATURES + HIDDEN..(b + 1) * FEATURES]
                .copy_from_slice(&second[b * HIDDEN..(b + 1) * HIDDEN]);
        }
        f
    }

    /// Per-frame features `[T*B, 1024]` (rows `(t, b)`), states after each step.
    fn per_frame_features(&self, fw: &Forward, batch: usize, steps: usize) -> Vec<f32> {
        let rows = batch * steps;
        let bh = batch * HIDDEN;
        let mut f = vec![0.0f32; rows * FEATURES];
        for row in 0..rows {
            let a = &fw.gru[0].hs[bh + row * HIDDEN..bh + (row + 1) * HIDDEN];
            let b = &fw.gru[1].hs[bh + row * HIDDEN..bh + (row + 1) * HIDDEN];
            f[row * FEATURES..row * FEATURES + HIDDEN].copy_from_slice(a);
            f[row * FEATURES + HIDDEN..(row + 1) * FEATURES].copy_from_slice(b);
        }
        f
    }

    /// Head: `A = σ(F)`, `Y = (A W_fc^T) S`. Returns `(A, Y)`.
    fn head_forward(&self, feats: &[f32], rows: usize) -> (Vec<f32>, Vec<f32>) {
        let act: Vec<f32> = feats.iter().map(|&v| sigmoid(v)).collect();
        let mut p = vec![0.0f32; rows * NUM_BONES];
        matmul_t(
            &mut p,
            (&act, false),
            (&self.params[self.layout.fc_w.clone()], true),
            (rows, FEATURES, NUM_BONES),
            false,
            1,
        );
        let mut y = vec![0.0f32; rows * NUM_BONES];
        for r in 0..rows {
            for j in 0..NUM_BONES {
                y[r * NUM_BONES + j] = (0..NUM_BONES)
                    .map(|i| p[r * NUM_BONES + i] * self.sym[i][j])
                    .sum();
            }
        }
        (act, y)
    }

    /// Head backward: accumulates dW_fc into `grad`, returns dF.
    fn head_backward(&self, act: &[f32], dy: &[f32], rows: usize, grad: &mut [f32]) -> Vec<f32> {
        let mut dp = vec![0.0f32; rows * NUM_BONES];
        for r in 0..rows {
            for i in 0..NUM_BONES {
                dp[r * NUM_BONES + i] = (0..NUM_BONES)
                    .map(|j| dy[r * NUM_BONES + j] * self.sym[i][j])
                    .sum();
            }
        }
        matmul_t(
            &mut grad[self.layout.fc_w.clone()],
            (&dp, true),
            (act, false),
            (NUM_BONES, rows, FEATURES),
            true,
            2,
        );
        let mut df = vec![0.0f32; rows * FEATURES];
        matmul_t(
            &mut df,
            (&dp, false),
            (&self.params[self.layout.fc_w.clone()], false),
            (rows, NUM_BONES, FEATURES),
            false,
            2,
        );
        for (d, a) in df.iter_mut().zip(act) {
            *d *= a * (1.0 - a);
        }
        df
    }
}

/// Buffers of one forward pass.
struct Forward {
    /// Time-major input `[T*B, 34]`.
    x: Vec<f32>,
    /// Embedding after ReLU and dropout, time-major `[T*B, 256]`.
    e: Vec<f32>,
    /// dE/d(pre-activation) factor: ReLU gate times dropout scale.
    mask: Vec<f32>,
    gru: [GruCache; 2],
}

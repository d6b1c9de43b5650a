//! The recurrence of [`FastNet`]: one GRU direction's time loop forwards
//! (keeping what the backward pass needs, [`GruCache`]) and backwards
//! (BPTT), over preallocated buffers with one GEMM per step. The network
//! around it (embedding, head, loss, the parameter vector) is the parent
//! module's.

use blapose_model::fast::linalg::matmul_t;
use blapose_model::{EMBED_DIM, GATES, HIDDEN};

use super::FastNet;

#[inline(always)]
pub(super) fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

#[inline(always)]
fn tanh(x: f32) -> f32 {
    2.0 * sigmoid(2.0 * x) - 1.0
}

/// Per-direction buffers of a forward pass, kept for the backward pass.
#[derive(Debug, Default, Clone)]
pub(super) struct GruCache {
    /// Input pre-activations `W_ih e + b_ih`, time-major `[T, B, 1536]`.
    pub(super) gi: Vec<f32>,
    /// States in processing order: `hs[s]` is the state before step `s`,
    /// `[(T+1), B, 512]`.
    pub(super) hs: Vec<f32>,
    /// Gates per step (processing order), `[T, B, 512]` each.
    pub(super) r: Vec<f32>,
    pub(super) z: Vec<f32>,
    pub(super) n: Vec<f32>,
    /// `W_hn h + b_hn` per step, `[T, B, 512]`.
    pub(super) ghn: Vec<f32>,
}

impl FastNet {
    pub(super) fn gru_forward(
        &self,
        g: usize,
        e: &[f32],
        batch: usize,
        steps: usize,
        reverse: bool,
    ) -> GruCache {
        let lay = &self.layout.gru[g];
        let p = &self.params;
        let rows = batch * steps;
        let mut gi = vec![0.0f32; rows * GATES];
        matmul_t(
            &mut gi,
            (e, false),
            (&p[lay.w_ih.clone()], true),
            (rows, EMBED_DIM, GATES),
            false,
            1,
        );
        let b_ih = &p[lay.b_ih.clone()];
        for r in 0..rows {
            for (v, b) in gi[r * GATES..(r + 1) * GATES].iter_mut().zip(b_ih) {
                *v += b;
            }
        }
        let w_hh = &p[lay.w_hh.clone()];
        let b_hh = &p[lay.b_hh.clone()];
        let bh = batch * HIDDEN;
        let mut c = GruCache {
            gi,
            hs: vec![0.0f32; (steps + 1) * bh],
            r: vec![0.0f32; steps * bh],
            z: vec![0.0f32; steps * bh],
            n: vec![0.0f32; steps * bh],
            ghn: vec![0.0f32; steps * bh],
        };
        let mut gh = vec![0.0f32; batch * GATES];
        for s in 0..steps {
            let t = if reverse { steps - 1 - s } else { s };
            let (done, next) = c.hs.split_at_mut((s + 1) * bh);
            let h = &done[s * bh..];
            matmul_t(
                &mut gh,
                (h, false),
                (w_hh, true),
                (batch, HIDDEN, GATES),
                false,
                1,
            );
            let h_next = &mut next[..bh];
            for b in 0..batch {
                let gi_row = &c.gi[(t * batch + b) * GATES..(t * batch + b + 1) * GATES];
                let gh_row = &gh[b * GATES..(b + 1) * GATES];
                let o = s * bh + b * HIDDEN;
                for k in 0..HIDDEN {
                    let r = sigmoid(gi_row[k] + gh_row[k] + b_hh[k]);
                    let z = sigmoid(gi_row[HIDDEN + k] + gh_row[HIDDEN + k] + b_hh[HIDDEN + k]);
                    let ghn = gh_row[2 * HIDDEN + k] + b_hh[2 * HIDDEN + k];
                    let n = tanh(gi_row[2 * HIDDEN + k] + r * ghn);
                    let hp = h[b * HIDDEN + k];
                    h_next[b * HIDDEN + k] = n + z * (hp - n);
                    c.r[o + k] = r;
                    c.z[o + k] = z;
                    c.n[o + k] = n;
                    c.ghn[o + k] = ghn;
                }
            }
        }
        c
    }

    /// BPTT of direction `g`. `dh_ext[s]` (`[T, B, 512]`, processing order)
    /// is the loss gradient w.r.t. the state after step `s`. Writes the
    /// direction's parameter gradients into `grad` (its sub-slice, layout
    /// `w_ih | w_hh | b_ih | b_hh`) and returns dE (`[T*B, 256]`, time-major).
    #[allow(clippy::too_many_arguments)]
    pub(super) fn gru_backward(
        &self,
        g: usize,
        c: &GruCache,
        e: &[f32],
        dh_ext: &[f32],
        batch: usize,
        steps: usize,
        reverse: bool,
        grad: &mut [f32],
    ) -> Vec<f32> {
        let lay = &self.layout.gru[g];
        let w_hh = &self.params[lay.w_hh.clone()];
        let w_ih = &self.params[lay.w_ih.clone()];
        let bh = batch * HIDDEN;
        let rows = batch * steps;
        // dGI indexed by time t, dGH by step s.
        let mut dgi = vec![0.0f32; rows * GATES];
        let mut dgh = vec![0.0f32; rows * GATES];
        let mut dh = vec![0.0f32; bh];
        let mut dh_prev = vec![0.0f32; bh];
        for s in (0..steps).rev() {
            let t = if reverse { steps - 1 - s } else { s };
            for (d, x) in dh.iter_mut().zip(&dh_ext[s * bh..(s + 1) * bh]) {
                *d += x;
            }
            let h_prev = &c.hs[s * bh..(s + 1) * bh];
            for b in 0..batch {
                let o = s * bh + b * HIDDEN;
                let gi_o = (t * batch + b) * GATES;
                let gh_o = (s * batch + b) * GATES;
                for k in 0..HIDDEN {
                    let (r, z, n, ghn) = (c.r[o + k], c.z[o + k], c.n[o + k], c.ghn[o + k]);
                    let d = dh[b * HIDDEN + k];
                    let dn = d * (1.0 - z);
                    let dz = d * (h_prev[b * HIDDEN + k] - n);
                    dh_prev[b * HIDDEN + k] = d * z;
                    let dan = dn * (1.0 - n * n);
                    let dr = dan * ghn;
                    let dar = dr * r * (1.0 - r);
                    let daz = dz * z * (1.0 - z);
                    dgi[gi_o + k] = dar;
                    dgi[gi_o + HIDDEN + k] = daz;
                    dgi[gi_o + 2 * HIDDEN + k] = dan;
                    dgh[gh_o + k] = dar;
                    dgh[gh_o + HIDDEN + k] = daz;
                    dgh[gh_o + 2 * HIDDEN + k] = dan * r;
                }
            }
            // dh_prev += dGH_s W_hh   ([B,1536] x [1536,512])
            matmul_t(
                &mut dh_prev,
                (&dgh[s * batch * GATES..(s + 1) * batch * GATES], false),
                (w_hh, false),
                (batch, GATES, HIDDEN),
                true,
                1,
            );
            std::mem::swap(&mut dh, &mut dh_prev);
        }
        let n_ih = lay.w_ih.len();
        let n_hh = lay.w_hh.len();
        let (g_ih, rest) = grad.split_at_mut(n_ih);
        let (g_hh, rest) = rest.split_at_mut(n_hh);
        let (g_bih, g_bhh) = rest.split_at_mut(GATES);
        // dW_ih = dGI^T E ; dW_hh = dGH^T H_prev (states before each step).
        matmul_t(
            g_ih,
            (&dgi, true),
            (e, false),
            (GATES, rows, EMBED_DIM),
            false,
            1,
        );
        matmul_t(
            g_hh,
            (&dgh, true),
            (&c.hs[..steps * bh], false),
            (GATES, rows, HIDDEN),
            false,
            1,
        );
        for r in 0..rows {
            for k in 0..GATES {
                g_bih[k] += dgi[r * GATES + k];
                g_bhh[k] += dgh[r * GATES + k];
            }
        }
        let mut de = vec![0.0f32; rows * EMBED_DIM];
        matmul_t(
            &mut de,
            (&dgi, false),
            (w_ih, false),
            (rows, GATES, EMBED_DIM),
            false,
            1,
        );
        de
    }
}

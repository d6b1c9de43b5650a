//! Input preconditioning for training, folded into the first layer when the
//! weights are saved.
//!
//! The network reads 34 normalized screen coordinates per frame. What tells
//! bone lengths apart is millimetres of difference *between* joints, while
//! the coordinates themselves swing by the whole image as the person walks
//! around: in raw coordinates the informative directions carry a tiny
//! fraction of the input variance, and the first layer (`Linear(34 -> 256)`)
//! has to learn large, nearly cancelling weights to see them. Adam does not
//! undo that (its steps are per weight, not per input direction), so
//! learning is slow.
//!
//! Training therefore feeds the network a fixed affine map of each frame
//! ([`InputPreconditioner`]): the root joint's coordinates, every other
//! joint relative to the root, each feature then centred and scaled to unit
//! variance over the synthetic validation set. The map is linear, so
//! `W' P(x) + b'` equals `W x + b` with `W = W' D A` and `b = b' - W' D mu`
//! ([`InputPreconditioner::fold`]): the saved weights file is the paper's
//! architecture on raw coordinates, and nothing that serves or evaluates a
//! model knows the preconditioner existed. Warm starts go the other way
//! ([`InputPreconditioner::unfold`]).

use blapose_core::skeleton::{NUM_JOINTS, ROOT};

use crate::synth::FRAME_DIM;

/// A fixed per-frame map `x -> D (A x - mu)` (see the module docs).
#[derive(Debug, Clone, PartialEq)]
pub struct InputPreconditioner {
    /// `mu`: mean of each root-relative feature.
    mean: [f32; FRAME_DIM],
    /// `D`: inverse standard deviation of each feature.
    inv_std: [f32; FRAME_DIM],
}

/// `A x`: the root's coordinates, every other joint relative to the root.
fn root_relative(frame: &[f32]) -> [f32; FRAME_DIM] {
    let root = [frame[2 * ROOT], frame[2 * ROOT + 1]];
    std::array::from_fn(|i| {
        if i / 2 == ROOT {
            frame[i]
        } else {
            frame[i] - root[i % 2]
        }
    })
}

impl InputPreconditioner {
    /// Statistics of the frames in `inputs` (flat, `FRAME_DIM` per frame).
    /// A feature that does not vary keeps scale 1.
    pub fn fit(inputs: &[f32]) -> Self {
        let mut sum = [0.0f64; FRAME_DIM];
        let mut sq = [0.0f64; FRAME_DIM];
        let mut n = 0usize;
        for frame in inputs.chunks_exact(FRAME_DIM) {
            let f = root_relative(frame);
            if f.iter().any(|v| !v.is_finite()) {
                continue;
            }
            for i in 0..FRAME_DIM {
                sum[i] += f64::from(f[i]);
                sq[i] += f64::from(f[i]).powi(2);
            }
            n += 1;
        }
        let n = n.max(1) as f64;
        let mean = std::array::from_fn(|i| (sum[i] / n) as f32);
        let inv_std = std::array::from_fn(|i| {
            let var = (sq[i] / n - (sum[i] / n).powi(2)).max(0.0);
            if var > 1e-12 {
                (1.0 / var.sqrt()) as f32
            } else {
                1.0
            }
        });
        Self { mean, inv_std }
    }

    /// Map every frame of `inputs` in place.
    pub fn apply(&self, inputs: &mut [f32]) {
        for frame in inputs.chunks_exact_mut(FRAME_DIM) {
            let f = root_relative(frame);
            for i in 0..FRAME_DIM {
                frame[i] = (f[i] - self.mean[i]) * self.inv_std[i];
            }
        }
    }

    /// Turn a first layer that reads preconditioned frames (`w`: rows of
    /// `FRAME_DIM`, `b`: one per row) into one that reads raw frames.
    pub fn fold(&self, w: &mut [f32], b: &mut [f32]) {
        for (row, bias) in w.chunks_exact_mut(FRAME_DIM).zip(b.iter_mut()) {
            let v: [f32; FRAME_DIM] = std::array::from_fn(|i| row[i] * self.inv_std[i]);
            *bias -= v.iter().zip(&self.mean).map(|(a, m)| a * m).sum::<f32>();
            row.copy_from_slice(&v);
            // The root's coordinates also enter every relative feature.
            for c in 0..2 {
                let others: f32 = (0..NUM_JOINTS)
                    .filter(|&j| j != ROOT)
                    .map(|j| v[2 * j + c])
                    .sum();
                row[2 * ROOT + c] -= others;
            }
        }
    }

    /// The inverse of [`Self::fold`]: a first layer on raw frames as one on
    /// preconditioned frames (for warm starts).
    pub fn unfold(&self, w: &mut [f32], b: &mut [f32]) {
        for (row, bias) in w.chunks_exact_mut(FRAME_DIM).zip(b.iter_mut()) {
            for c in 0..2 {
                let all: f32 = (0..NUM_JOINTS).map(|j| row[2 * j + c]).sum();
                row[2 * ROOT + c] = all;
            }
            *bias += row.iter().zip(&self.mean).map(|(u, m)| u * m).sum::<f32>();
            for i in 0..FRAME_DIM {
                row[i] /= self.inv_std[i];
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::rngs::StdRng;
    use rand::{Rng, SeedableRng};

    fn frames(n: usize, rng: &mut StdRng) -> Vec<f32> {
        (0..n)
            .flat_map(|_| {
                let root = [rng.random_range(-0.5..0.5), rng.random_range(-0.3..0.3)];
                (0..FRAME_DIM)
                    .map(|i| root[i % 2] + rng.random_range(-0.05f32..0.05))
                    .collect::<Vec<_>>()
            })
            .collect()
    }

    fn layer(w: &[f32], b: &[f32], x: &[f32]) -> Vec<f32> {
        w.chunks_exact(FRAME_DIM)
            .zip(b)
            .map(|(row, bias)| row.iter().zip(x).map(|(a, v)| a * v).sum::<f32>() + bias)
            .collect()
    }

    #[test]
    fn preconditioned_features_are_standardized() {
        let mut rng = StdRng::seed_from_u64(1);
        let mut x = frames(4000, &mut rng);
        let p = InputPreconditioner::fit(&x);
        p.apply(&mut x);
        for i in 0..FRAME_DIM {
            let col: Vec<f32> = x.iter().skip(i).step_by(FRAME_DIM).copied().collect();
            let m = col.iter().sum::<f32>() / col.len() as f32;
            let v = col.iter().map(|c| (c - m).powi(2)).sum::<f32>() / col.len() as f32;
            assert!(
                m.abs() < 1e-3 && (v - 1.0).abs() < 1e-2,
                "feature {i}: {m} {v}"
            );
        }
    }

    #[test]
    fn a_folded_layer_on_raw_frames_equals_the_layer_on_preconditioned_ones() {
        let mut rng = StdRng::seed_from_u64(2);
        let fit = frames(500, &mut rng);
        let p = InputPreconditioner::fit(&fit);
        let w: Vec<f32> = (0..8 * FRAME_DIM)
            .map(|_| rng.random_range(-1.0..1.0))
            .collect();
        let b: Vec<f32> = (0..8).map(|_| rng.random_range(-1.0..1.0)).collect();
        let raw = frames(3, &mut rng);
        let mut pre = raw.clone();
        p.apply(&mut pre);
        let (mut wf, mut bf) = (w.clone(), b.clone());
        p.fold(&mut wf, &mut bf);
        for (x, xp) in raw.chunks_exact(FRAME_DIM).zip(pre.chunks_exact(FRAME_DIM)) {
            for (a, c) in layer(&wf, &bf, x).iter().zip(layer(&w, &b, xp)) {
                assert!((a - c).abs() < 1e-3 * (1.0 + c.abs()), "{a} vs {c}");
            }
        }
        // unfold undoes fold.
        p.unfold(&mut wf, &mut bf);
        for (a, c) in wf.iter().chain(&bf).zip(w.iter().chain(&b)) {
            assert!((a - c).abs() < 1e-3 * (1.0 + c.abs()), "{a} vs {c}");
        }
    }
}

//! Does the root solve place people too far or too near, by the same
//! factor everywhere? The solve ([`blapose_core::motion::root`]) reads the
//! person's 2D size against the skeleton's: if a 2D detector puts its
//! joints systematically closer together than the skeleton's joints
//! project (a narrower hip, a shorter torso), every person is placed too
//! far by the same fraction, whatever lengths the skeleton has.
//!
//! [`RootPairs`] collects solved and true roots per trial; [`fit_scale`]
//! is the one factor that brings the solved roots closest to the truth
//! (least squares along the viewing rays), and [`mrpe_mm`] scores roots
//! scaled by it. The factor is fitted with the *true* skeleton on the
//! training subjects (what the detections do, not what a length model
//! gets wrong) and checked across subjects.

use blapose_core::metrics::MM_PER_M;
use blapose_core::Pose;
use blapose_train::motion_eval::{place_roots, Scene};

/// Solved and true roots of one trial.
#[derive(Debug, Clone)]
pub struct RootPairs {
    /// The trial's subject.
    pub subject: String,
    /// The trial's camera.
    pub camera: String,
    /// Roots solved frame by frame for the poses.
    pub solved: Vec<[f64; 3]>,
    /// The true roots.
    pub truth: Vec<[f64; 3]>,
}

impl RootPairs {
    /// Roots solved for `poses` (root-relative) through `scene`'s rays.
    pub fn solve(subject: &str, camera: &str, poses: &[Pose], scene: &Scene) -> Self {
        Self {
            subject: subject.to_string(),
            camera: camera.to_string(),
            solved: place_roots(poses, scene),
            truth: scene.root.clone(),
        }
    }
}

/// Roots solved with joints whose reprojection misses by more than
/// `c` (ray units: pixels over the focal length) down-weighted (Huber,
/// `iters` reweightings); a frame that cannot be solved repeats the last.
pub fn place_roots_robust(poses: &[Pose], scene: &Scene, c: f64, iters: usize) -> Vec<[f64; 3]> {
    use blapose_core::motion::root::solve_root;
    use blapose_core::skeleton::{NUM_JOINTS, ROOT};
    let mut last = [0.0; 3];
    poses
        .iter()
        .zip(&scene.rays)
        .map(|(p, (r, w))| {
            let mut weights = *w;
            let mut t = solve_root(r, p, &weights);
            for _ in 0..iters {
                let Some(root) = t else { break };
                for j in 0..NUM_JOINTS {
                    let q: [f64; 3] =
                        std::array::from_fn(|i| (p[j][i] - p[ROOT][i]) as f64 + root[i]);
                    let e =
                        ((q[0] / q[2] - r[j][0]).powi(2) + (q[1] / q[2] - r[j][1]).powi(2)).sqrt();
                    weights[j] = w[j] * if e > c { c / e } else { 1.0 };
                }
                t = solve_root(r, p, &weights).or(t);
            }
            if let Some(v) = t {
                last = v;
            }
            last
        })
        .collect()
}

/// Each root replaced by the per-axis median of it and the `window - 1`
/// before it (causal).
pub fn causal_median(roots: &[[f64; 3]], window: usize) -> Vec<[f64; 3]> {
    (0..roots.len())
        .map(|t| {
            let from = (t + 1).saturating_sub(window.max(1));
            std::array::from_fn(|i| {
                let mut v: Vec<f64> = roots[from..=t].iter().map(|r| r[i]).collect();
                v.sort_by(f64::total_cmp);
                v[v.len() / 2]
            })
        })
        .collect()
}

/// What a learned depth correction reads of one frame: the rays relative
/// to the pelvis's ray and the pose relative to its pelvis, each divided
/// by its own root-mean-square spread (scale-free: the depth the solve
/// gives is not an input), and a constant.
pub fn depth_features(rays: &blapose_core::motion::root::Rays, pose: &Pose) -> Vec<f64> {
    use blapose_core::skeleton::{NUM_JOINTS, ROOT};
    let mut f = Vec::with_capacity(5 * NUM_JOINTS + 1);
    let r: Vec<[f64; 2]> = rays
        .iter()
        .map(|q| [q[0] - rays[ROOT][0], q[1] - rays[ROOT][1]])
        .collect();
    let s2 = (r.iter().map(|q| q[0] * q[0] + q[1] * q[1]).sum::<f64>() / NUM_JOINTS as f64)
        .sqrt()
        .max(1e-9);
    f.extend(r.iter().flat_map(|q| [q[0] / s2, q[1] / s2]));
    let p: Vec<[f64; 3]> = pose
        .iter()
        .map(|q| std::array::from_fn(|i| (q[i] - pose[ROOT][i]) as f64))
        .collect();
    let s3 = (p.iter().map(|q| dot(*q, *q)).sum::<f64>() / NUM_JOINTS as f64)
        .sqrt()
        .max(1e-9);
    f.extend(p.iter().flat_map(|q| q.map(|v| v / s3)));
    f.push(1.0);
    f
}

/// A linear model of `ln(true depth / solved depth)` from
/// [`depth_features`], fitted by ridge least squares.
#[derive(Debug, Clone)]
pub struct DepthCorrection {
    weights: Vec<f64>,
}

impl DepthCorrection {
    /// Fit on `(features, ln ratio)` samples with ridge `lambda`.
    pub fn fit<'a>(
        samples: impl IntoIterator<Item = (&'a [f64], f64)>,
        lambda: f64,
    ) -> Option<Self> {
        use nalgebra::{DMatrix, DVector};
        let mut ata: Option<DMatrix<f64>> = None;
        let mut atb: Option<DVector<f64>> = None;
        for (x, y) in samples {
            let v = DVector::from_column_slice(x);
            let a = ata.get_or_insert_with(|| DMatrix::zeros(x.len(), x.len()));
            a.ger(1.0, &v, &v, 1.0);
            let b = atb.get_or_insert_with(|| DVector::zeros(x.len()));
            b.axpy(y, &v, 1.0);
        }
        let (mut a, b) = (ata?, atb?);
        for i in 0..a.nrows() {
            a[(i, i)] += lambda;
        }
        let w = a.cholesky()?.solve(&b);
        Some(Self {
            weights: w.iter().copied().collect(),
        })
    }

    /// The factor to multiply a solved root by.
    pub fn factor(&self, features: &[f64]) -> f64 {
        features
            .iter()
            .zip(&self.weights)
            .map(|(a, b)| a * b)
            .sum::<f64>()
            .exp()
    }
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// The factor `k` minimising `Σ |k·solved − truth|²` over every frame of
/// `pairs` (1 when there is nothing to fit).
pub fn fit_scale<'a>(pairs: impl IntoIterator<Item = &'a RootPairs>) -> f64 {
    let (mut num, mut den) = (0.0, 0.0);
    for p in pairs {
        for (s, t) in p.solved.iter().zip(&p.truth) {
            num += dot(*s, *t);
            den += dot(*s, *s);
        }
    }
    if den > 0.0 {
        num / den
    } else {
        1.0
    }
}

/// Mean root position error (mm) of `pairs`' solved roots scaled by `k`.
pub fn mrpe_mm<'a>(pairs: impl IntoIterator<Item = &'a RootPairs>, k: f64) -> f64 {
    let (mut sum, mut n) = (0.0, 0usize);
    for p in pairs {
        for (s, t) in p.solved.iter().zip(&p.truth) {
            let d = [k * s[0] - t[0], k * s[1] - t[1], k * s[2] - t[2]];
            sum += dot(d, d).sqrt();
            n += 1;
        }
    }
    sum / n.max(1) as f64 * MM_PER_M
}

/// Median over frames of solved depth over true depth.
pub fn median_depth_ratio<'a>(pairs: impl IntoIterator<Item = &'a RootPairs>) -> f64 {
    let mut r: Vec<f64> = pairs
        .into_iter()
        .flat_map(|p| p.solved.iter().zip(&p.truth).map(|(s, t)| s[2] / t[2]))
        .filter(|v| v.is_finite())
        .collect();
    if r.is_empty() {
        return f64::NAN;
    }
    r.sort_by(f64::total_cmp);
    r[r.len() / 2]
}

/// Where the root error sits (mm): mean |depth error|, mean |error across
/// the image| (x, y), the root mean square of each trial's mean signed
/// depth error (what no filter over time can remove) and the root mean
/// square of the depth error about its trial's mean (what one can).
pub fn depth_split_mm<'a>(pairs: impl IntoIterator<Item = &'a RootPairs>) -> [f64; 4] {
    let (mut dz_abs, mut dxy, mut bias2, mut wobble2, mut n, mut trials) =
        (0.0, 0.0, 0.0, 0.0, 0usize, 0usize);
    for p in pairs {
        let dz: Vec<f64> = p
            .solved
            .iter()
            .zip(&p.truth)
            .map(|(s, t)| s[2] - t[2])
            .collect();
        if dz.is_empty() {
            continue;
        }
        let mean = dz.iter().sum::<f64>() / dz.len() as f64;
        bias2 += mean * mean;
        trials += 1;
        for (s, t) in p.solved.iter().zip(&p.truth) {
            let z = s[2] - t[2];
            dz_abs += z.abs();
            dxy += ((s[0] - t[0]).powi(2) + (s[1] - t[1]).powi(2)).sqrt();
            wobble2 += (z - mean).powi(2);
            n += 1;
        }
    }
    let n = n.max(1) as f64;
    [
        dz_abs / n * MM_PER_M,
        dxy / n * MM_PER_M,
        (bias2 / trials.max(1) as f64).sqrt() * MM_PER_M,
        (wobble2 / n).sqrt() * MM_PER_M,
    ]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_fitted_scale_undoes_a_uniform_bias() {
        let truth: Vec<[f64; 3]> = (0..50)
            .map(|i| [0.1 * i as f64, -0.3, 3.0 + 0.05 * i as f64])
            .collect();
        let solved = truth.iter().map(|t| t.map(|v| v * 1.08)).collect();
        let p = RootPairs {
            subject: "S1".into(),
            camera: "c".into(),
            solved,
            truth,
        };
        let k = fit_scale([&p]);
        assert!((k - 1.0 / 1.08).abs() < 1e-12, "{k}");
        assert!(mrpe_mm([&p], k) < 1e-9);
        assert!(mrpe_mm([&p], 1.0) > 100.0);
        assert!((median_depth_ratio([&p]) - 1.08).abs() < 1e-12);
    }

    #[test]
    fn a_causal_median_reads_no_later_root_and_drops_a_spike() {
        let mut roots: Vec<[f64; 3]> = (0..9).map(|i| [0.0, 0.0, 3.0 + 0.01 * i as f64]).collect();
        roots[4][2] = 30.0;
        let m = causal_median(&roots, 3);
        assert_eq!(m[0], roots[0]);
        assert!((m[4][2] - 3.03).abs() < 1e-12, "{:?}", m[4]);
        let mut later = roots.clone();
        later[8][2] = -5.0;
        assert_eq!(causal_median(&later, 3)[..8], m[..8]);
    }

    #[test]
    fn the_depth_correction_learns_a_linear_log_ratio() {
        let samples: Vec<(Vec<f64>, f64)> = (0..200)
            .map(|i| {
                let x = (i as f64 * 0.37).sin();
                (vec![x, 1.0], 0.05 * x - 0.02)
            })
            .collect();
        let model =
            DepthCorrection::fit(samples.iter().map(|(f, y)| (f.as_slice(), *y)), 1e-9).unwrap();
        assert!((model.factor(&[0.5, 1.0]) - (0.025f64 - 0.02).exp()).abs() < 1e-9);
    }
}

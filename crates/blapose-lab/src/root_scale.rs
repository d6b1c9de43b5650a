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
}

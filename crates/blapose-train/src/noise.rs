//! 2D detector-noise models fitted to the training subjects' real
//! Stacked Hourglass detections.
//!
//! At test time the model sees real detections, whose joints are defined
//! differently from the mocap joints (the SH hips, spine and head are a few
//! centimetres off) and which jitter. Training on clean projections leaves
//! that gap open. The residual `r_t = SH17_t - project(GT_t)` of every
//! *training* sequence and camera is kept in a [`ResidualBank`], expressed in
//! **depth-scaled metric units** (`r_norm * root_depth / focal_norm`, i.e.
//! roughly metres at the subject), so it can be re-applied to a synthetic
//! sample whose subject stands at another depth: `r_norm' = r_metric *
//! focal_norm' / depth'`.
//!
//! [`NoiseKind::Residual`] adds the residual of the very sequence and camera
//! the sample was synthesised from, time-aligned with the same playback
//! stride (the detector's errors depend on the pose and the view, so the
//! aligned residual is the most realistic one); [`NoiseKind::Gaussian`] adds
//! iid per-joint Gaussian noise whose per-joint, per-axis std is fitted to
//! the same residuals. Residuals longer than [`MAX_RESIDUAL_M`] (detector
//! failures) are clamped so a few gross errors don't dominate.

use blapose_core::skeleton::NUM_JOINTS;
use blapose_core::Keypoints2d;
use rand::Rng;
use rand_distr::{Distribution, StandardNormal};
use serde::{Deserialize, Serialize};

/// Residual norms above this (metric units, metres at the subject) are
/// clamped to it.
pub const MAX_RESIDUAL_M: f32 = 0.3;

/// Which noise is added to the synthetic 2D input (`--noise`; the same
/// spelling in a run's configuration).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum NoiseKind {
    /// Clean projections.
    None,
    /// iid per-joint Gaussian with per-joint std fitted to the residuals.
    Gaussian,
    /// The real, time-aligned residual of the same sequence and camera.
    Residual,
}

impl NoiseKind {
    /// The flag spelling.
    pub fn name(self) -> &'static str {
        match self {
            Self::None => "none",
            Self::Gaussian => "gaussian",
            Self::Residual => "residual",
        }
    }
}

impl std::fmt::Display for NoiseKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// One frame's residual in metric units (17 joints x 2).
pub type MetricResidual = [[f32; 2]; NUM_JOINTS];

/// The residual of one frame in metric units: `(sh - gt) * depth / focal`,
/// clamped to [`MAX_RESIDUAL_M`] per joint. `None` if anything is not finite
/// or the depth is not positive.
pub fn metric_residual(
    sh: &Keypoints2d,
    gt: &Keypoints2d,
    root_depth: f32,
    focal: [f32; 2],
) -> Option<MetricResidual> {
    let usable = root_depth > 0.0 && focal[0] > 0.0 && focal[1] > 0.0; // false for NaN too
    if !usable {
        return None;
    }
    let mut out = [[0.0f32; 2]; NUM_JOINTS];
    for j in 0..NUM_JOINTS {
        let mut r = [
            (sh[j][0] - gt[j][0]) * root_depth / focal[0],
            (sh[j][1] - gt[j][1]) * root_depth / focal[1],
        ];
        if !(r[0].is_finite() && r[1].is_finite()) {
            return None;
        }
        let n = (r[0] * r[0] + r[1] * r[1]).sqrt();
        if n > MAX_RESIDUAL_M {
            r = [r[0] * MAX_RESIDUAL_M / n, r[1] * MAX_RESIDUAL_M / n];
        }
        out[j] = r;
    }
    Some(out)
}

/// Real detection residuals of the training subjects, one track per
/// (training sequence, camera), plus the per-joint Gaussian fit.
#[derive(Debug, Clone, Default)]
pub struct ResidualBank {
    /// `tracks[seq][cam]`: per-frame metric residuals, or `None` when that
    /// camera has no detections.
    tracks: Vec<Vec<Option<Vec<MetricResidual>>>>,
    /// Per-joint, per-axis standard deviation (metric units).
    std: MetricResidual,
    /// Per-joint, per-axis mean (metric units): the systematic joint
    /// definition offset, kept so the Gaussian model includes the bias.
    mean: MetricResidual,
    frames: usize,
}

impl ResidualBank {
    /// Build from tracks (already metric, see [`metric_residual`]).
    pub fn new(tracks: Vec<Vec<Option<Vec<MetricResidual>>>>) -> Self {
        let mut sum = [[0.0f64; 2]; NUM_JOINTS];
        let mut sq = [[0.0f64; 2]; NUM_JOINTS];
        let mut n = 0usize;
        for r in tracks.iter().flatten().flatten().flatten() {
            n += 1;
            for j in 0..NUM_JOINTS {
                for a in 0..2 {
                    let v = f64::from(r[j][a]);
                    sum[j][a] += v;
                    sq[j][a] += v * v;
                }
            }
        }
        let mut mean = [[0.0f32; 2]; NUM_JOINTS];
        let mut std = [[0.0f32; 2]; NUM_JOINTS];
        if n > 0 {
            let nf = n as f64;
            for j in 0..NUM_JOINTS {
                for a in 0..2 {
                    let m = sum[j][a] / nf;
                    mean[j][a] = m as f32;
                    std[j][a] = (sq[j][a] / nf - m * m).max(0.0).sqrt() as f32;
                }
            }
        }
        Self {
            tracks,
            std,
            mean,
            frames: n,
        }
    }

    /// Number of residual frames in the bank.
    pub fn frames(&self) -> usize {
        self.frames
    }

    /// Per-joint, per-axis std (metric units).
    pub fn std(&self) -> &MetricResidual {
        &self.std
    }

    /// Per-joint, per-axis mean (metric units).
    pub fn mean(&self) -> &MetricResidual {
        &self.mean
    }

    /// The residual track of sequence `seq`, camera `cam`, if any.
    pub fn track(&self, seq: usize, cam: usize) -> Option<&[MetricResidual]> {
        self.tracks.get(seq)?.get(cam)?.as_deref()
    }

    /// Any non-empty track, chosen at random (for samples whose own camera
    /// has no detections).
    pub fn random_track<R: Rng + ?Sized>(&self, rng: &mut R) -> Option<&[MetricResidual]> {
        let all: Vec<&[MetricResidual]> = self
            .tracks
            .iter()
            .flatten()
            .filter_map(|t| t.as_deref())
            .filter(|t| !t.is_empty())
            .collect();
        if all.is_empty() {
            None
        } else {
            Some(all[rng.random_range(0..all.len())])
        }
    }

    /// A Gaussian draw (metric units) from the fitted per-joint model.
    pub fn gaussian<R: Rng + ?Sized>(&self, rng: &mut R) -> MetricResidual {
        std::array::from_fn(|j| {
            std::array::from_fn(|a| {
                let z: f32 = StandardNormal.sample(rng);
                self.mean[j][a] + self.std[j][a] * z
            })
        })
    }
}

/// Linear interpolation of a residual track at fractional frame `u`
/// (clamped to the track).
pub fn residual_at(track: &[MetricResidual], u: f32) -> MetricResidual {
    let last = track.len().saturating_sub(1);
    let u = u.clamp(0.0, last as f32);
    let i = (u.floor() as usize).min(last);
    let k = (i + 1).min(last);
    let a = u - i as f32;
    std::array::from_fn(|j| {
        std::array::from_fn(|c| track[i][j][c] * (1.0 - a) + track[k][j][c] * a)
    })
}

/// Add a metric residual to normalized keypoints at root depth `depth`
/// seen with normalized focal lengths `focal`.
pub fn apply_residual(kp: &mut Keypoints2d, r: &MetricResidual, depth: f32, focal: [f32; 2]) {
    for j in 0..NUM_JOINTS {
        kp[j][0] += r[j][0] * focal[0] / depth;
        kp[j][1] += r[j][1] * focal[1] / depth;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn flag_config_and_display_spellings_agree() {
        use clap::ValueEnum;
        for k in NoiseKind::value_variants() {
            assert_eq!(k.to_possible_value().unwrap().get_name(), k.name());
            assert_eq!(serde_json::to_value(k).unwrap(), k.name());
            assert_eq!(k.to_string(), k.name());
        }
    }

    #[test]
    fn residual_round_trips_through_depth() {
        let gt: Keypoints2d = std::array::from_fn(|j| [j as f32 * 0.01, 0.1]);
        let mut sh = gt;
        sh[3][0] += 0.02;
        let r = metric_residual(&sh, &gt, 5.0, [2.3, 2.3]).unwrap();
        assert!((r[3][0] - 0.02 * 5.0 / 2.3).abs() < 1e-6);
        let mut back = gt;
        apply_residual(&mut back, &r, 5.0, [2.3, 2.3]);
        assert!((back[3][0] - sh[3][0]).abs() < 1e-6);
        // Twice as far: half the image-space offset.
        let mut far = gt;
        apply_residual(&mut far, &r, 10.0, [2.3, 2.3]);
        assert!(((far[3][0] - gt[3][0]) - 0.01).abs() < 1e-6);
        assert!(metric_residual(&sh, &gt, 0.0, [2.3, 2.3]).is_none());
    }

    #[test]
    fn gross_errors_are_clamped_and_stats_fitted() {
        let gt: Keypoints2d = [[0.0; 2]; NUM_JOINTS];
        let mut sh = gt;
        sh[0][0] = 10.0;
        let r = metric_residual(&sh, &gt, 1.0, [1.0, 1.0]).unwrap();
        assert!((r[0][0] - MAX_RESIDUAL_M).abs() < 1e-6);
        let a = [[0.01f32, 0.0]; NUM_JOINTS];
        let b = [[0.03f32, 0.0]; NUM_JOINTS];
        let bank = ResidualBank::new(vec![vec![Some(vec![a, b]), None]]);
        assert_eq!(bank.frames(), 2);
        assert!((bank.mean()[5][0] - 0.02).abs() < 1e-6);
        assert!((bank.std()[5][0] - 0.01).abs() < 1e-6);
        assert!(bank.track(0, 1).is_none());
        let mid = residual_at(bank.track(0, 0).unwrap(), 0.5);
        assert!((mid[2][0] - 0.02).abs() < 1e-6);
    }
}

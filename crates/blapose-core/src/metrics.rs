//! Evaluation metrics for 3D pose sequences, as the Human3.6M literature
//! (VideoPose3D and BLAPose) computes them.
//!
//! Units: every metric returns the units of its inputs (metres in, metres
//! out; multiply by [`MM_PER_M`] for the millimetres papers report). MPJVE is
//! per frame of the input (`m/frame` at 50 Hz for Human3.6M).
//!
//! - MPJPE (protocol 1): mean Euclidean joint distance. Poses are compared as
//!   given; lifters emit root-relative poses, so pass root-relative ground
//!   truth ([`crate::pose::root_relative`]).
//! - P-MPJPE (protocol 2): MPJPE after aligning each predicted frame to the
//!   ground truth with the best similarity transform (rotation, uniform
//!   scale, translation; orthogonal Procrustes with the reflection fix so the
//!   "rotation" is never a mirror).
//! - N-MPJPE: MPJPE after the best per-frame uniform scale (no centring,
//!   like VideoPose3D: inputs are root-relative).
//! - MPJVE: mean distance between predicted and true joint velocities
//!   (first differences over time).
//! - Bone-length error: mean absolute difference of the 16 bone lengths,
//!   per bone and overall.
//! - Action aggregation ([`ActionAggregator`]): a frame-weighted mean per
//!   action (all takes, subjects and cameras of that action), then the
//!   unweighted mean over actions.
//! - [`PoseMetrics`]: the millimetre summary of one set of poses, the one
//!   shape the client's before/after table ([`Evaluation`], [`evaluate`])
//!   and the trainer's adjustment tables both report and serialize.
//!
//! Non-finite inputs propagate (the result is NaN): metrics report, they do
//! not validate. All sums are accumulated in `f64`.

use std::collections::BTreeMap;
use std::fmt;

use nalgebra::{Matrix3, Vector3};
use serde::{Deserialize, Serialize};

use crate::bones::bone_lengths;
use crate::pose::{root_relative, BoneLengths, Pose};
use crate::skeleton::{NUM_BONES, NUM_JOINTS};

/// Millimetres per metre.
pub const MM_PER_M: f64 = 1000.0;

/// Why a metric could not be computed.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum MetricError {
    /// Prediction and ground truth have different numbers of frames.
    #[error("prediction has {pred} frames but ground truth has {gt}")]
    LengthMismatch {
        /// Predicted frames.
        pred: usize,
        /// Ground-truth frames.
        gt: usize,
    },
    /// Not enough frames (`needed` or more).
    #[error("need at least {needed} frames, got {got}")]
    TooShort {
        /// Minimum number of frames.
        needed: usize,
        /// Frames given.
        got: usize,
    },
}

fn check_pair<A, B>(pred: &[A], gt: &[B], needed: usize) -> Result<(), MetricError> {
    if pred.len() != gt.len() {
        return Err(MetricError::LengthMismatch {
            pred: pred.len(),
            gt: gt.len(),
        });
    }
    if pred.len() < needed {
        return Err(MetricError::TooShort {
            needed,
            got: pred.len(),
        });
    }
    Ok(())
}

#[inline]
fn dist(a: [f64; 3], b: [f32; 3]) -> f64 {
    let d = [a[0] - b[0] as f64, a[1] - b[1] as f64, a[2] - b[2] as f64];
    (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt()
}

fn to_f64(p: &Pose) -> [[f64; 3]; NUM_JOINTS] {
    p.map(|j| j.map(f64::from))
}

fn mean_dist(pred: &[[f64; 3]; NUM_JOINTS], gt: &Pose) -> f64 {
    pred.iter().zip(gt).map(|(a, b)| dist(*a, *b)).sum::<f64>() / NUM_JOINTS as f64
}

/// Mean of a per-frame quantity over a sequence.
fn mean_over<F: Fn(&Pose, &Pose) -> f64>(
    pred: &[Pose],
    gt: &[Pose],
    f: F,
) -> Result<f64, MetricError> {
    check_pair(pred, gt, 1)?;
    Ok(pred.iter().zip(gt).map(|(p, g)| f(p, g)).sum::<f64>() / pred.len() as f64)
}

fn per_frame<F: Fn(&Pose, &Pose) -> f64>(
    pred: &[Pose],
    gt: &[Pose],
    f: F,
) -> Result<Vec<f64>, MetricError> {
    check_pair(pred, gt, 0)?;
    Ok(pred.iter().zip(gt).map(|(p, g)| f(p, g)).collect())
}

/// Per-joint Euclidean distances of one frame.
pub fn joint_errors(pred: &Pose, gt: &Pose) -> [f64; NUM_JOINTS] {
    std::array::from_fn(|j| dist(pred[j].map(f64::from), gt[j]))
}

/// MPJPE of one frame.
pub fn pose_mpjpe(pred: &Pose, gt: &Pose) -> f64 {
    mean_dist(&to_f64(pred), gt)
}

/// MPJPE (protocol 1) over a sequence.
pub fn mpjpe(pred: &[Pose], gt: &[Pose]) -> Result<f64, MetricError> {
    mean_over(pred, gt, pose_mpjpe)
}

/// MPJPE of every frame.
pub fn mpjpe_per_frame(pred: &[Pose], gt: &[Pose]) -> Result<Vec<f64>, MetricError> {
    per_frame(pred, gt, pose_mpjpe)
}

/// The similarity transform of `pred` closest to `gt` (least squares over
/// joints): `a * R * pred + t` with `R` a proper rotation (det +1).
///
/// Degenerate inputs have a defined answer: a prediction with all joints at
/// one point aligns to the ground truth's centroid (scale 0).
pub fn procrustes_align(pred: &Pose, gt: &Pose) -> [[f64; 3]; NUM_JOINTS] {
    let x = to_f64(gt);
    let y = to_f64(pred);
    let centroid = |p: &[[f64; 3]; NUM_JOINTS]| {
        p.iter()
            .fold(Vector3::zeros(), |s, j| s + Vector3::from(*j))
            / NUM_JOINTS as f64
    };
    let mu_x = centroid(&x);
    let mu_y = centroid(&y);
    // H = X0^T Y0 (3x3), rows of X0/Y0 are centred joints.
    let mut h = Matrix3::<f64>::zeros();
    let mut norm_y2 = 0.0;
    for j in 0..NUM_JOINTS {
        let xj = Vector3::from(x[j]) - mu_x;
        let yj = Vector3::from(y[j]) - mu_y;
        h += xj * yj.transpose();
        norm_y2 += yj.norm_squared();
    }
    if norm_y2 <= f64::MIN_POSITIVE || !norm_y2.is_finite() {
        return [[mu_x.x, mu_x.y, mu_x.z]; NUM_JOINTS];
    }
    let svd = h.svd(true, true);
    let (Some(u), Some(v_t)) = (svd.u, svd.v_t) else {
        return [[f64::NAN; 3]; NUM_JOINTS];
    };
    let mut s = svd.singular_values;
    let mut v = v_t.transpose();
    // Row-vector convention: aligned_j = a * y_j^T R + mu_x with R = V U^T.
    let mut r = v * u.transpose();
    if r.determinant() < 0.0 {
        // Reflection fix: flip the axis of the smallest singular value.
        let k = s.imin();
        v.column_mut(k).neg_mut();
        s[k] = -s[k];
        r = v * u.transpose();
    }
    let a = s.sum() / norm_y2;
    std::array::from_fn(|j| {
        let yj = (Vector3::from(y[j]) - mu_y).transpose();
        let aligned = (yj * r).transpose() * a + mu_x;
        [aligned.x, aligned.y, aligned.z]
    })
}

/// P-MPJPE of one frame.
pub fn pose_p_mpjpe(pred: &Pose, gt: &Pose) -> f64 {
    mean_dist(&procrustes_align(pred, gt), gt)
}

/// P-MPJPE (protocol 2) over a sequence (alignment per frame).
pub fn p_mpjpe(pred: &[Pose], gt: &[Pose]) -> Result<f64, MetricError> {
    mean_over(pred, gt, pose_p_mpjpe)
}

/// P-MPJPE of every frame.
pub fn p_mpjpe_per_frame(pred: &[Pose], gt: &[Pose]) -> Result<Vec<f64>, MetricError> {
    per_frame(pred, gt, pose_p_mpjpe)
}

/// N-MPJPE of one frame: scale `pred` by `<gt, pred> / <pred, pred>`
/// (0 for an all-zero prediction), then MPJPE.
pub fn pose_n_mpjpe(pred: &Pose, gt: &Pose) -> f64 {
    let y = to_f64(pred);
    let x = to_f64(gt);
    let (mut xy, mut yy) = (0.0, 0.0);
    for j in 0..NUM_JOINTS {
        for i in 0..3 {
            xy += x[j][i] * y[j][i];
            yy += y[j][i] * y[j][i];
        }
    }
    let s = if yy > 0.0 { xy / yy } else { 0.0 };
    mean_dist(&y.map(|p| p.map(|v| v * s)), gt)
}

/// N-MPJPE over a sequence.
pub fn n_mpjpe(pred: &[Pose], gt: &[Pose]) -> Result<f64, MetricError> {
    mean_over(pred, gt, pose_n_mpjpe)
}

/// MPJVE: mean over frames `1..T` and joints of
/// `|(pred[t] - pred[t-1]) - (gt[t] - gt[t-1])|`. Needs two frames.
pub fn mpjve(pred: &[Pose], gt: &[Pose]) -> Result<f64, MetricError> {
    check_pair(pred, gt, 2)?;
    let mut sum = 0.0;
    for t in 1..pred.len() {
        for j in 0..NUM_JOINTS {
            let d: [f64; 3] = std::array::from_fn(|i| {
                (pred[t][j][i] as f64 - pred[t - 1][j][i] as f64)
                    - (gt[t][j][i] as f64 - gt[t - 1][j][i] as f64)
            });
            sum += (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        }
    }
    Ok(sum / ((pred.len() - 1) * NUM_JOINTS) as f64)
}

/// Acceleration error: mean over frames `1..T-1` and joints of
/// `|(pred[t+1] - 2 pred[t] + pred[t-1]) - (gt[t+1] - 2 gt[t] + gt[t-1])|`
/// (input units per frame²). Needs three frames.
pub fn accel_error(pred: &[Pose], gt: &[Pose]) -> Result<f64, MetricError> {
    check_pair(pred, gt, 3)?;
    let mut sum = 0.0;
    for t in 1..pred.len() - 1 {
        for j in 0..NUM_JOINTS {
            let d: [f64; 3] = std::array::from_fn(|i| {
                let a = |s: &[Pose]| {
                    s[t + 1][j][i] as f64 - 2.0 * s[t][j][i] as f64 + s[t - 1][j][i] as f64
                };
                a(pred) - a(gt)
            });
            sum += (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        }
    }
    Ok(sum / ((pred.len() - 2) * NUM_JOINTS) as f64)
}

/// Mean root position error (MRPE): the mean distance between predicted
/// and true root positions (input units).
pub fn mrpe(pred: &[[f64; 3]], gt: &[[f64; 3]]) -> Result<f64, MetricError> {
    check_pair(pred, gt, 1)?;
    let sum: f64 = pred
        .iter()
        .zip(gt)
        .map(|(p, g)| {
            ((p[0] - g[0]).powi(2) + (p[1] - g[1]).powi(2) + (p[2] - g[2]).powi(2)).sqrt()
        })
        .sum();
    Ok(sum / pred.len() as f64)
}

/// Mean absolute bone-length error, per bone and overall (input units).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BoneLengthError {
    /// Mean absolute error of each bone.
    pub per_bone: [f64; NUM_BONES],
    /// Mean over the 16 bones.
    pub mean: f64,
}

impl BoneLengthError {
    /// The same error scaled (e.g. by [`MM_PER_M`]).
    pub fn scaled(&self, factor: f64) -> Self {
        Self {
            per_bone: self.per_bone.map(|v| v * factor),
            mean: self.mean * factor,
        }
    }
}

/// Bone-length error between paired length sets (e.g. a model's prediction
/// per sequence vs the subject's true lengths).
pub fn bone_length_error(
    pred: &[BoneLengths],
    gt: &[BoneLengths],
) -> Result<BoneLengthError, MetricError> {
    check_pair(pred, gt, 1)?;
    let mut per_bone = [0.0f64; NUM_BONES];
    for (p, g) in pred.iter().zip(gt) {
        for b in 0..NUM_BONES {
            per_bone[b] += (p[b] as f64 - g[b] as f64).abs();
        }
    }
    let per_bone = per_bone.map(|s| s / pred.len() as f64);
    Ok(BoneLengthError {
        per_bone,
        mean: per_bone.iter().sum::<f64>() / NUM_BONES as f64,
    })
}

/// Bone-length error of predicted poses against ground-truth poses, frame
/// by frame (how lifters' bone lengths are scored).
pub fn pose_bone_length_error(pred: &[Pose], gt: &[Pose]) -> Result<BoneLengthError, MetricError> {
    check_pair(pred, gt, 1)?;
    let p: Vec<BoneLengths> = pred.iter().map(bone_lengths).collect();
    let g: Vec<BoneLengths> = gt.iter().map(bone_lengths).collect();
    bone_length_error(&p, &g)
}

/// The action of a Human3.6M sequence name: the take number is dropped
/// (`"Walking 1"` -> `"Walking"`, `"Walking"` -> `"Walking"`). A key with a
/// subject prefix (`"S9/Walking 1"` or `"S9/Walking 1/54138969"`) is
/// reduced to its sequence part first.
pub fn action_name(sequence: &str) -> &str {
    let seq = match sequence.split('/').nth(1) {
        Some(s) => s,
        None => sequence,
    };
    match seq.rsplit_once(' ') {
        Some((head, take)) if !take.is_empty() && take.bytes().all(|b| b.is_ascii_digit()) => head,
        _ => seq,
    }
}

/// Frame-weighted accumulation per action, then an unweighted mean over
/// actions (the Human3.6M tables' "Avg" column).
#[derive(Debug, Clone, Default)]
pub struct ActionAggregator {
    sums: BTreeMap<String, (f64, usize)>,
}

impl ActionAggregator {
    /// An empty aggregator.
    pub fn new() -> Self {
        Self::default()
    }

    /// Add a sequence's per-frame errors under its sequence name (the take
    /// number is stripped with [`action_name`]).
    pub fn add_frames(&mut self, sequence: &str, errors: &[f64]) {
        let e = self
            .sums
            .entry(action_name(sequence).to_owned())
            .or_insert((0.0, 0));
        e.0 += errors.iter().sum::<f64>();
        e.1 += errors.len();
    }

    /// Add a sequence's mean error over `frames` frames.
    pub fn add_mean(&mut self, sequence: &str, mean: f64, frames: usize) {
        let e = self
            .sums
            .entry(action_name(sequence).to_owned())
            .or_insert((0.0, 0));
        e.0 += mean * frames as f64;
        e.1 += frames;
    }

    /// Mean error of each action (actions with zero frames are left out),
    /// sorted by action name.
    pub fn per_action(&self) -> Vec<(String, f64)> {
        self.sums
            .iter()
            .filter(|(_, (_, n))| *n > 0)
            .map(|(a, (s, n))| (a.clone(), s / *n as f64))
            .collect()
    }

    /// Mean over actions of the per-action means; `None` when empty.
    pub fn mean_over_actions(&self) -> Option<f64> {
        let per = self.per_action();
        (!per.is_empty()).then(|| per.iter().map(|(_, v)| v).sum::<f64>() / per.len() as f64)
    }
}

/// Accuracy of one set of poses, in millimetres (MPJVE in millimetres per
/// frame).
///
/// Serialized as `{"mpjpe_mm":..,"p_mpjpe_mm":..,"bone_error_mm":..}`, with
/// `"mpjve_mm"` between the second and the third only when it was computed.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PoseMetrics {
    /// MPJPE (protocol 1).
    pub mpjpe_mm: f64,
    /// P-MPJPE (protocol 2, similarity-aligned).
    pub p_mpjpe_mm: f64,
    /// MPJVE, when computed (the trainer's tables); `None` where only
    /// positions are compared (the client's before/after table).
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub mpjve_mm: Option<f64>,
    /// Mean absolute bone-length error over the 16 bones and all frames.
    pub bone_error_mm: f64,
}

/// Accuracy of `pred` against `gt`, both moved to a pelvis at the origin
/// for MPJPE (P-MPJPE and bone lengths do not depend on translation), as
/// lifters are scored under protocol 1; MPJVE is not computed.
pub fn pose_metrics(pred: &[Pose], gt: &[Pose]) -> Result<PoseMetrics, MetricError> {
    let pred_rel: Vec<Pose> = pred.iter().map(root_relative).collect();
    let gt_rel: Vec<Pose> = gt.iter().map(root_relative).collect();
    Ok(PoseMetrics {
        mpjpe_mm: mpjpe(&pred_rel, &gt_rel)? * MM_PER_M,
        p_mpjpe_mm: p_mpjpe(&pred_rel, &gt_rel)? * MM_PER_M,
        mpjve_mm: None,
        bone_error_mm: pose_bone_length_error(pred, gt)?.mean * MM_PER_M,
    })
}

/// A lifter's accuracy and the adjusted accuracy on one sequence: what an
/// adjustment did, as `blapose-client` prints it (a table, via `Display`)
/// and writes it (`{"frames":T,"before":{..},"after":{..}}`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Evaluation {
    /// Frames compared.
    pub frames: usize,
    /// The poses before the adjustment (the lifter's).
    pub before: PoseMetrics,
    /// The adjusted poses.
    pub after: PoseMetrics,
}

/// Compare the lifter's poses and the adjusted poses with the ground truth
/// ([`pose_metrics`] for each).
pub fn evaluate(
    lifted: &[Pose],
    adjusted: &[Pose],
    gt: &[Pose],
) -> Result<Evaluation, MetricError> {
    Ok(Evaluation {
        frames: gt.len(),
        before: pose_metrics(lifted, gt)?,
        after: pose_metrics(adjusted, gt)?,
    })
}

/// The relative change from `before` to `after`, or `-` without a base.
fn change(before: f64, after: f64) -> String {
    if before > 0.0 {
        format!("{:+.1}%", (after - before) / before * 100.0)
    } else {
        "-".to_string()
    }
}

impl fmt::Display for Evaluation {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(
            f,
            "{:<18} {:>10} {:>10} {:>9}",
            format!("{} frames", self.frames),
            "before",
            "after",
            "change"
        )?;
        let rows = [
            ("MPJPE (mm)", self.before.mpjpe_mm, self.after.mpjpe_mm),
            (
                "P-MPJPE (mm)",
                self.before.p_mpjpe_mm,
                self.after.p_mpjpe_mm,
            ),
            (
                "bone error (mm)",
                self.before.bone_error_mm,
                self.after.bone_error_mm,
            ),
        ];
        for (name, b, a) in rows {
            writeln!(f, "{name:<18} {b:>10.2} {a:>10.2} {:>9}", change(b, a))?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use approx::assert_relative_eq;

    fn pose(scale: f32, shift: f32) -> Pose {
        std::array::from_fn(|j| {
            let j = j as f32;
            [
                scale * (0.1 * j).sin() + shift,
                scale * 0.07 * j + shift,
                scale * (0.3 * j).cos() + shift,
            ]
        })
    }

    #[test]
    fn identical_poses_score_zero_and_translation_is_ignored() {
        let gt = vec![pose(1.0, 0.0); 3];
        let moved = vec![pose(1.0, 2.5); 3];
        let m = pose_metrics(&moved, &gt).unwrap();
        assert!(
            m.mpjpe_mm < 1e-3 && m.p_mpjpe_mm < 1e-3 && m.bone_error_mm < 1e-3,
            "{m:?}"
        );
        assert_eq!(m.mpjve_mm, None, "positions only");
    }

    #[test]
    fn scaled_pose_has_the_expected_bone_error() {
        let gt = vec![pose(1.0, 0.0); 2];
        let big = vec![pose(1.1, 0.0); 2];
        let m = pose_metrics(&big, &gt).unwrap();
        let mean_len = bone_lengths(&gt[0]).iter().map(|&l| l as f64).sum::<f64>() / 16.0;
        assert_relative_eq!(
            m.bone_error_mm,
            0.1 * mean_len * 1000.0,
            max_relative = 1e-4
        );
        // A uniformly scaled pose is perfect after similarity alignment.
        assert!(m.p_mpjpe_mm < 1e-2, "{m:?}");
        assert!(m.mpjpe_mm > 1.0);
    }

    #[test]
    fn evaluation_compares_both_sides_and_prints_a_table() {
        let gt = vec![pose(1.0, 0.0); 2];
        let e = evaluate(&[pose(1.1, 0.0), pose(1.1, 0.0)], &gt, &gt).unwrap();
        assert_eq!(e.frames, 2);
        assert!(e.before.bone_error_mm > 1.0 && e.after.bone_error_mm < 1e-3);
        let table = e.to_string();
        assert!(table.starts_with("2 frames"), "{table}");
        assert!(table.contains("bone error (mm)"), "{table}");
        assert!(table.contains("-100.0%"), "{table}");
        assert!(matches!(
            evaluate(&gt[..1], &gt, &gt),
            Err(MetricError::LengthMismatch { .. })
        ));
    }
}

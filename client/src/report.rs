//! Before/after accuracy of an adjustment against ground truth.
//!
//! The metrics themselves live in [`blapose_core::metrics`]; this module only
//! decides what to compare (the lifter's poses and the adjusted poses, each
//! against `gt_3d`, both root-relative as lifters are scored under
//! protocol 1) and how to present it: a small table for people and the JSON
//! shape `{"frames":T,"before":{..},"after":{..}}` for scripts.

use std::fmt;

use blapose_core::metrics::{mpjpe, p_mpjpe, pose_bone_length_error, MetricError, MM_PER_M};
use blapose_core::pose::root_relative;
use blapose_core::Pose;
use serde::{Deserialize, Serialize};

/// Accuracy of one set of poses, in millimetres.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PoseMetrics {
    /// MPJPE (protocol 1, root-relative).
    pub mpjpe_mm: f64,
    /// P-MPJPE (protocol 2, similarity-aligned).
    pub p_mpjpe_mm: f64,
    /// Mean absolute bone-length error over the 16 bones and all frames.
    pub bone_error_mm: f64,
}

/// The lifter's accuracy and the adjusted accuracy on one sequence.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Evaluation {
    /// Frames compared.
    pub frames: usize,
    /// The lifter's poses (`pose_3d`).
    pub before: PoseMetrics,
    /// The adjusted poses.
    pub after: PoseMetrics,
}

/// Accuracy of `pred` against `gt` (both moved to a pelvis at the origin
/// for MPJPE; P-MPJPE and bone lengths do not depend on translation).
pub fn pose_metrics(pred: &[Pose], gt: &[Pose]) -> Result<PoseMetrics, MetricError> {
    let pred_rel: Vec<Pose> = pred.iter().map(root_relative).collect();
    let gt_rel: Vec<Pose> = gt.iter().map(root_relative).collect();
    Ok(PoseMetrics {
        mpjpe_mm: mpjpe(&pred_rel, &gt_rel)? * MM_PER_M,
        p_mpjpe_mm: p_mpjpe(&pred_rel, &gt_rel)? * MM_PER_M,
        bone_error_mm: pose_bone_length_error(pred, gt)?.mean * MM_PER_M,
    })
}

/// Compare the lifter's poses and the adjusted poses with the ground truth.
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
    }

    #[test]
    fn scaled_pose_has_the_expected_bone_error() {
        let gt = vec![pose(1.0, 0.0); 2];
        let big = vec![pose(1.1, 0.0); 2];
        let m = pose_metrics(&big, &gt).unwrap();
        let mean_len = blapose_core::bones::bone_lengths(&gt[0])
            .iter()
            .map(|&l| l as f64)
            .sum::<f64>()
            / 16.0;
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
    fn json_has_the_documented_shape() {
        let gt = vec![pose(1.0, 0.0); 2];
        let e = evaluate(&[pose(1.1, 0.0), pose(1.1, 0.0)], &gt, &gt).unwrap();
        let v: serde_json::Value = serde_json::to_value(e).unwrap();
        assert_eq!(v["frames"], 2);
        for side in ["before", "after"] {
            for k in ["mpjpe_mm", "p_mpjpe_mm", "bone_error_mm"] {
                assert!(v[side][k].is_number(), "{side}.{k} in {v}");
            }
        }
        assert!(e.to_string().contains("bone error (mm)"));
        assert!(matches!(
            evaluate(&gt[..1], &gt, &gt),
            Err(MetricError::LengthMismatch { .. })
        ));
    }
}

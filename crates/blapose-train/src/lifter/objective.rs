//! What a lifter is trained to minimise.
//!
//! * [`Objective::Mpjpe`]: the lifter's own joints against the ground
//!   truth (training from scratch).
//! * [`Objective::Adjusted`]: the paper's fine-tuning objective, `L =
//!   L_direction + L_MPJPE`. The lifter's pose is rebuilt from its own bone
//!   directions and the lengths a *frozen* bone-length model predicted for
//!   the stream ([`AdjustmentGraph`]), and `L_MPJPE` scores that rebuilt
//!   pose; `L_direction` is the mean Euclidean distance between the
//!   predicted and true unit bone directions (the reference's direction
//!   error). The lengths do not depend on the lifter, so the gradient flows
//!   through the directions only: the lifter learns the directions that work
//!   best *after* adjustment, which is what a served pose is.
//!
//! The adjustment here is the differentiable twin of
//! `blapose_core::bones::adjust_pose` (pelvis at the origin): bones are
//! child minus parent (a fixed incidence matrix), and joint `j` is the sum
//! of the scaled directions along its path from the pelvis (a fixed path
//! matrix). A test checks both agree.

use blapose_core::skeleton::{NUM_BONES, PARENTS, ROOT};
use blapose_core::NUM_JOINTS;
use candle_core::{Device, Tensor};
use serde::{Deserialize, Serialize};

use super::OUTPUT_DIM;
use crate::error::TrainError;

/// MPJPE loss (metres) of `(B, OUTPUT_DIM)` predictions.
pub fn mpjpe_loss(pred: &Tensor, target: &Tensor) -> Result<Tensor, TrainError> {
    let b = pred.dim(0)?;
    let d = (pred - target)?.reshape((b, OUTPUT_DIM / 3, 3))?;
    Ok((d.sqr()?.sum(2)? + 1e-12)?.sqrt()?.mean_all()?)
}

/// The training objective of a lifter run (`finetune --objective`; the
/// same spelling in a run's configuration).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "snake_case")]
pub enum Objective {
    /// MPJPE of the lifter's joints.
    #[default]
    Mpjpe,
    /// `L_direction + L_MPJPE` of the pose adjusted to given lengths.
    Adjusted,
}

/// Squared-norm floor when normalizing bone vectors (m^2): keeps the
/// gradient finite for a predicted bone of zero length.
const NORM_FLOOR: f64 = 1e-12;

/// The skeleton as two constant matrices over the 16 non-pelvis joints.
pub struct AdjustmentGraph {
    /// `(16 bones, 16 joints)`: bone `b` = joint `b + 1` minus its parent.
    incidence: Tensor,
    /// `(16 joints, 16 bones)`: 1 where the bone lies on the joint's path
    /// from the pelvis.
    paths: Tensor,
}

impl AdjustmentGraph {
    /// Build the matrices of the Human3.6M-17 skeleton.
    pub fn new() -> Result<Self, TrainError> {
        let n = NUM_JOINTS - 1;
        let mut incidence = vec![0.0f32; NUM_BONES * n];
        let mut paths = vec![0.0f32; n * NUM_BONES];
        for b in 0..NUM_BONES {
            let child = b + 1;
            incidence[b * n + (child - 1)] = 1.0;
            if PARENTS[child] != ROOT {
                incidence[b * n + (PARENTS[child] - 1)] = -1.0;
            }
        }
        for joint in 1..NUM_JOINTS {
            let mut j = joint;
            while j != ROOT {
                paths[(joint - 1) * NUM_BONES + (j - 1)] = 1.0;
                j = PARENTS[j];
            }
        }
        Ok(Self {
            incidence: Tensor::from_vec(incidence, (NUM_BONES, n), &Device::Cpu)?,
            paths: Tensor::from_vec(paths, (n, NUM_BONES), &Device::Cpu)?,
        })
    }

    /// `(B, 48)` joints 1..17 -> `(B, 16, 3)` unit bone directions.
    pub fn directions(&self, joints: &Tensor) -> Result<Tensor, TrainError> {
        let b = joints.dim(0)?;
        let bones = self
            .incidence
            .broadcast_matmul(&joints.reshape((b, NUM_JOINTS - 1, 3))?)?;
        let norm = (bones.sqr()?.sum_keepdim(2)? + NORM_FLOOR)?.sqrt()?;
        Ok(bones.broadcast_div(&norm)?)
    }

    /// `(B, 16, 3)` directions and `(B, 16)` lengths -> `(B, 48)` joints
    /// 1..17 with the pelvis at the origin.
    pub fn rebuild(&self, directions: &Tensor, lengths: &Tensor) -> Result<Tensor, TrainError> {
        let b = directions.dim(0)?;
        let bones = directions.broadcast_mul(&lengths.unsqueeze(2)?)?;
        Ok(self
            .paths
            .broadcast_matmul(&bones)?
            .reshape((b, OUTPUT_DIM))?)
    }

    /// The fine-tuning loss of `(B, 48)` predictions against `(B, 48)`
    /// targets with `(B, 16)` lengths (metres): `(total, L_direction,
    /// L_MPJPE)` with `total = direction_weight * L_direction + L_MPJPE`
    /// (the paper's weight is 1), a scalar tensor to differentiate.
    pub fn loss(
        &self,
        pred: &Tensor,
        target: &Tensor,
        lengths: &Tensor,
        direction_weight: f64,
    ) -> Result<(Tensor, f64, f64), TrainError> {
        let dirs = self.directions(pred)?;
        let true_dirs = self.directions(target)?.detach();
        let l_dir = ((dirs.clone() - true_dirs)?.sqr()?.sum(2)? + NORM_FLOOR)?
            .sqrt()?
            .mean_all()?;
        let l_mpjpe = mpjpe_loss(&self.rebuild(&dirs, lengths)?, target)?;
        let (d, m) = (
            f64::from(l_dir.to_scalar::<f32>()?),
            f64::from(l_mpjpe.to_scalar::<f32>()?),
        );
        Ok((((l_dir * direction_weight)? + l_mpjpe)?, d, m))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lifter::pose_to_target;
    use blapose_core::bones::{adjust_pose, bone_lengths};
    use blapose_core::Pose;

    fn pose(seed: f32) -> Pose {
        std::array::from_fn(|j| {
            if j == 0 {
                [0.0; 3]
            } else {
                let t = seed + j as f32;
                [0.3 * t.sin(), 0.2 * (1.7 * t).cos(), 0.1 * (0.3 * t).sin()]
            }
        })
    }

    #[test]
    fn rebuild_matches_the_core_adjustment() {
        let g = AdjustmentGraph::new().unwrap();
        let (p, q) = (pose(0.5), pose(2.0));
        let lengths = bone_lengths(&q);
        let x = Tensor::from_slice(&pose_to_target(&p), (1, OUTPUT_DIM), &Device::Cpu).unwrap();
        let l = Tensor::from_slice(&lengths, (1, NUM_BONES), &Device::Cpu).unwrap();
        let ours = g
            .rebuild(&g.directions(&x).unwrap(), &l)
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1::<f32>()
            .unwrap();
        let core = pose_to_target(&adjust_pose(&p, &lengths).unwrap());
        for (a, b) in ours.iter().zip(&core) {
            assert!((a - b).abs() < 1e-5, "{a} vs {b}");
        }
    }

    #[test]
    fn loss_ignores_length_errors_and_sees_direction_errors() {
        let g = AdjustmentGraph::new().unwrap();
        let truth = pose(1.0);
        let row = |p: &Pose| {
            Tensor::from_slice(&pose_to_target(p), (1, OUTPUT_DIM), &Device::Cpu).unwrap()
        };
        let t = row(&truth);
        let l = Tensor::from_slice(&bone_lengths(&truth), (1, NUM_BONES), &Device::Cpu).unwrap();
        // Every bone twice as long, same directions: the adjustment undoes it.
        let doubled: Pose = std::array::from_fn(|j| truth[j].map(|v| 2.0 * v));
        let (_, d, m) = g.loss(&row(&doubled), &t, &l, 1.0).unwrap();
        assert!(d < 1e-4 && m < 1e-5, "{d} {m}");
        // Other directions cost in both terms, and the gradient reaches the
        // prediction.
        let wrong = candle_core::Var::from_tensor(&row(&pose(1.3))).unwrap();
        let (total, d, m) = g.loss(wrong.as_tensor(), &t, &l, 1.0).unwrap();
        assert!(d > 0.01 && m > 0.001, "{d} {m}");
        let grads = total.backward().unwrap();
        let grad = grads.get(wrong.as_tensor()).unwrap().flatten_all().unwrap();
        let grad = grad.to_vec1::<f32>().unwrap();
        assert!(grad.iter().all(|v| v.is_finite()) && grad.iter().any(|v| *v != 0.0));
    }
}

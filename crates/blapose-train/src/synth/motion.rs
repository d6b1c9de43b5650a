//! The motion synthetic samples are built from: a training sequence's root
//! trajectory and bone directions (decomposed once), sampled at fractional
//! frames, and rebuilt with other lengths on the same floor.

use std::sync::Arc;

use blapose_core::bones::rebuild;
use blapose_core::camera::Camera;
use blapose_core::{BoneDirections, BoneLengths, Pose};

/// One training sequence of a training subject, pre-decomposed.
#[derive(Debug, Clone)]
pub struct MotionSequence {
    /// Subject, e.g. `"S1"`.
    pub subject: String,
    /// Sequence name, e.g. `"Walking 1"`.
    pub action: String,
    /// World-space root (pelvis) position per frame, metres.
    pub roots: Vec<[f32; 3]>,
    /// Unit bone directions per frame (world space).
    pub dirs: Vec<BoneDirections>,
    /// The subject's bone lengths (mean over the sequence).
    pub lengths: BoneLengths,
    /// The subject's cameras.
    pub cameras: Arc<Vec<Camera>>,
}

impl MotionSequence {
    /// Number of frames.
    pub fn len(&self) -> usize {
        self.roots.len()
    }

    /// True when there are no frames.
    pub fn is_empty(&self) -> bool {
        self.roots.is_empty()
    }

    /// Root position and directions at fractional frame `u`.
    pub fn at(&self, u: f32) -> ([f32; 3], BoneDirections) {
        let last = self.len() - 1;
        let u = u.clamp(0.0, last as f32);
        let i = (u.floor() as usize).min(last);
        let k = (i + 1).min(last);
        let a = u - i as f32;
        let lerp3 = |p: [f32; 3], q: [f32; 3]| std::array::from_fn(|c| p[c] * (1.0 - a) + q[c] * a);
        let root = lerp3(self.roots[i], self.roots[k]);
        let dirs = std::array::from_fn(|b| {
            let d: [f32; 3] = lerp3(self.dirs[i][b], self.dirs[k][b]);
            let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
            // Opposite directions in consecutive frames (never seen in
            // mocap) would interpolate through zero: keep frame i's.
            if n > 1e-6 {
                d.map(|v| v / n)
            } else {
                self.dirs[i][b]
            }
        });
        (root, dirs)
    }
}

/// The world height (`z`, up in Human3.6M) of a pose's lowest joint.
pub fn lowest_height(pose: &Pose) -> f32 {
    pose.iter().map(|j| j[2]).fold(f32::INFINITY, f32::min)
}

/// [`rebuild`] with `lengths`, then lifted (or lowered) so that its
/// lowest joint is as high as in the pose rebuilt with the `original`
/// lengths: feet on the floor stay on it, a jump stays a jump.
pub fn rebuild_on_floor(
    root: [f32; 3],
    dirs: &BoneDirections,
    lengths: &BoneLengths,
    original: &BoneLengths,
) -> Pose {
    let mut pose = rebuild(root, dirs, lengths);
    let lift = lowest_height(&rebuild(root, dirs, original)) - lowest_height(&pose);
    pose.iter_mut().for_each(|j| j[2] += lift);
    pose
}

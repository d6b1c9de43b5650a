//! Where the person is: the pelvis position in camera space, solved from
//! the 2D keypoints and the root-relative 3D pose, and the camera's floor
//! frame for world coordinates.
//!
//! A person of size L at distance Z through a lens of focal f appears with
//! size f·L/Z: with the intrinsics and the person's true lengths, the 2D
//! keypoints fix the depth. Given the root-relative pose `X_j` and each
//! joint's viewing ray `(x_j, y_j)` (undistorted, `x = X/Z`), the pelvis
//! `T` satisfies `X_j + T ∝ (x_j, y_j, 1)`, two linear equations per joint:
//! `T_x - x_j T_z = x_j Z_j - X_j` and `T_y - y_j T_z = y_j Z_j - Y_j`. Their
//! weighted least-squares solution is [`solve_root`]. It is only as good
//! as the lengths: a skeleton 5 % too long is placed about 5 % too far.

use nalgebra::{Matrix3, Vector3};

use crate::pose::Pose;
use crate::skeleton::{NUM_JOINTS, ROOT};

/// Nearest depth a solved root may have (metres): nearer, the solve is
/// degenerate (keypoints mislabelled, a pose from another person).
pub const MIN_ROOT_DEPTH: f64 = 0.1;

/// How much each joint counts in the served root solve: every joint but
/// the neck/nose and the head, whose 2D detections (a head top, an
/// interpolated neck) are furthest from the skeleton's joints. Chosen on
/// held-out training trials among four joint sets (`blapose-lab motion`):
/// it placed the root 7 % (streamed) to 10 % (offline) closer than all
/// joints.
pub const ROOT_JOINT_WEIGHTS: [f64; NUM_JOINTS] = [
    1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 0.0, 0.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0,
];

/// Viewing rays of the 17 joints: undistorted image-plane coordinates
/// `(X/Z, Y/Z)` (pixels minus the principal point, over the focal length).
pub type Rays = [[f64; 2]; NUM_JOINTS];

/// The focal length assumed for a camera the client did not calibrate, as
/// a multiple of the image's larger side: about a 53° field of view across
/// that side, between a phone's main camera and a webcam.
pub const ASSUMED_FOCAL_PER_SIDE: f64 = 1.0;

/// The pelvis position in camera space (metres) that best explains the
/// rays for `pose` (taken relative to its own pelvis); `weights` per joint
/// (0 leaves a joint out). `None` when the system is degenerate or puts the
/// person behind or at the camera.
pub fn solve_root(rays: &Rays, pose: &Pose, weights: &[f64; NUM_JOINTS]) -> Option<[f64; 3]> {
    let mut a = Matrix3::<f64>::zeros();
    let mut b = Vector3::<f64>::zeros();
    for j in 0..NUM_JOINTS {
        let w = weights[j];
        if w <= 0.0 {
            continue;
        }
        let [x, y] = rays[j];
        let p: [f64; 3] = std::array::from_fn(|i| pose[j][i] as f64 - pose[ROOT][i] as f64);
        for (row, rhs) in [
            (Vector3::new(1.0, 0.0, -x), x * p[2] - p[0]),
            (Vector3::new(0.0, 1.0, -y), y * p[2] - p[1]),
        ] {
            a += w * row * row.transpose();
            b += w * rhs * row;
        }
    }
    let t = a.try_inverse()? * b;
    (t.iter().all(|v| v.is_finite()) && t[2] >= MIN_ROOT_DEPTH).then(|| [t[0], t[1], t[2]])
}

/// A camera's floor frame: world `z` up with the floor at 0, `y` the
/// optical axis turned horizontal, `x` to the camera's right; the origin on
/// the floor below the camera.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FloorFrame {
    /// Rows: world x, y, z axes in camera coordinates.
    axes: [[f64; 3]; 3],
    camera_height: f64,
}

/// Why a floor frame cannot be built.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum FloorFrameError {
    /// The up vector is zero, not finite, or along the optical axis.
    #[error("the camera's up direction must be a finite vector not parallel to the optical axis")]
    Up,
}

impl FloorFrame {
    /// From world "up" in camera coordinates (`x` right, `y` down, `z`
    /// forward; any length) and the camera's height above the floor.
    pub fn new(up: [f64; 3], camera_height: f64) -> Result<Self, FloorFrameError> {
        let up = Vector3::from(up);
        let n = up.norm();
        if !n.is_finite() || n == 0.0 {
            return Err(FloorFrameError::Up);
        }
        let z = up / n;
        let forward = Vector3::new(0.0, 0.0, 1.0);
        let y = forward - forward.dot(&z) * z;
        if y.norm() < 1e-6 {
            return Err(FloorFrameError::Up);
        }
        let y = y.normalize();
        let x = y.cross(&z);
        Ok(Self {
            axes: [x.into(), y.into(), z.into()],
            camera_height,
        })
    }

    /// A camera-space point in world coordinates (floor at height 0).
    pub fn to_world(&self, p: [f64; 3]) -> [f64; 3] {
        let dot = |a: [f64; 3]| a[0] * p[0] + a[1] * p[1] + a[2] * p[2];
        [
            dot(self.axes[0]),
            dot(self.axes[1]),
            dot(self.axes[2]) + self.camera_height,
        ]
    }

    /// World up in camera coordinates (unit).
    pub fn up(&self) -> [f64; 3] {
        self.axes[2]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pose() -> Pose {
        std::array::from_fn(|j| {
            let j = j as f32;
            [
                0.05 * (j % 4.0) - 0.1,
                0.1 * (j % 5.0) - 0.3,
                0.03 * (j % 3.0),
            ]
        })
    }

    #[test]
    fn recovers_the_root_from_exact_rays() {
        let mut p = pose();
        let r0 = p[0];
        for q in &mut p {
            *q = [q[0] - r0[0], q[1] - r0[1], q[2] - r0[2]];
        }
        let root = [0.4, -0.2, 4.5];
        let rays: Rays = std::array::from_fn(|j| {
            let q = [
                p[j][0] as f64 + root[0],
                p[j][1] as f64 + root[1],
                p[j][2] as f64 + root[2],
            ];
            [q[0] / q[2], q[1] / q[2]]
        });
        let got = solve_root(&rays, &p, &[1.0; NUM_JOINTS]).unwrap();
        for i in 0..3 {
            assert!((got[i] - root[i]).abs() < 1e-5, "{got:?}");
        }
        // The same rays with a skeleton 10 % larger put it 10 % further.
        let big: Pose = p.map(|q| q.map(|v| v * 1.1));
        let far = solve_root(&rays, &big, &[1.0; NUM_JOINTS]).unwrap();
        assert!((far[2] / root[2] - 1.1).abs() < 1e-4, "{far:?}");
        assert!(solve_root(&rays, &p, &[0.0; NUM_JOINTS]).is_none());
    }

    #[test]
    fn a_level_camera_puts_the_floor_below_it() {
        let f = FloorFrame::new([0.0, -1.0, 0.0], 1.5).unwrap();
        // A point 1.5 m below the camera and 3 m ahead is on the floor.
        let w = f.to_world([0.2, 1.5, 3.0]);
        assert!((w[0] - 0.2).abs() < 1e-12 && (w[1] - 3.0).abs() < 1e-12 && w[2].abs() < 1e-12);
        assert!(FloorFrame::new([0.0, 0.0, 1.0], 1.5).is_err());
    }
}

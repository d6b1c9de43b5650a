//! Fixed-size pose types and the operations that only relabel or mirror
//! joints (horizontal flips, flat-buffer views).
//!
//! Poses are plain arrays rather than matrices so that a `Vec<Pose>` is one
//! contiguous `f32` buffer (what the trainer batches and the npz files hold)
//! and so that no crate needs nalgebra just to pass a pose around.

use crate::skeleton::{flipped_joint, NUM_BONES, NUM_JOINTS};

/// A 3D pose: 17 joints x (x, y, z), Human3.6M joint order, metres.
pub type Pose = [[f32; 3]; NUM_JOINTS];
/// 2D keypoints in Human3.6M joint order (pixels or normalized coordinates).
pub type Keypoints2d = [[f32; 2]; NUM_JOINTS];
/// The 16 bone lengths, indexed like [`crate::skeleton::BONE_NAMES`].
pub type BoneLengths = [f32; NUM_BONES];
/// The 16 unit bone directions (child minus parent, normalized).
pub type BoneDirections = [[f32; 3]; NUM_BONES];

/// Values of one [`Pose`] in a flat buffer (the wire's and the npz files'
/// layout): 17 joints x 3.
pub const POSE_VALUES: usize = NUM_JOINTS * 3;
/// Values of one [`Keypoints2d`] frame in a flat buffer: 17 joints x 2.
pub const KEYPOINT_VALUES: usize = NUM_JOINTS * 2;

/// Mirror a 3D pose left/right: negate x and swap left and right joints.
///
/// In *camera* coordinates this is exactly what a horizontally flipped image
/// shows (see [`crate::camera::Camera::flipped`]). Applying it twice gives
/// the input back bit for bit.
pub fn flip_pose(pose: &Pose) -> Pose {
    let mut out = [[0.0; 3]; NUM_JOINTS];
    for (j, p) in pose.iter().enumerate() {
        out[flipped_joint(j)] = [-p[0], p[1], p[2]];
    }
    out
}

/// The bone lengths of the mirrored person ([`flip_pose`]): left and right
/// bones swap. Twice is the identity.
pub fn flip_bone_lengths(lengths: &BoneLengths) -> BoneLengths {
    let mut out = [0.0; NUM_BONES];
    for (b, l) in lengths.iter().enumerate() {
        // Bone `b` ends at joint `b + 1`.
        out[flipped_joint(b + 1) - 1] = *l;
    }
    out
}

/// Mirror Human3.6M-order keypoints in normalized screen coordinates:
/// `x -> -x` and swap left/right joints. Twice is the identity.
pub fn flip_keypoints_normalized(kp: &Keypoints2d) -> Keypoints2d {
    let mut out = [[0.0; 2]; NUM_JOINTS];
    for (j, p) in kp.iter().enumerate() {
        out[flipped_joint(j)] = [-p[0], p[1]];
    }
    out
}

/// Mirror Human3.6M-order keypoints in pixels for an image `width` pixels
/// wide: `u -> width - u` and swap left/right joints.
///
/// `width - u` (not `width - 1 - u`) is the mirror that corresponds to
/// negating normalized coordinates, which is the convention the camera flip
/// uses; twice is the identity up to f32 rounding.
pub fn flip_keypoints_pixels(kp: &Keypoints2d, width: u32) -> Keypoints2d {
    let w = width as f32;
    let mut out = [[0.0; 2]; NUM_JOINTS];
    for (j, p) in kp.iter().enumerate() {
        out[flipped_joint(j)] = [w - p[0], p[1]];
    }
    out
}

/// Subtract the root (pelvis) position from every joint.
pub fn root_relative(pose: &Pose) -> Pose {
    let r = pose[crate::skeleton::ROOT];
    pose.map(|p| [p[0] - r[0], p[1] - r[1], p[2] - r[2]])
}

/// View a slice of poses as one flat `f32` buffer (`T * 17 * 3` values).
pub fn poses_as_flat(poses: &[Pose]) -> &[f32] {
    poses.as_flattened().as_flattened()
}

/// Copy exactly `17 * 3` values, joint-major, into a pose; `None` for any
/// other length.
pub fn pose_from_flat(flat: &[f32]) -> Option<Pose> {
    let flat: &[f32; POSE_VALUES] = flat.try_into().ok()?;
    Some(std::array::from_fn(|j| {
        [flat[3 * j], flat[3 * j + 1], flat[3 * j + 2]]
    }))
}

/// Copy a flat `f32` buffer of `T * 17 * 3` values into poses; `None` when
/// the length is not a multiple of 51.
pub fn poses_from_flat(flat: &[f32]) -> Option<Vec<Pose>> {
    const N: usize = POSE_VALUES;
    if !flat.len().is_multiple_of(N) {
        return None;
    }
    flat.chunks_exact(N).map(pose_from_flat).collect()
}

/// Copy a flat `f32` buffer of `T * 17 * 2` values into keypoint frames;
/// `None` when the length is not a multiple of 34.
pub fn keypoints_from_flat(flat: &[f32]) -> Option<Vec<Keypoints2d>> {
    const N: usize = KEYPOINT_VALUES;
    if !flat.len().is_multiple_of(N) {
        return None;
    }
    Some(
        flat.chunks_exact(N)
            .map(|c| std::array::from_fn(|j| [c[2 * j], c[2 * j + 1]]))
            .collect(),
    )
}

/// True when every coordinate of the pose is finite.
pub fn is_finite(pose: &Pose) -> bool {
    pose.iter().flatten().all(|v| v.is_finite())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn flat_round_trip() {
        let poses: Vec<Pose> = (0..3)
            .map(|t| std::array::from_fn(|j| [t as f32, j as f32, 0.5]))
            .collect();
        let flat = poses_as_flat(&poses);
        assert_eq!(flat.len(), 3 * 51);
        assert_eq!(flat[51 + 3 * 2 + 1], 2.0);
        assert_eq!(poses_from_flat(flat).unwrap(), poses);
        assert!(poses_from_flat(&flat[1..]).is_none());
        assert_eq!(pose_from_flat(&flat[51..102]), Some(poses[1]));
        assert!(pose_from_flat(&flat[..50]).is_none());
        assert!(pose_from_flat(&flat[..102]).is_none());
        assert!(keypoints_from_flat(&[0.0; 33]).is_none());
        assert_eq!(keypoints_from_flat(&[1.0; 68]).unwrap().len(), 2);
    }

    #[test]
    fn flip_swaps_sides_and_negates_x() {
        let pose: Pose = std::array::from_fn(|j| [j as f32, 2.0 * j as f32, 1.0]);
        let f = flip_pose(&pose);
        // r_hip (1) and l_hip (4) swap; pelvis stays.
        assert_eq!(f[1], [-4.0, 8.0, 1.0]);
        assert_eq!(f[4], [-1.0, 2.0, 1.0]);
        assert_eq!(f[0], [0.0, 0.0, 1.0]);
        assert_eq!(flip_pose(&f), pose);
        let kp: Keypoints2d = std::array::from_fn(|j| [j as f32, 1.0]);
        assert_eq!(flip_keypoints_pixels(&kp, 1000)[16], [1000.0 - 13.0, 1.0]);
    }

    #[test]
    fn flipped_lengths_are_the_lengths_of_the_flipped_pose() {
        let pose: Pose = std::array::from_fn(|j| [0.1 * j as f32, (j * j) as f32 * 0.01, 0.3]);
        let flipped = flip_bone_lengths(&crate::bones::bone_lengths(&pose));
        let of_flipped = crate::bones::bone_lengths(&flip_pose(&pose));
        for (a, b) in flipped.iter().zip(&of_flipped) {
            assert!((a - b).abs() < 1e-6);
        }
        assert_ne!(flipped, crate::bones::bone_lengths(&pose));
        assert_eq!(
            flip_bone_lengths(&flipped),
            crate::bones::bone_lengths(&pose)
        );
    }
}

//! The Human3.6M 17-joint skeleton: joint names, the kinematic tree and the
//! 16 bones BLAPose predicts lengths for.
//!
//! Bone `i` (0-based) connects joint `i + 1` (the child) to its parent, so a
//! pose can be rebuilt by walking the bones in index order: every parent
//! precedes its children. All other crates index bones through this module.

/// Number of joints in the Human3.6M skeleton.
pub const NUM_JOINTS: usize = 17;
/// Number of bones (one per non-root joint).
pub const NUM_BONES: usize = 16;
/// Index of the root joint (pelvis).
pub const ROOT: usize = 0;

/// Joint names in Human3.6M order (`joints_17` in `cameras.json`).
pub const JOINT_NAMES: [&str; NUM_JOINTS] = [
    "pelvis",
    "r_hip",
    "r_knee",
    "r_ankle",
    "l_hip",
    "l_knee",
    "l_ankle",
    "spine",
    "thorax",
    "neck_nose",
    "head",
    "l_shoulder",
    "l_elbow",
    "l_wrist",
    "r_shoulder",
    "r_elbow",
    "r_wrist",
];

/// Parent of each joint; the root's parent is itself.
pub const PARENTS: [usize; NUM_JOINTS] = [0, 0, 1, 2, 0, 4, 5, 0, 7, 8, 9, 8, 11, 12, 8, 14, 15];

/// Bone names, bone `i` ends at joint `i + 1`.
pub const BONE_NAMES: [&str; NUM_BONES] = [
    "r_hip",
    "r_thigh",
    "r_calf",
    "l_hip",
    "l_thigh",
    "l_calf",
    "spine",
    "thorax",
    "neck",
    "head",
    "l_shoulder",
    "l_upper_arm",
    "l_forearm",
    "r_shoulder",
    "r_upper_arm",
    "r_forearm",
];

/// The six left/right pairs of bones `(right, left)` whose lengths are equal
/// in a real body: hip, thigh, calf, shoulder, upper arm, forearm.
pub const SYMMETRIC_BONE_PAIRS: [(usize, usize); 6] =
    [(0, 3), (1, 4), (2, 5), (13, 10), (14, 11), (15, 12)];

/// Joints on the left side, paired index-wise with [`RIGHT_JOINTS`]; a
/// horizontal flip swaps them.
pub const LEFT_JOINTS: [usize; 6] = [4, 5, 6, 11, 12, 13];
/// Joints on the right side, paired index-wise with [`LEFT_JOINTS`].
pub const RIGHT_JOINTS: [usize; 6] = [1, 2, 3, 14, 15, 16];

/// Child joint of bone `bone`.
#[inline]
pub const fn bone_child(bone: usize) -> usize {
    bone + 1
}

/// Parent joint of bone `bone`.
#[inline]
pub const fn bone_parent(bone: usize) -> usize {
    PARENTS[bone + 1]
}

/// The joint index a horizontal flip maps `joint` to (left <-> right).
pub fn flipped_joint(joint: usize) -> usize {
    if let Some(k) = LEFT_JOINTS.iter().position(|&j| j == joint) {
        RIGHT_JOINTS[k]
    } else if let Some(k) = RIGHT_JOINTS.iter().position(|&j| j == joint) {
        LEFT_JOINTS[k]
    } else {
        joint
    }
}

/// Index of a bone by name, e.g. `"l_forearm"`.
pub fn bone_index(name: &str) -> Option<usize> {
    BONE_NAMES.iter().position(|&n| n == name)
}

/// Index of a joint by name, e.g. `"r_wrist"`.
pub fn joint_index(name: &str) -> Option<usize> {
    JOINT_NAMES.iter().position(|&n| n == name)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parents_precede_children() {
        for b in 0..NUM_BONES {
            assert!(bone_parent(b) < bone_child(b), "bone {b}");
        }
    }

    #[test]
    fn symmetric_pairs_are_left_right_mirrors() {
        for &(r, l) in &SYMMETRIC_BONE_PAIRS {
            assert!(BONE_NAMES[r].starts_with("r_"), "{}", BONE_NAMES[r]);
            assert!(BONE_NAMES[l].starts_with("l_"), "{}", BONE_NAMES[l]);
            assert_eq!(BONE_NAMES[r][2..], BONE_NAMES[l][2..]);
            assert_eq!(flipped_joint(bone_child(r)), bone_child(l));
        }
    }

    #[test]
    fn flip_is_an_involution() {
        for j in 0..NUM_JOINTS {
            assert_eq!(flipped_joint(flipped_joint(j)), j);
            let name = JOINT_NAMES[j];
            let other = JOINT_NAMES[flipped_joint(j)];
            if let Some(rest) = name.strip_prefix("l_") {
                assert_eq!(other, format!("r_{rest}"));
            }
        }
    }
}

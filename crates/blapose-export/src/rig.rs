//! The BVH skeleton: 17 joints under blapose's joint names plus four helper
//! joints, the T-pose rest pose, each joint's channel order, and which bone
//! each joint's rotation aims and where its twist comes from.
//!
//! # Why four helper joints
//!
//! In BVH a joint's rotation moves all of its children rigidly, so the
//! pelvis's three children (`r_hip`, `l_hip`, `spine`) and the thorax's
//! (`neck_nose`, `l_shoulder`, `r_shoulder`) would have to keep fixed angles
//! between them. A lifter's poses do not (blapose keeps its bone directions),
//! and with only the 17 joints those six joints would miss their positions
//! by centimetres. So each hip bone and each shoulder bone gets a joint of
//! its own, at its parent's position (zero offset, rotation channels only):
//! `r_pelvis` and `l_pelvis` at the pelvis (their bones end at `r_hip` /
//! `l_hip`: the two halves of the pelvis), `r_clavicle` and `l_clavicle` at
//! the thorax (ending at `r_shoulder` / `l_shoulder`). This is the usual
//! motion-capture rig (CMU's BVH has `LHipJoint` and `LeftShoulder`), and
//! every one of the 17 joints then lands on its position.
//!
//! # Rest pose
//!
//! A T-pose in the Y-up frame ([`crate::axes`]), facing `+Z`, the person's
//! left along `+X`, pelvis at the origin: spine, thorax, neck and head bones
//! straight up (`+Y`), hip bones and both arms horizontal (`±X`), legs
//! straight down (`-Y`); each bone as long as the motion's length for it.
//! Leaves end in an End Site a quarter of their bone's length long: forward
//! (`+Z`) from the ankles (a foot), up from the head, outwards from the
//! wrists (a hand); the 17 joints have no toe, head-top or hand joint, so
//! these carry no data.

use blapose_core::skeleton::{bone_parent, NUM_BONES, NUM_JOINTS};
use blapose_core::BoneLengths;

use crate::rot::{add, scale, Order, Vec3};

const PX: Vec3 = [1.0, 0.0, 0.0];
const NX: Vec3 = [-1.0, 0.0, 0.0];
const PY: Vec3 = [0.0, 1.0, 0.0];
const NY: Vec3 = [0.0, -1.0, 0.0];
const PZ: Vec3 = [0.0, 0.0, 1.0];
const NZ: Vec3 = [0.0, 0.0, -1.0];

/// Channel orders. The outermost angle is the one with the largest range
/// and the middle one (where gimbal lock sits, at ±90 degrees) the bone's own
/// axis, whose twist stays small: heading first for the root, then the bone
/// axis in the middle (`Y` for vertical bones, `X` for horizontal ones).
const ROOT_ORDER: Order = [1, 0, 2]; // Yrotation Xrotation Zrotation
const VERTICAL: Order = [2, 1, 0]; // Zrotation Yrotation Xrotation
const HORIZONTAL: Order = [2, 0, 1]; // Zrotation Xrotation Yrotation

/// Which line fixes an absolute frame's twist.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Line {
    /// `r_hip` to `l_hip`.
    Hips,
    /// `r_shoulder` to `l_shoulder`.
    Shoulders,
    /// The mean direction of the two.
    HipsAndShoulders,
}

/// How a joint's rotation is found.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Aim {
    /// Its bone's direction, and for the twist a body line made
    /// perpendicular to it (its rest direction along `+X`): pelvis, spine,
    /// thorax. Absolute, so the body's heading never drifts.
    Frame(Line),
    /// The smallest rotation from its parent's frame that aims its bone (no
    /// twist of its own): the helpers, the neck, and the hinges (knee,
    /// elbow), whose twist is their parent's.
    Swing,
    /// A swing, then the twist about the bone that turns `rest_bend` (the
    /// direction the next bone bends to in the rest pose) into the plane of
    /// this bone and the next, the knee or elbow plane. The plane is only
    /// as good as the bend is clear, so the twist is held from frame to
    /// frame and moves towards the plane's by a weight that goes from 0 below
    /// [`BEND_RAMP_DEG`]`.0` degrees of bend (a straight limb keeps its last
    /// twist) to 1 above [`BEND_RAMP_DEG`]`.1` (the plane sets it). The
    /// sequence starts with the twist a backward pass ends with, its first
    /// clear plane. `fold`: the knee, which does not bend backwards, takes
    /// the twist modulo 180 degrees (a slightly hyperextended knee in noisy
    /// poses would otherwise spin the thigh half a turn).
    Bend {
        /// The joint at the end of the next bone (ankle, wrist).
        far: usize,
        /// The bend direction in the rest pose.
        rest_bend: Vec3,
        /// Twist modulo 180 degrees.
        fold: bool,
    },
    /// A leaf: no bone to aim, no rotation relative to its parent.
    Leaf {
        /// The End Site's direction in the rest pose.
        end: Vec3,
    },
}

/// One BVH joint.
#[derive(Debug, Clone, Copy)]
pub struct RigJoint {
    /// Its name in the file (and Blender's bone name).
    pub name: &'static str,
    /// Index of its parent in [`RIG`], `None` for the root.
    pub parent: Option<usize>,
    /// The Human3.6M joint at its position.
    pub at: usize,
    /// The Human3.6M joint its bone ends at (`None` for leaves).
    pub aim: Option<usize>,
    /// Its bone's direction in the rest pose.
    pub rest_dir: Vec3,
    /// Where its swing starts from, in the rest frame: the rest direction,
    /// except for the upper arms (see [`RIG`]).
    pub neutral: Vec3,
    /// Its rotation channels' order.
    pub order: Order,
    /// How its rotation is found.
    pub kind: Aim,
}

const fn j(
    name: &'static str,
    parent: Option<usize>,
    at: usize,
    aim: Option<usize>,
    rest_dir: Vec3,
    order: Order,
    kind: Aim,
) -> RigJoint {
    RigJoint {
        name,
        parent,
        at,
        aim,
        rest_dir,
        neutral: rest_dir,
        order,
        kind,
    }
}

/// The upper arms swing from a neutral direction forward and out (45
/// degrees from the T-pose's sideways one), so that the swing's singular
/// direction, its opposite (back and across the body), is one an arm cannot
/// take; from the T-pose direction, an arm reaching across the chest comes
/// close to it and its rotation turns fast under small changes.
const fn upper_arm(mut joint: RigJoint, neutral: Vec3) -> RigJoint {
    joint.neutral = neutral;
    joint
}

const H: f64 = std::f64::consts::FRAC_1_SQRT_2;

/// The 21 BVH joints, in file order (parents first).
#[rustfmt::skip]
pub const RIG: [RigJoint; 21] = [
    j("pelvis", None, 0, Some(7), PY, ROOT_ORDER, Aim::Frame(Line::Hips)),
    j("r_pelvis", Some(0), 0, Some(1), NX, HORIZONTAL, Aim::Swing),
    j("r_hip", Some(1), 1, Some(2), NY, VERTICAL, Aim::Bend { far: 3, rest_bend: NZ, fold: true }),
    j("r_knee", Some(2), 2, Some(3), NY, VERTICAL, Aim::Swing),
    j("r_ankle", Some(3), 3, None, NY, VERTICAL, Aim::Leaf { end: PZ }),
    j("l_pelvis", Some(0), 0, Some(4), PX, HORIZONTAL, Aim::Swing),
    j("l_hip", Some(5), 4, Some(5), NY, VERTICAL, Aim::Bend { far: 6, rest_bend: NZ, fold: true }),
    j("l_knee", Some(6), 5, Some(6), NY, VERTICAL, Aim::Swing),
    j("l_ankle", Some(7), 6, None, NY, VERTICAL, Aim::Leaf { end: PZ }),
    j("spine", Some(0), 7, Some(8), PY, VERTICAL, Aim::Frame(Line::HipsAndShoulders)),
    j("thorax", Some(9), 8, Some(9), PY, VERTICAL, Aim::Frame(Line::Shoulders)),
    j("neck_nose", Some(10), 9, Some(10), PY, VERTICAL, Aim::Swing),
    j("head", Some(11), 10, None, PY, VERTICAL, Aim::Leaf { end: PY }),
    j("l_clavicle", Some(10), 8, Some(11), PX, HORIZONTAL, Aim::Swing),
    upper_arm(j("l_shoulder", Some(13), 11, Some(12), PX, HORIZONTAL, Aim::Bend { far: 13, rest_bend: PZ, fold: false }), [H, 0.0, H]),
    j("l_elbow", Some(14), 12, Some(13), PX, HORIZONTAL, Aim::Swing),
    j("l_wrist", Some(15), 13, None, PX, HORIZONTAL, Aim::Leaf { end: PX }),
    j("r_clavicle", Some(10), 8, Some(14), NX, HORIZONTAL, Aim::Swing),
    upper_arm(j("r_shoulder", Some(17), 14, Some(15), NX, HORIZONTAL, Aim::Bend { far: 16, rest_bend: PZ, fold: false }), [-H, 0.0, H]),
    j("r_elbow", Some(18), 15, Some(16), NX, HORIZONTAL, Aim::Swing),
    j("r_wrist", Some(19), 16, None, NX, HORIZONTAL, Aim::Leaf { end: NX }),
];

/// Below the first bend angle (degrees) a knee or elbow plane does not
/// move the twist; from the second on it sets it.
pub const BEND_RAMP_DEG: (f64, f64) = (15.0, 45.0);

/// An End Site's length as a fraction of its leaf's bone.
pub const END_SITE_FRACTION: f64 = 0.25;

/// The rest direction of each Human3.6M bone (the direction of the joint
/// that aims it).
pub fn bone_rest_dirs() -> [Vec3; NUM_BONES] {
    let mut dirs = [[0.0; 3]; NUM_BONES];
    for r in RIG.iter() {
        if let Some(child) = r.aim {
            dirs[child - 1] = r.rest_dir;
        }
    }
    dirs
}

/// The 17 joints' positions in the rest pose (metres, Y-up frame).
pub fn rest_positions(lengths: &BoneLengths) -> [Vec3; NUM_JOINTS] {
    let dirs = bone_rest_dirs();
    let mut pos = [[0.0; 3]; NUM_JOINTS];
    for b in 0..NUM_BONES {
        pos[b + 1] = add(pos[bone_parent(b)], scale(dirs[b], lengths[b] as f64));
    }
    pos
}

/// Each rig joint's OFFSET (from its parent's position, rest pose).
pub fn offsets(lengths: &BoneLengths) -> [Vec3; 21] {
    let rest = rest_positions(lengths);
    std::array::from_fn(|r| match RIG[r].parent {
        None => [0.0; 3],
        Some(p) => crate::rot::sub(rest[RIG[r].at], rest[RIG[p].at]),
    })
}

/// A leaf's End Site offset.
pub fn end_site(r: usize, lengths: &BoneLengths) -> Option<Vec3> {
    match RIG[r].kind {
        Aim::Leaf { end } => Some(scale(
            end,
            END_SITE_FRACTION * lengths[RIG[r].at - 1] as f64,
        )),
        _ => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use blapose_core::skeleton::{JOINT_NAMES, PARENTS};

    #[test]
    fn every_joint_is_there_once_and_every_bone_is_aimed_once() {
        for (j, name) in JOINT_NAMES.iter().enumerate() {
            let found: Vec<_> = RIG.iter().filter(|r| r.name == *name).collect();
            assert_eq!(found.len(), 1, "{name}");
            assert_eq!(found[0].at, j);
        }
        for b in 0..NUM_BONES {
            assert_eq!(
                RIG.iter().filter(|r| r.aim == Some(b + 1)).count(),
                1,
                "bone {b}"
            );
        }
    }

    #[test]
    fn the_rig_follows_the_skeleton() {
        for (i, r) in RIG.iter().enumerate() {
            if let Some(p) = r.parent {
                assert!(p < i);
                // A joint sits at its parent's position (helper) or at the
                // child of the joint its parent aims.
                assert!(r.at == RIG[p].at || Some(r.at) == RIG[p].aim, "{}", r.name);
            }
            if let Some(c) = r.aim {
                assert_eq!(PARENTS[c], r.at, "{}", r.name);
            }
        }
    }

    #[test]
    fn rest_pose_has_the_lengths() {
        let lengths: BoneLengths = std::array::from_fn(|b| 0.1 + 0.01 * b as f32);
        let rest = rest_positions(&lengths);
        for b in 0..NUM_BONES {
            let d = crate::rot::norm(crate::rot::sub(rest[b + 1], rest[bone_parent(b)]));
            assert!((d - lengths[b] as f64).abs() < 1e-9);
        }
        // Left is +X, the legs hang down, the head is up.
        assert!(rest[4][0] > 0.0 && rest[1][0] < 0.0 && rest[3][1] < 0.0 && rest[10][1] > 0.0);
        assert_eq!(
            end_site(4, &lengths).unwrap(),
            [0.0, 0.0, 0.25 * lengths[2] as f64]
        );
    }
}

//! Bone decomposition and the BLAPose adjustment.
//!
//! A pose is a tree of 16 bones rooted at the pelvis (see
//! [`crate::skeleton`]). Decomposing it gives each bone's length and unit
//! direction; rebuilding walks the tree from the root, placing every child at
//! `parent + length * direction`. BLAPose's *adjustment* keeps a lifter's
//! directions and root position and swaps in predicted lengths.
//!
//! # Defined results for degenerate input
//!
//! - A coordinate that is NaN or infinite is rejected with
//!   [`BoneError::NonFiniteJoint`] naming the first such joint.
//! - A bone shorter than [`MIN_BONE_LENGTH`] (1 µm when poses are in metres)
//!   has no direction. The strict functions ([`decompose`], [`adjust_pose`],
//!   ...) reject it with [`BoneError::ZeroLengthBone`]. The lenient policy
//!   ([`ZeroBonePolicy::KeepInput`], used by [`adjust_pose_lenient`]) keeps
//!   that bone's input offset unchanged (the child stays on its parent) and
//!   still adjusts every other bone: training and evaluation code want a
//!   defined pose for every frame rather than an error for a rare collapsed
//!   joint, and keeping the input is the least surprising answer.
//! - Target lengths must be finite and `>= 0` ([`BoneError::InvalidLength`]);
//!   zero is allowed and collapses the child onto its parent.
//! - Results are checked: if huge inputs overflow `f32`, the functions return
//!   [`BoneError::Overflow`] instead of a non-finite pose. Nothing returned
//!   `Ok` ever contains NaN or infinity.
//!
//! Norms and divisions are computed in `f64` so that directions are unit
//! vectors to f32 precision even for extreme magnitudes.

use crate::pose::{BoneDirections, BoneLengths, Pose};
use crate::skeleton::{
    bone_child, bone_parent, BONE_NAMES, JOINT_NAMES, NUM_BONES, SYMMETRIC_BONE_PAIRS,
};

/// Bones shorter than this (in the pose's units; 1 µm for metres) count as
/// zero-length: their direction is undefined.
pub const MIN_BONE_LENGTH: f32 = 1e-6;

/// Why a pose could not be decomposed or adjusted.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum BoneError {
    /// A joint has a NaN or infinite coordinate.
    #[error("joint {joint} ({name}) has a non-finite coordinate")]
    NonFiniteJoint {
        /// Joint index (Human3.6M order).
        joint: usize,
        /// Joint name.
        name: &'static str,
    },
    /// A bone is shorter than [`MIN_BONE_LENGTH`], so it has no direction.
    #[error("bone {bone} ({name}) has zero length ({length:e} < {MIN_BONE_LENGTH:e}): its direction is undefined")]
    ZeroLengthBone {
        /// Bone index.
        bone: usize,
        /// Bone name.
        name: &'static str,
        /// The measured length.
        length: f32,
    },
    /// A requested bone length is negative, NaN or infinite.
    #[error("target length of bone {bone} ({name}) is invalid: {value} (must be finite and >= 0)")]
    InvalidLength {
        /// Bone index.
        bone: usize,
        /// Bone name.
        name: &'static str,
        /// The rejected value.
        value: f32,
    },
    /// The result does not fit in `f32` (inputs of astronomically large
    /// magnitude).
    #[error("result overflows f32 (inputs too large)")]
    Overflow,
    /// A sequence and its per-frame lengths differ in length.
    #[error("{poses} poses but {lengths} sets of bone lengths")]
    SequenceLengthMismatch {
        /// Number of poses.
        poses: usize,
        /// Number of length sets.
        lengths: usize,
    },
    /// An error in one frame of a sequence.
    #[error("frame {frame}: {source}")]
    InFrame {
        /// Frame index within the sequence.
        frame: usize,
        /// What went wrong in that frame.
        #[source]
        source: Box<BoneError>,
    },
}

/// What the adjustment does with a bone shorter than [`MIN_BONE_LENGTH`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum ZeroBonePolicy {
    /// Fail with [`BoneError::ZeroLengthBone`].
    #[default]
    Error,
    /// Keep the bone's input offset (child stays where it was relative to
    /// its parent); all other bones are adjusted.
    KeepInput,
}

fn check_finite(pose: &Pose) -> Result<(), BoneError> {
    match pose.iter().position(|p| !p.iter().all(|v| v.is_finite())) {
        Some(joint) => Err(BoneError::NonFiniteJoint {
            joint,
            name: JOINT_NAMES[joint],
        }),
        None => Ok(()),
    }
}

fn check_output(pose: Pose) -> Result<Pose, BoneError> {
    if pose.iter().flatten().all(|v| v.is_finite()) {
        Ok(pose)
    } else {
        Err(BoneError::Overflow)
    }
}

/// Check that every target length is finite and non-negative.
pub fn validate_lengths(lengths: &BoneLengths) -> Result<(), BoneError> {
    match lengths.iter().position(|l| !(l.is_finite() && *l >= 0.0)) {
        Some(bone) => Err(BoneError::InvalidLength {
            bone,
            name: BONE_NAMES[bone],
            value: lengths[bone],
        }),
        None => Ok(()),
    }
}

/// Bone vector (child minus parent) and its length, in f64.
#[inline]
fn bone_vector(pose: &Pose, bone: usize) -> ([f64; 3], f64) {
    let c = pose[bone_child(bone)];
    let p = pose[bone_parent(bone)];
    let v = [
        c[0] as f64 - p[0] as f64,
        c[1] as f64 - p[1] as f64,
        c[2] as f64 - p[2] as f64,
    ];
    let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    (v, n)
}

/// The 16 bone lengths of a pose (Euclidean norms, no checks: a non-finite
/// joint gives a non-finite length for the bones touching it).
pub fn bone_lengths(pose: &Pose) -> BoneLengths {
    std::array::from_fn(|b| bone_vector(pose, b).1 as f32)
}

/// Split a pose into 16 bone lengths and 16 unit directions.
///
/// Errors on a non-finite joint or a bone shorter than [`MIN_BONE_LENGTH`].
pub fn decompose(pose: &Pose) -> Result<(BoneLengths, BoneDirections), BoneError> {
    check_finite(pose)?;
    let mut lengths = [0.0; NUM_BONES];
    let mut dirs = [[0.0; 3]; NUM_BONES];
    for b in 0..NUM_BONES {
        let (v, n) = bone_vector(pose, b);
        let len = n as f32;
        if !len.is_finite() {
            return Err(BoneError::Overflow);
        }
        if len < MIN_BONE_LENGTH {
            return Err(BoneError::ZeroLengthBone {
                bone: b,
                name: BONE_NAMES[b],
                length: len,
            });
        }
        lengths[b] = len;
        dirs[b] = [(v[0] / n) as f32, (v[1] / n) as f32, (v[2] / n) as f32];
    }
    Ok((lengths, dirs))
}

/// Build a pose from a root position, bone directions and lengths, walking
/// the tree from the root: `joint[child] = joint[parent] + length * dir`.
///
/// Directions are used as given (not re-normalized). Finite inputs give a
/// finite pose unless the magnitudes overflow `f32`.
pub fn rebuild(root: [f32; 3], dirs: &BoneDirections, lengths: &BoneLengths) -> Pose {
    let mut pose = [[0.0f32; 3]; crate::skeleton::NUM_JOINTS];
    pose[crate::skeleton::ROOT] = root;
    for b in 0..NUM_BONES {
        let p = pose[bone_parent(b)];
        let d = dirs[b];
        let l = lengths[b];
        pose[bone_child(b)] = [p[0] + l * d[0], p[1] + l * d[1], p[2] + l * d[2]];
    }
    pose
}

/// The BLAPose adjustment with an explicit [`ZeroBonePolicy`]: keep the
/// pose's root position and bone directions, replace its bone lengths.
pub fn adjust_pose_with(
    pose: &Pose,
    lengths: &BoneLengths,
    policy: ZeroBonePolicy,
) -> Result<Pose, BoneError> {
    check_finite(pose)?;
    validate_lengths(lengths)?;
    let mut out = [[0.0f64; 3]; crate::skeleton::NUM_JOINTS];
    let r = pose[crate::skeleton::ROOT];
    out[crate::skeleton::ROOT] = [r[0] as f64, r[1] as f64, r[2] as f64];
    for b in 0..NUM_BONES {
        let (v, n) = bone_vector(pose, b);
        let p = out[bone_parent(b)];
        let offset = if (n as f32) < MIN_BONE_LENGTH {
            match policy {
                ZeroBonePolicy::Error => {
                    return Err(BoneError::ZeroLengthBone {
                        bone: b,
                        name: BONE_NAMES[b],
                        length: n as f32,
                    })
                }
                ZeroBonePolicy::KeepInput => v,
            }
        } else {
            let s = lengths[b] as f64 / n;
            [v[0] * s, v[1] * s, v[2] * s]
        };
        out[bone_child(b)] = [p[0] + offset[0], p[1] + offset[1], p[2] + offset[2]];
    }
    check_output(out.map(|p| p.map(|v| v as f32)))
}

/// The BLAPose adjustment: keep the pose's root position and bone
/// directions, replace its bone lengths. Strict: a zero-length bone is an
/// error (see the module docs).
pub fn adjust_pose(pose: &Pose, lengths: &BoneLengths) -> Result<Pose, BoneError> {
    adjust_pose_with(pose, lengths, ZeroBonePolicy::Error)
}

/// [`adjust_pose`], except that a zero-length bone keeps its input offset
/// instead of failing ([`ZeroBonePolicy::KeepInput`]). Non-finite poses and
/// invalid lengths are still errors.
pub fn adjust_pose_lenient(pose: &Pose, lengths: &BoneLengths) -> Result<Pose, BoneError> {
    adjust_pose_with(pose, lengths, ZeroBonePolicy::KeepInput)
}

fn in_frame(frame: usize) -> impl FnOnce(BoneError) -> BoneError {
    move |e| BoneError::InFrame {
        frame,
        source: Box::new(e),
    }
}

/// Adjust every frame of a sequence to the same lengths (one person).
/// Errors name the first failing frame ([`BoneError::InFrame`]).
pub fn adjust_sequence(poses: &[Pose], lengths: &BoneLengths) -> Result<Vec<Pose>, BoneError> {
    adjust_sequence_with(poses, lengths, ZeroBonePolicy::Error)
}

/// [`adjust_sequence`] with an explicit [`ZeroBonePolicy`].
pub fn adjust_sequence_with(
    poses: &[Pose],
    lengths: &BoneLengths,
    policy: ZeroBonePolicy,
) -> Result<Vec<Pose>, BoneError> {
    validate_lengths(lengths)?;
    poses
        .iter()
        .enumerate()
        .map(|(t, p)| adjust_pose_with(p, lengths, policy).map_err(in_frame(t)))
        .collect()
}

/// Adjust frame `t` to `lengths[t]` (e.g. the online model's running
/// prediction). The two slices must have the same length.
pub fn adjust_sequence_per_frame(
    poses: &[Pose],
    lengths: &[BoneLengths],
    policy: ZeroBonePolicy,
) -> Result<Vec<Pose>, BoneError> {
    if poses.len() != lengths.len() {
        return Err(BoneError::SequenceLengthMismatch {
            poses: poses.len(),
            lengths: lengths.len(),
        });
    }
    poses
        .iter()
        .zip(lengths)
        .enumerate()
        .map(|(t, (p, l))| adjust_pose_with(p, l, policy).map_err(in_frame(t)))
        .collect()
}

/// Replace each symmetric pair (hip, thigh, calf, shoulder, upper arm,
/// forearm) by the mean of its left and right lengths, as BLAPose does with
/// its predictions.
pub fn average_symmetric_pairs(lengths: &mut BoneLengths) {
    for &(r, l) in &SYMMETRIC_BONE_PAIRS {
        let m = 0.5 * (lengths[r] + lengths[l]);
        lengths[r] = m;
        lengths[l] = m;
    }
}

/// The summed length of the 16 bones, metres: a body's overall size
/// (what the benchmarks' size slope and the matched stature read).
pub fn summed_length(lengths: &BoneLengths) -> f64 {
    lengths.iter().map(|&v| f64::from(v)).sum()
}

/// Mean of each bone's length over a sequence (frames whose lengths are not
/// all finite are skipped); `None` when no frame is usable.
pub fn mean_bone_lengths(poses: &[Pose]) -> Option<BoneLengths> {
    let mut sum = [0.0f64; NUM_BONES];
    let mut n = 0usize;
    for p in poses {
        let l = bone_lengths(p);
        if l.iter().all(|v| v.is_finite()) {
            for (s, v) in sum.iter_mut().zip(l) {
                *s += v as f64;
            }
            n += 1;
        }
    }
    (n > 0).then(|| sum.map(|s| (s / n as f64) as f32))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::skeleton::NUM_JOINTS;

    /// A plausible standing pose (metres), Human3.6M order.
    pub(crate) fn t_pose() -> Pose {
        [
            [0.0, 0.0, 1.0],
            [-0.13, 0.0, 1.0],
            [-0.13, 0.0, 0.55],
            [-0.13, 0.0, 0.1],
            [0.13, 0.0, 1.0],
            [0.13, 0.0, 0.55],
            [0.13, 0.0, 0.1],
            [0.0, 0.0, 1.23],
            [0.0, 0.0, 1.48],
            [0.0, 0.05, 1.6],
            [0.0, 0.0, 1.7],
            [0.15, 0.0, 1.45],
            [0.42, 0.0, 1.45],
            [0.67, 0.0, 1.45],
            [-0.15, 0.0, 1.45],
            [-0.42, 0.0, 1.45],
            [-0.67, 0.0, 1.45],
        ]
    }

    #[test]
    fn decompose_known_pose() {
        let (l, d) = decompose(&t_pose()).unwrap();
        assert!((l[1] - 0.45).abs() < 1e-6, "r_thigh {}", l[1]);
        assert_eq!(d[1], [0.0, 0.0, -1.0]);
        assert!((l[12] - 0.25).abs() < 1e-6);
        assert_eq!(d[12], [1.0, 0.0, 0.0]);
    }

    #[test]
    fn adjustment_sets_lengths_and_keeps_root() {
        let mut target = bone_lengths(&t_pose());
        target[12] = 0.3;
        target[1] = 0.5;
        let adj = adjust_pose(&t_pose(), &target).unwrap();
        assert_eq!(adj[0], t_pose()[0]);
        let got = bone_lengths(&adj);
        for b in 0..NUM_BONES {
            assert!((got[b] - target[b]).abs() < 1e-6, "bone {b}");
        }
        // the wrist moved out by 5 cm along +x, knee and ankle down by 5 cm
        assert!((adj[13][0] - 0.72).abs() < 1e-6);
        assert!((adj[3][2] - 0.05).abs() < 1e-6);
    }

    #[test]
    fn zero_length_bone_policies() {
        let mut pose = t_pose();
        pose[13] = pose[12]; // l_forearm collapsed
        let target = bone_lengths(&t_pose());
        let err = adjust_pose(&pose, &target).unwrap_err();
        assert!(
            matches!(
                err,
                BoneError::ZeroLengthBone {
                    bone: 12,
                    name: "l_forearm",
                    ..
                }
            ),
            "{err}"
        );
        assert!(err.to_string().contains("l_forearm"));
        assert!(matches!(
            decompose(&pose),
            Err(BoneError::ZeroLengthBone { bone: 12, .. })
        ));
        let lenient = adjust_pose_lenient(&pose, &target).unwrap();
        assert_eq!(
            lenient[13], lenient[12],
            "collapsed bone keeps its zero offset"
        );
        assert!(lenient.iter().flatten().all(|v| v.is_finite()));
        // a bone below the threshold but non-zero counts as zero too
        pose[13][0] += 0.5e-6;
        assert!(adjust_pose(&pose, &target).is_err());
    }

    #[test]
    fn non_finite_inputs_are_named() {
        for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
            let mut pose = t_pose();
            pose[15][1] = bad;
            let e = adjust_pose(&pose, &bone_lengths(&t_pose())).unwrap_err();
            assert_eq!(
                e,
                BoneError::NonFiniteJoint {
                    joint: 15,
                    name: "r_elbow"
                }
            );
            assert!(decompose(&pose).is_err());
            assert!(adjust_pose_lenient(&pose, &bone_lengths(&t_pose())).is_err());
            let mut l = bone_lengths(&t_pose());
            l[4] = bad;
            let e = adjust_pose(&t_pose(), &l).unwrap_err();
            assert!(
                matches!(
                    e,
                    BoneError::InvalidLength {
                        bone: 4,
                        name: "l_thigh",
                        ..
                    }
                ),
                "{e}"
            );
        }
        let mut l = bone_lengths(&t_pose());
        l[0] = -0.1;
        assert!(matches!(
            adjust_pose(&t_pose(), &l),
            Err(BoneError::InvalidLength { bone: 0, .. })
        ));
        l[0] = 0.0;
        let z = adjust_pose(&t_pose(), &l).unwrap();
        assert_eq!(
            z[1], z[0],
            "zero target length collapses the child onto its parent"
        );
    }

    #[test]
    fn overflow_is_an_error_not_infinity() {
        let mut pose = [[0.0f32; 3]; NUM_JOINTS];
        for (j, p) in pose.iter_mut().enumerate() {
            *p = [j as f32 * 1e37, 0.0, 0.0];
        }
        let l = [f32::MAX; NUM_BONES];
        assert_eq!(adjust_pose(&pose, &l), Err(BoneError::Overflow));
    }

    #[test]
    fn sequence_errors_name_the_frame() {
        let mut seq = vec![t_pose(); 5];
        seq[3][7][2] = f32::NAN;
        let e = adjust_sequence(&seq, &bone_lengths(&t_pose())).unwrap_err();
        assert!(
            matches!(&e, BoneError::InFrame { frame: 3, source } if matches!(**source, BoneError::NonFiniteJoint { joint: 7, .. }))
        );
        assert!(e.to_string().starts_with("frame 3: joint 7 (spine)"), "{e}");
        let per = vec![bone_lengths(&t_pose()); 4];
        assert!(matches!(
            adjust_sequence_per_frame(&seq, &per, ZeroBonePolicy::Error),
            Err(BoneError::SequenceLengthMismatch {
                poses: 5,
                lengths: 4
            })
        ));
        seq[3] = t_pose();
        let per: Vec<BoneLengths> = (0..5).map(|t| [0.1 + 0.01 * t as f32; NUM_BONES]).collect();
        let out = adjust_sequence_per_frame(&seq, &per, ZeroBonePolicy::Error).unwrap();
        assert!((bone_lengths(&out[4])[9] - 0.14).abs() < 1e-6);
    }

    #[test]
    fn symmetric_average() {
        let mut l: BoneLengths = std::array::from_fn(|b| b as f32);
        average_symmetric_pairs(&mut l);
        assert_eq!(l[0], 1.5);
        assert_eq!(l[3], 1.5);
        assert_eq!(l[13], 11.5);
        assert_eq!(l[10], 11.5);
        assert_eq!(l[6], 6.0);
        assert_eq!(mean_bone_lengths(&[]), None);
    }
}

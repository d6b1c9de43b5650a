//! What the server answers for one frame.
//!
//! An answer carries the adjusted pose, the session's current lengths and,
//! when the server lifted the pose itself, the lifter's pose; its arrays
//! are checked here, so a misshaped answer is a protocol error.

use blapose_core::{BoneLengths, Pose};
use blapose_proto::v1 as pb;

use super::wire::{lengths_from_flat, pose_from_flat};
use crate::error::ClientError;

/// A frame the server adjusted.
#[derive(Debug, Clone, PartialEq)]
pub struct AdjustedFrame {
    /// The request's frame index.
    pub frame_index: u64,
    /// Input bone directions and root, the session's current lengths.
    pub pose: Pose,
    /// The session's current bone-length estimate (metres).
    pub bone_lengths: BoneLengths,
    /// Frames processed in the session, this one included.
    pub frames_seen: u64,
    /// The server lifter's pose for this frame and the lifter's name;
    /// `None` when the client sent the pose. (Boxed: most sessions send
    /// their poses, and their answers stay small.)
    pub lifted: Option<Box<LiftedPose>>,
    /// With the motion stage: where it placed the pelvis. (Boxed, like
    /// `lifted`, to keep plain answers small.)
    pub root: Option<Box<PlacedRoot>>,
}

/// Where the motion stage placed a frame's pelvis.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PlacedRoot {
    /// Camera space, metres (x right, y down, z forward).
    pub position: [f32; 3],
    /// Placed through an assumed focal length (no calibration sent).
    pub focal_assumed: bool,
    /// The placed pose in world coordinates (z up, the floor at 0), when
    /// the session's calibration has a camera height.
    pub world: Option<Pose>,
}

/// The pose a server lifter produced for a frame, before adjustment.
#[derive(Debug, Clone, PartialEq)]
pub struct LiftedPose {
    /// The lifter's name, e.g. `videopose27-causal`.
    pub lifter: String,
    /// Root-relative camera space, metres, pelvis at 0.
    pub pose: Pose,
}

impl AdjustedFrame {
    pub(crate) fn from_proto(msg: pb::AdjustedFrame) -> Result<Self, ClientError> {
        let lifted = match (msg.lifter.is_empty(), msg.lifted_pose_3d.is_empty()) {
            (true, true) => None,
            (false, false) => Some(Box::new(LiftedPose {
                pose: pose_from_flat(&msg.lifted_pose_3d, "lifted_pose_3d")?,
                lifter: msg.lifter,
            })),
            _ => {
                return Err(ClientError::Protocol(format!(
                    "frame {}: a lifter name ({:?}) must come with the lifted pose ({} values) and vice versa",
                    msg.frame_index,
                    msg.lifter,
                    msg.lifted_pose_3d.len()
                )))
            }
        };
        let root = match msg.root_position.as_slice() {
            [] => None,
            [x, y, z] => Some(Box::new(PlacedRoot {
                position: [*x, *y, *z],
                focal_assumed: msg.focal_assumed,
                world: if msg.world_pose_3d.is_empty() {
                    None
                } else {
                    Some(pose_from_flat(&msg.world_pose_3d, "world_pose_3d")?)
                },
            })),
            other => {
                return Err(ClientError::Protocol(format!(
                    "frame {}: root_position has {} values, expected 3",
                    msg.frame_index,
                    other.len()
                )))
            }
        };
        Ok(AdjustedFrame {
            root,
            frame_index: msg.frame_index,
            pose: pose_from_flat(&msg.adjusted_pose_3d, "adjusted_pose_3d")?,
            bone_lengths: lengths_from_flat(&msg.bone_lengths, "bone_lengths")?,
            frames_seen: msg.frames_seen,
            lifted,
        })
    }

    /// The server lifter that produced the input pose; `None` when the
    /// client sent it.
    pub fn lifter(&self) -> Option<&str> {
        self.lifted.as_ref().map(|l| l.lifter.as_str())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use blapose_core::NUM_JOINTS;

    #[test]
    fn short_arrays_from_the_server_are_protocol_errors() {
        let msg = pb::AdjustedFrame {
            frame_index: 3,
            adjusted_pose_3d: vec![0.0; 50],
            bone_lengths: vec![0.1; 16],
            frames_seen: 1,
            ..Default::default()
        };
        let err = AdjustedFrame::from_proto(msg).unwrap_err();
        assert!(err.to_string().contains("50 values"), "{err}");
        let msg = pb::AdjustedFrame {
            frame_index: 3,
            adjusted_pose_3d: (0..51).map(|v| v as f32).collect(),
            bone_lengths: vec![0.1; 16],
            frames_seen: 1,
            ..Default::default()
        };
        let f = AdjustedFrame::from_proto(msg.clone()).unwrap();
        assert_eq!(f.pose[16], [48.0, 49.0, 50.0]);
        assert_eq!((f.lifter(), &f.lifted), (None, &None), "a client pose");
        // A lifted frame names its lifter and carries the lifted pose.
        let lifted = pb::AdjustedFrame {
            lifter: "videopose27-causal".into(),
            lifted_pose_3d: vec![0.5; 51],
            ..msg.clone()
        };
        let f = AdjustedFrame::from_proto(lifted.clone()).unwrap();
        assert_eq!(f.lifter(), Some("videopose27-causal"));
        assert_eq!(f.lifted.map(|l| l.pose), Some([[0.5; 3]; NUM_JOINTS]));
        for broken in [
            pb::AdjustedFrame {
                lifted_pose_3d: vec![0.5; 50],
                ..lifted.clone()
            },
            pb::AdjustedFrame {
                lifted_pose_3d: vec![],
                ..lifted.clone()
            },
            pb::AdjustedFrame {
                lifter: String::new(),
                ..lifted
            },
        ] {
            assert!(matches!(
                AdjustedFrame::from_proto(broken),
                Err(ClientError::Protocol(_))
            ));
        }
    }
}

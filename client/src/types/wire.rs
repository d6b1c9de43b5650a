//! The wire form of the types the client shares with the replay format.
//!
//! [`CameraCalibration`], [`Subject`] and [`FrameInput`] are defined below
//! the client (`blapose_data::replay`), where the replay files need them
//! too; their protobuf form is the client's business, so it is written
//! here, once: [`ToProto`] builds the messages the client sends, and the
//! `*_from_proto` functions read what the server echoes. The helpers for
//! flat pose and length arrays make a misshaped answer a protocol error
//! instead of a panic.

use blapose_core::layouts::{Coordinates, InputFormat};
use blapose_core::skeleton::NUM_BONES;
use blapose_core::{BoneLengths, ModelKind, Pose};
use blapose_data::replay::{CameraCalibration, FrameInput, Subject};
use blapose_proto::convert::{layout_from_proto, model_from_proto, sex_from_proto};
use blapose_proto::v1 as pb;

use crate::error::ClientError;

/// A client type's protobuf message.
pub trait ToProto {
    /// The generated message type.
    type Message;

    /// The wire message.
    fn to_proto(&self) -> Self::Message;
}

impl ToProto for FrameInput {
    type Message = pb::Frame;

    fn to_proto(&self) -> pb::Frame {
        pb::Frame {
            frame_index: self.frame_index,
            keypoints_2d: self.keypoints_2d.as_flattened().to_vec(),
            confidence: self.confidence.clone(),
            pose_3d: self
                .pose_3d
                .map(|p| p.as_flattened().to_vec())
                .unwrap_or_default(),
        }
    }
}

impl ToProto for CameraCalibration {
    type Message = pb::CameraCalibration;

    /// The calibration as sent; a height not given is 0 on the wire.
    fn to_proto(&self) -> pb::CameraCalibration {
        pb::CameraCalibration {
            up: self.up.to_vec(),
            focal_x: self.focal[0],
            focal_y: self.focal[1],
            principal_x: self.principal[0],
            principal_y: self.principal[1],
            image_size: self
                .image_size
                .map(|(width, height)| pb::ImageSize { width, height }),
            height: self.height.unwrap_or(0.0),
            distortion: self.distortion.map_or_else(Vec::new, |d| d.to_vec()),
        }
    }
}

impl ToProto for Subject {
    type Message = pb::Subject;

    fn to_proto(&self) -> pb::Subject {
        pb::Subject {
            height_m: self.height_m,
            sex: self.sex.map_or(pb::Sex::Unspecified, pb::Sex::from) as i32,
        }
    }
}

/// Parse a calibration message (as echoed by the server). Only the shape
/// is checked (`up` must have 3 values); see
/// [`CameraCalibration::validate`]. A height of 0 is "not given" (`None`).
pub fn camera_from_proto(msg: &pb::CameraCalibration) -> Result<CameraCalibration, ClientError> {
    let up: [f32; 3] = msg.up.as_slice().try_into().map_err(|_| {
        ClientError::Protocol(format!("camera.up has {} values, expected 3", msg.up.len()))
    })?;
    Ok(CameraCalibration {
        up,
        focal: [msg.focal_x, msg.focal_y],
        principal: [msg.principal_x, msg.principal_y],
        image_size: msg.image_size.map(|s| (s.width, s.height)),
        height: (msg.height != 0.0).then_some(msg.height),
        distortion: match *msg.distortion.as_slice() {
            [] => None,
            [k1, k2, p1, p2] => Some([k1, k2, p1, p2, 0.0]),
            [k1, k2, p1, p2, k3] => Some([k1, k2, p1, p2, k3]),
            ref other => {
                return Err(ClientError::Protocol(format!(
                    "camera.distortion has {} values, expected 0, 4 or 5",
                    other.len()
                )))
            }
        },
    })
}

/// Parse a subject message (an unknown sex reads as unknown).
pub fn subject_from_proto(msg: &pb::Subject) -> Subject {
    Subject {
        height_m: msg.height_m,
        sex: sex_from_proto(msg.sex),
    }
}

/// The model a server answer names; a protocol error for UNSPECIFIED or a
/// number this client does not know.
pub(crate) fn model_from_answer(value: i32) -> Result<ModelKind, ClientError> {
    model_from_proto(value).ok_or_else(|| ClientError::Protocol(format!("unknown model {value}")))
}

/// Parse the wire message (as echoed by the server).
pub(crate) fn input_format_from_proto(msg: &pb::InputFormat) -> Result<InputFormat, ClientError> {
    let layout = layout_from_proto(msg.layout)
        .ok_or_else(|| ClientError::Protocol(format!("unknown keypoint layout {}", msg.layout)))?;
    let coordinates = msg
        .coordinates
        .map(Coordinates::from)
        .ok_or_else(|| ClientError::Protocol("input format without coordinates".into()))?;
    Ok(InputFormat {
        layout,
        coordinates,
    })
}

/// A flat 51-value pose from the wire.
pub(crate) fn pose_from_flat(values: &[f32], what: &str) -> Result<Pose, ClientError> {
    blapose_core::pose::pose_from_flat(values).ok_or_else(|| {
        ClientError::Protocol(format!(
            "{what} has {} values, expected {}",
            values.len(),
            blapose_core::pose::POSE_VALUES
        ))
    })
}

/// A flat 16-value length vector from the wire.
pub(crate) fn lengths_from_flat(values: &[f32], what: &str) -> Result<BoneLengths, ClientError> {
    values.try_into().map_err(|_| {
        ClientError::Protocol(format!(
            "{what} has {} values, expected {NUM_BONES}",
            values.len()
        ))
    })
}

/// An optional 16-value length vector from the wire (empty: `None`).
pub(crate) fn optional_lengths(values: &[f32]) -> Result<Option<BoneLengths>, ClientError> {
    if values.is_empty() {
        Ok(None)
    } else {
        lengths_from_flat(values, "bone_lengths").map(Some)
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use blapose_core::layouts::KeypointLayout;
    use blapose_core::{Sex, NUM_JOINTS};
    use blapose_data::replay::{layout_code, layout_from_code};
    use blapose_proto::convert::layout_to_proto;

    #[test]
    fn layout_codes_are_the_wire_numbers() {
        for l in KeypointLayout::ALL {
            assert_eq!(layout_code(l), layout_to_proto(l) as u32);
            assert_eq!(layout_from_code(layout_code(l)), Some(l));
        }
        assert_eq!(layout_from_code(0), None);
        assert_eq!(layout_from_code(9), None);
    }

    #[test]
    fn input_format_round_trips() {
        for f in [
            InputFormat::pixels(KeypointLayout::Sh16, 1000, 1002),
            InputFormat {
                layout: KeypointLayout::Coco17,
                coordinates: Coordinates::Normalized,
            },
        ] {
            assert_eq!(input_format_from_proto(&f.into()).unwrap(), f);
        }
        let bad = pb::InputFormat {
            layout: 0,
            coordinates: None,
        };
        assert!(matches!(
            input_format_from_proto(&bad),
            Err(ClientError::Protocol(_))
        ));
    }

    #[test]
    fn frame_input_flattens_joint_major() {
        let mut pose = [[0.0f32; 3]; NUM_JOINTS];
        pose[1] = [1.0, 2.0, 3.0];
        let f = FrameInput {
            frame_index: 9,
            keypoints_2d: vec![[1.0, 2.0], [3.0, 4.0]],
            confidence: vec![],
            pose_3d: Some(pose),
        };
        let p = f.to_proto();
        assert_eq!(p.keypoints_2d, vec![1.0, 2.0, 3.0, 4.0]);
        assert_eq!(&p.pose_3d[3..6], &[1.0, 2.0, 3.0]);
        assert_eq!(p.frame_index, 9);
        let keypoints_only = FrameInput { pose_3d: None, ..f };
        assert!(keypoints_only.to_proto().pose_3d.is_empty());
    }

    /// A calibration every test of the client's types shares.
    pub(crate) fn calibration() -> CameraCalibration {
        CameraCalibration {
            up: [0.01, -0.98, 0.2],
            focal: [1145.5, 1146.25],
            principal: [512.5, 515.0],
            image_size: Some((1000, 1002)),
            height: Some(1.75),
            distortion: None,
        }
    }

    #[test]
    fn camera_calibration_round_trips_through_the_wire_message() {
        let c = calibration();
        let msg = c.to_proto();
        assert_eq!(msg.up, vec![0.01, -0.98, 0.2]);
        assert_eq!((msg.focal_x, msg.focal_y), (1145.5, 1146.25));
        assert_eq!((msg.principal_x, msg.principal_y), (512.5, 515.0));
        assert_eq!(
            msg.image_size,
            Some(pb::ImageSize {
                width: 1000,
                height: 1002
            })
        );
        assert_eq!(msg.height, 1.75);
        assert_eq!(camera_from_proto(&msg).unwrap(), c);
        let no_size = CameraCalibration {
            image_size: None,
            ..c
        };
        assert_eq!(no_size.to_proto().image_size, None);
        assert_eq!(camera_from_proto(&no_size.to_proto()).unwrap(), no_size);
        for up in [vec![], vec![0.0, -1.0], vec![0.0, -1.0, 0.0, 1.0]] {
            let msg = pb::CameraCalibration { up, ..msg.clone() };
            let err = camera_from_proto(&msg).unwrap_err();
            assert!(
                matches!(&err, ClientError::Protocol(m) if m.contains("camera.up")),
                "{err}"
            );
        }
    }

    #[test]
    fn camera_height_is_sent_as_zero_when_not_given() {
        let c = calibration();
        // Given: sent as is, read back as Some.
        let msg = c.to_proto();
        assert_eq!(msg.height, 1.75);
        let back = camera_from_proto(&msg).unwrap();
        assert_eq!(back.height, Some(1.75));
        // Not given: 0 on the wire, None again when read back.
        let unknown = CameraCalibration { height: None, ..c };
        let msg = unknown.to_proto();
        assert_eq!(msg.height, 0.0);
        assert_eq!(
            camera_from_proto(&msg).unwrap(),
            unknown,
            "0 is read as not given"
        );
        // A message that leaves the field out (older senders) has no height.
        let old = pb::CameraCalibration {
            up: vec![0.0, -1.0, 0.0],
            focal_x: 1000.0,
            focal_y: 1000.0,
            ..Default::default()
        };
        assert_eq!(camera_from_proto(&old).unwrap().height, None);
        // Any other value is kept for validate to judge.
        let odd = pb::CameraCalibration {
            height: 50.0,
            ..c.to_proto()
        };
        assert_eq!(camera_from_proto(&odd).unwrap().height, Some(50.0));
    }

    #[test]
    fn subjects_round_trip_through_the_wire_message() {
        for sex in [None, Some(Sex::Female), Some(Sex::Male)] {
            let subject = Subject {
                height_m: 1.68,
                sex,
            };
            let msg = subject.to_proto();
            assert_eq!(msg.height_m, 1.68);
            assert_eq!(subject_from_proto(&msg), subject);
        }
        let unknown = pb::Subject {
            height_m: 1.7,
            sex: 9,
        };
        assert_eq!(subject_from_proto(&unknown).sex, None);
    }
}

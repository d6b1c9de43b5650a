//! The validate stage: every check of client input, and its typed errors,
//! before anything touches a session, the queue or a model.
//!
//! Everything a client sends is checked here, as text-embeddings-inference
//! validates and tokenises a request before its queue: keypoints are read
//! into Human3.6M-17 order and normalized screen coordinates (blapose-core's
//! layouts and camera modules, the models' common input), a 3D pose is one
//! the adjustment is guaranteed to accept, and a camera calibration is one
//! the camera-aware models' input contract can read ([`camera`]). Because
//! the later stages only ever see validated input, a bad frame is refused
//! without the session's state moving. Nothing here builds a camera, fills
//! a joint or runs a model ([`crate::prepare`] and [`crate::answer`] do).
//! Every error says which value is wrong and what was expected; all of them
//! map to INVALID_ARGUMENT.

use blapose_core::bones::{self, BoneError};
use blapose_core::layouts::{Coordinates, KeypointLayout};
use blapose_core::lens::LensDistortion;
use blapose_core::level::{self, CalibrationError};
pub use blapose_core::pose::POSE_VALUES;
use blapose_core::skeleton::JOINT_NAMES;
use blapose_core::{ModelKind, Pose, Sex, NUM_JOINTS};
use blapose_model::input::{ModelInput, ViewCalibration};
use blapose_model::stature::{MAX_STATURE_M, MIN_STATURE_M};
pub use blapose_proto::convert::layout_to_proto;
use blapose_proto::convert::{model_from_proto, sex_from_proto};
use blapose_proto::v1 as pb;

use crate::backend::INPUT_DIM;
use crate::session::{InputFormat, SessionCamera};

mod invalid;

pub use invalid::{InvalidInput, MAX_KEYPOINT_ABS, MAX_POSE_ABS};

fn layout_from_proto(value: i32) -> Result<KeypointLayout, InvalidInput> {
    blapose_proto::convert::layout_from_proto(value).ok_or(
        if value == pb::KeypointLayout::Unspecified as i32 {
            InvalidInput::UnspecifiedLayout
        } else {
            InvalidInput::UnknownLayout(value)
        },
    )
}

/// Validate an `InputFormat`.
pub fn input_format(format: Option<&pb::InputFormat>) -> Result<InputFormat, InvalidInput> {
    let format = format.ok_or(InvalidInput::MissingInputFormat)?;
    let layout = layout_from_proto(format.layout)?;
    let coordinates = match format.coordinates {
        None => return Err(InvalidInput::MissingCoordinates),
        Some(pb::input_format::Coordinates::Normalized(false)) => {
            return Err(InvalidInput::NormalizedFalse)
        }
        Some(pb::input_format::Coordinates::ImageSize(size))
            if size.width == 0 || size.height == 0 =>
        {
            return Err(InvalidInput::BadImageSize {
                width: size.width,
                height: size.height,
            })
        }
        Some(given) => Coordinates::from(given),
    };
    Ok(InputFormat {
        layout,
        coordinates,
    })
}

/// The `InputFormat` a spec was built from (echoed on open/resume).
pub fn input_format_to_proto(spec: &InputFormat) -> pb::InputFormat {
    (*spec).into()
}

/// Validate an optional `CameraCalibration` against the input format and
/// `served`, the camera-aware models' input contract (`None` when the
/// server has no camera-aware models: a calibration is then refused): a
/// plausible camera height, and one when the contract scales to the floor;
/// three values of up; the image the pixels refer to; a calibration that
/// rectifies; a lens model that inverts over the image; a camera inside the
/// ones the models were trained through. The camera the contract reads the
/// keypoints through is built here, once: a session keeps it for its life
/// ([`SessionCamera::input`]), a sequence request for its frames.
pub fn camera(
    calibration: Option<&pb::CameraCalibration>,
    spec: &InputFormat,
    served: Option<&ModelInput>,
) -> Result<Option<SessionCamera>, InvalidInput> {
    let Some(c) = calibration else {
        return Ok(None);
    };
    let Some(served) = served else {
        return Err(InvalidInput::NoCameraAwareModel);
    };
    let height = c.height;
    if height != 0.0 && !level::is_camera_height(height) {
        return Err(InvalidInput::CameraHeight(height));
    }
    if served.framing.needs_camera_height() && height == 0.0 {
        return Err(InvalidInput::CameraHeightRequired);
    }
    let up: [f32; 3] =
        c.up.as_slice()
            .try_into()
            .map_err(|_| InvalidInput::CameraUpCount { got: c.up.len() })?;
    let image_size =
        level::calibration_image_size(spec.coordinates, c.image_size.map(|s| (s.width, s.height)))
            .map_err(|e| match e {
                CalibrationError::ImageSizeMismatch {
                    camera_width,
                    camera_height,
                    width,
                    height,
                } => InvalidInput::CameraImageSizeMismatch {
                    camera_width,
                    camera_height,
                    width,
                    height,
                },
                CalibrationError::ImageSizeMissing => InvalidInput::CameraImageSizeMissing,
                other => InvalidInput::Camera(other.into()),
            })?;
    let mut view = ViewCalibration {
        up: up.map(f64::from),
        focal: [c.focal_x, c.focal_y].map(f64::from),
        principal: [c.principal_x, c.principal_y].map(f64::from),
        image_size,
        camera_height: (height != 0.0).then_some(height),
        lens: None,
    };
    // The calibration must rectify; checked before the lens, which the
    // contract's camera then undoes on top of the level one.
    let input = served.camera(&view)?;
    view.lens =
        LensDistortion::checked(&c.distortion, view.focal, view.principal, Some(image_size))
            .map_err(InvalidInput::CameraDistortion)?;
    served
        .admits(&view)
        .map_err(InvalidInput::OutsideTrainedCameras)?;
    let input = match (input, view.lens) {
        (Some(input), Some(lens)) => Some(input.with_lens(lens)),
        (input, _) => input,
    };
    Ok(Some(SessionCamera {
        calibration: c.clone(),
        input,
        view,
    }))
}

/// A model number of a request: `None` for UNSPECIFIED (the RPC's
/// default), else the model, or [`InvalidInput::UnknownModel`].
fn model(value: i32) -> Result<Option<ModelKind>, InvalidInput> {
    if value == pb::Model::Unspecified as i32 {
        return Ok(None);
    }
    model_from_proto(value)
        .map(Some)
        .ok_or(InvalidInput::UnknownModel(value))
}

/// Check the model of an `OpenSession` (only the online GRU streams).
pub fn stream_model(value: i32) -> Result<ModelKind, InvalidInput> {
    match model(value)?.unwrap_or(ModelKind::Gru) {
        ModelKind::Gru => Ok(ModelKind::Gru),
        ModelKind::BiGru => Err(InvalidInput::OfflineModelOnStream),
    }
}

/// The model of an `AdjustSequenceRequest` (Bi-GRU by default).
pub fn offline_model(value: i32) -> Result<ModelKind, InvalidInput> {
    Ok(model(value)?.unwrap_or(ModelKind::BiGru))
}

/// A checked subject: as sent (echoed on open, carried by tokens), with
/// its sex read.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ValidSubject {
    /// As sent in `OpenSession.subject` / `AdjustSequenceRequest.subject`.
    pub subject: pb::Subject,
    /// Its sex, when given.
    pub sex: Option<Sex>,
}

/// Validate an optional subject: a stature the stature model covers, and
/// a known sex.
pub fn subject(subject: Option<&pb::Subject>) -> Result<Option<ValidSubject>, InvalidInput> {
    let Some(s) = subject else {
        return Ok(None);
    };
    if !(s.height_m.is_finite() && (MIN_STATURE_M..=MAX_STATURE_M).contains(&s.height_m)) {
        return Err(InvalidInput::SubjectHeight(s.height_m));
    }
    let sex = sex_from_proto(s.sex);
    if sex.is_none() && s.sex != pb::Sex::Unspecified as i32 {
        return Err(InvalidInput::SubjectSex(s.sex));
    }
    Ok(Some(ValidSubject { subject: *s, sex }))
}

/// Where a joint counts as missing: [`blapose_core::missing::MISSING_CONFIDENCE`]
/// (its coordinates are not read; the models read it held at its last
/// detection: in a session, before its first detection at the centroid of
/// the frame's detected joints; in `AdjustSequence`, at its first
/// detection). Measured with `blapose eval --drop-joints 0.2`: holding
/// costs nothing measurable where garbage fed as is costs the Bi-GRU
/// 1.6 mm (models/README.md).
pub use blapose_core::missing::MISSING_CONFIDENCE;

/// One frame's model input and which of its Human3.6M joints were detected
/// (confidence at least [`MISSING_CONFIDENCE`]; all, without confidences).
/// Missing joints' coordinates are not validated; they are placeholders
/// for the hold to replace.
fn detected_input(
    spec: &InputFormat,
    keypoints: &[f32],
    confidence: &[f32],
) -> Result<([f32; INPUT_DIM], [bool; NUM_JOINTS]), InvalidInput> {
    let joints = spec.layout.num_joints();
    check_confidence(joints, confidence)?;
    if confidence.is_empty() || keypoints.len() != joints * 2 {
        return Ok((model_input(spec, keypoints)?, [true; NUM_JOINTS]));
    }
    let detected: Vec<bool> = confidence
        .iter()
        .map(|&c| c >= MISSING_CONFIDENCE)
        .collect();
    let mut read = keypoints.to_vec();
    for (j, _) in detected.iter().enumerate().filter(|(_, d)| !**d) {
        read[2 * j] = 0.0;
        read[2 * j + 1] = 0.0;
    }
    let input = model_input(spec, &read)?;
    let present =
        spec.layout
            .present_h36m17(&detected)
            .map_err(|_| InvalidInput::ConfidenceCount {
                got: confidence.len(),
                expected: joints,
            })?;
    Ok((input, present))
}

/// Check a frame's confidences: none, or one finite value >= 0 per joint.
fn check_confidence(joints: usize, confidence: &[f32]) -> Result<(), InvalidInput> {
    if !confidence.is_empty() && confidence.len() != joints {
        return Err(InvalidInput::ConfidenceCount {
            got: confidence.len(),
            expected: joints,
        });
    }
    if let Some((joint, &value)) = confidence
        .iter()
        .enumerate()
        .find(|(_, c)| !(c.is_finite() && **c >= 0.0))
    {
        return Err(InvalidInput::BadConfidence { joint, value });
    }
    Ok(())
}

/// Validate one frame's keypoints (every joint detected; confidences are
/// [`detected_input`]'s) and turn them into the model's input: Human3.6M-17
/// order, normalized screen coordinates, joint-major `(x, y)`.
pub fn model_input(
    spec: &InputFormat,
    keypoints: &[f32],
) -> Result<[f32; INPUT_DIM], InvalidInput> {
    let layout = spec.layout;
    let joints = layout.num_joints();
    if keypoints.len() != joints * 2 {
        return Err(InvalidInput::KeypointCount {
            got: keypoints.len(),
            expected: joints * 2,
            joints,
            layout: pb_layout_name(layout),
        });
    }
    let names = layout.joint_names();
    let mut points = [[0.0f32; 2]; NUM_JOINTS];
    for (j, pair) in keypoints.chunks_exact(2).enumerate() {
        for &v in pair {
            if !v.is_finite() {
                return Err(InvalidInput::NonFiniteKeypoint {
                    joint: j,
                    name: names[j],
                });
            }
            if v.abs() > MAX_KEYPOINT_ABS {
                return Err(InvalidInput::KeypointOutOfRange {
                    joint: j,
                    name: names[j],
                    value: v,
                });
            }
        }
        points[j] = [pair[0], pair[1]];
    }
    // Counts and values were checked above, so the conversion cannot fail;
    // map its error anyway rather than assume.
    let h36m = layout
        .to_h36m17(&points[..joints])
        .map_err(|_| InvalidInput::KeypointCount {
            got: keypoints.len(),
            expected: joints * 2,
            joints,
            layout: pb_layout_name(layout),
        })?;
    let mut input = [0.0f32; INPUT_DIM];
    for (j, p) in h36m.iter().enumerate() {
        let n = spec.coordinates.normalize(*p);
        input[2 * j] = n[0];
        input[2 * j + 1] = n[1];
    }
    Ok(input)
}

fn pb_layout_name(layout: KeypointLayout) -> &'static str {
    layout_to_proto(layout).as_str_name()
}

/// Validate a 3D pose: 51 finite values within bounds, every bone longer
/// than `MIN_BONE_LENGTH` (so the adjustment has a direction to keep).
pub fn pose(values: &[f32]) -> Result<Pose, InvalidInput> {
    if values.len() != POSE_VALUES {
        return Err(InvalidInput::PoseCount { got: values.len() });
    }
    let mut pose = [[0.0f32; 3]; NUM_JOINTS];
    for (j, xyz) in values.chunks_exact(3).enumerate() {
        for &v in xyz {
            if !v.is_finite() {
                return Err(InvalidInput::Pose(BoneError::NonFiniteJoint {
                    joint: j,
                    name: JOINT_NAMES[j],
                }));
            }
            if v.abs() > MAX_POSE_ABS {
                return Err(InvalidInput::PoseOutOfRange {
                    joint: j,
                    name: JOINT_NAMES[j],
                    value: v,
                });
            }
        }
        pose[j] = [xyz[0], xyz[1], xyz[2]];
    }
    bones::decompose(&pose).map_err(InvalidInput::Pose)?;
    Ok(pose)
}

/// A validated frame.
#[derive(Debug, Clone, PartialEq)]
pub struct ValidFrame {
    /// Model input (missing joints: placeholders).
    pub input: [f32; INPUT_DIM],
    /// Which Human3.6M joints were detected.
    pub present: [bool; NUM_JOINTS],
    /// Pose to adjust.
    pub pose: Pose,
}

/// Validate a streamed frame.
pub fn frame(spec: &InputFormat, frame: &pb::Frame) -> Result<ValidFrame, InvalidInput> {
    let (input, present) = detected_input(spec, &frame.keypoints_2d, &frame.confidence)?;
    Ok(ValidFrame {
        input,
        present,
        pose: pose(&frame.pose_3d)?,
    })
}

/// Validate a streamed frame of a session whose poses the server lifts:
/// `pose_3d` must be empty, and some joint detected (there is nothing to
/// lift otherwise); the keypoints become the model's (and the lifter's)
/// input, with which joints were detected.
pub fn keypoints_frame(
    spec: &InputFormat,
    frame: &pb::Frame,
) -> Result<([f32; INPUT_DIM], [bool; NUM_JOINTS]), InvalidInput> {
    if !frame.pose_3d.is_empty() {
        return Err(InvalidInput::PoseInLiftingSession {
            got: frame.pose_3d.len(),
        });
    }
    let (input, present) = detected_input(spec, &frame.keypoints_2d, &frame.confidence)?;
    if !present.contains(&true) {
        return Err(InvalidInput::NothingToLift);
    }
    Ok((input, present))
}

/// Check a pose the server lifter produced as a client's pose is checked
/// (finite, within bounds, no zero-length bone), so the adjustment accepts it.
pub fn lifted_pose(pose: &Pose) -> Result<Pose, InvalidInput> {
    self::pose(pose.as_flattened())
}

/// A validated offline request.
#[derive(Debug, Clone, PartialEq)]
pub struct ValidSequence {
    /// Which model to run.
    pub model: ModelKind,
    /// `frames x INPUT_DIM` inputs in normalized screen coordinates
    /// (missing joints: placeholders).
    pub inputs: Vec<f32>,
    /// `frames x NUM_JOINTS`: which joints were detected.
    pub present: Vec<bool>,
    /// One pose per frame.
    pub poses: Vec<Pose>,
    /// The request's calibration, when it sent one.
    pub camera: Option<SessionCamera>,
}

/// Validate an `AdjustSequenceRequest` (`camera_aware`: the server's
/// camera-aware models' input contract, see [`camera`]).
pub fn sequence(
    req: &pb::AdjustSequenceRequest,
    camera_aware: Option<&ModelInput>,
) -> Result<ValidSequence, InvalidInput> {
    let spec = input_format(req.input_format.as_ref())?;
    let model = offline_model(req.model)?;
    let camera = camera(req.camera.as_ref(), &spec, camera_aware)?;
    let frames = req.num_frames as usize;
    if frames == 0 {
        return Err(InvalidInput::NoFrames);
    }
    let joints = spec.layout.num_joints();
    let check = |field, got: usize, per_frame: usize| {
        let expected = frames.saturating_mul(per_frame);
        if got == expected {
            Ok(())
        } else {
            Err(InvalidInput::SequenceLength {
                field,
                got,
                expected,
                frames,
                per_frame,
            })
        }
    };
    check("keypoints_2d", req.keypoints_2d.len(), joints * 2)?;
    check("poses_3d", req.poses_3d.len(), POSE_VALUES)?;
    if !req.confidence.is_empty() {
        check("confidence", req.confidence.len(), joints)?;
    }
    let mut inputs = Vec::with_capacity(frames * INPUT_DIM);
    let mut present = Vec::with_capacity(frames * NUM_JOINTS);
    let mut poses = Vec::with_capacity(frames);
    for t in 0..frames {
        let in_frame = |e| InvalidInput::InFrame {
            frame: t,
            source: Box::new(e),
        };
        let kp = &req.keypoints_2d[t * joints * 2..(t + 1) * joints * 2];
        let conf = if req.confidence.is_empty() {
            &[][..]
        } else {
            &req.confidence[t * joints..(t + 1) * joints]
        };
        let (input, detected) = detected_input(&spec, kp, conf).map_err(in_frame)?;
        inputs.extend_from_slice(&input);
        present.extend_from_slice(&detected);
        poses.push(pose(&req.poses_3d[t * POSE_VALUES..(t + 1) * POSE_VALUES]).map_err(in_frame)?);
    }
    if !present.iter().any(|&p| p) {
        return Err(InvalidInput::NothingDetected);
    }
    Ok(ValidSequence {
        model,
        inputs,
        present,
        poses,
        camera,
    })
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use blapose_core::camera::normalize_screen;

    fn spec(layout: KeypointLayout, coordinates: Coordinates) -> InputFormat {
        InputFormat {
            layout,
            coordinates,
        }
    }

    /// A plausible standing pose (metres).
    pub(crate) fn standing_pose() -> Vec<f32> {
        let joints: [[f32; 3]; 17] = [
            [0.0, 0.0, 4.0],
            [-0.13, 0.0, 4.0],
            [-0.13, 0.45, 4.0],
            [-0.13, 0.9, 4.0],
            [0.13, 0.0, 4.0],
            [0.13, 0.45, 4.0],
            [0.13, 0.9, 4.0],
            [0.0, -0.23, 4.0],
            [0.0, -0.48, 4.0],
            [0.0, -0.58, 4.0],
            [0.0, -0.7, 4.0],
            [0.15, -0.45, 4.0],
            [0.43, -0.45, 4.0],
            [0.68, -0.45, 4.0],
            [-0.15, -0.45, 4.0],
            [-0.43, -0.45, 4.0],
            [-0.68, -0.45, 4.0],
        ];
        joints.iter().flatten().copied().collect()
    }

    pub(crate) fn format(
        layout: i32,
        coordinates: Option<pb::input_format::Coordinates>,
    ) -> pb::InputFormat {
        pb::InputFormat {
            layout,
            coordinates,
        }
    }

    #[test]
    fn input_formats_are_checked() {
        use pb::input_format::Coordinates as C;
        let size = |w, h| {
            Some(C::ImageSize(pb::ImageSize {
                width: w,
                height: h,
            }))
        };
        assert_eq!(input_format(None), Err(InvalidInput::MissingInputFormat));
        assert_eq!(
            input_format(Some(&format(0, size(10, 10)))),
            Err(InvalidInput::UnspecifiedLayout)
        );
        assert_eq!(
            input_format(Some(&format(42, size(10, 10)))),
            Err(InvalidInput::UnknownLayout(42))
        );
        assert_eq!(
            input_format(Some(&format(-1, size(10, 10)))),
            Err(InvalidInput::UnknownLayout(-1))
        );
        assert_eq!(
            input_format(Some(&format(1, None))),
            Err(InvalidInput::MissingCoordinates)
        );
        assert_eq!(
            input_format(Some(&format(1, size(0, 10)))),
            Err(InvalidInput::BadImageSize {
                width: 0,
                height: 10
            })
        );
        assert_eq!(
            input_format(Some(&format(2, Some(C::Normalized(false))))),
            Err(InvalidInput::NormalizedFalse)
        );
        let ok = input_format(Some(&format(3, size(1920, 1080)))).unwrap();
        assert_eq!(
            ok,
            spec(
                KeypointLayout::Coco17,
                Coordinates::Pixels {
                    width: 1920,
                    height: 1080
                }
            )
        );
        assert_eq!(input_format(Some(&input_format_to_proto(&ok))), Ok(ok));
        let n = input_format(Some(&format(2, Some(C::Normalized(true))))).unwrap();
        assert_eq!(n, spec(KeypointLayout::Sh16, Coordinates::Normalized));
        assert_eq!(input_format(Some(&input_format_to_proto(&n))), Ok(n));
    }

    #[test]
    fn models_are_checked() {
        assert_eq!(stream_model(0), Ok(ModelKind::Gru));
        assert_eq!(stream_model(1), Ok(ModelKind::Gru));
        assert_eq!(stream_model(2), Err(InvalidInput::OfflineModelOnStream));
        assert_eq!(stream_model(9), Err(InvalidInput::UnknownModel(9)));
        assert_eq!(offline_model(0), Ok(ModelKind::BiGru));
        assert_eq!(offline_model(1), Ok(ModelKind::Gru));
        assert_eq!(offline_model(2), Ok(ModelKind::BiGru));
        assert_eq!(offline_model(-3), Err(InvalidInput::UnknownModel(-3)));
    }

    #[test]
    fn pixels_are_normalized_after_layout_conversion() {
        let s = spec(
            KeypointLayout::H36m17,
            Coordinates::Pixels {
                width: 1000,
                height: 1002,
            },
        );
        let kp: Vec<f32> = (0..34).map(|i| i as f32 * 10.0).collect();
        let input = model_input(&s, &kp).unwrap();
        for j in 0..17 {
            let want = normalize_screen([kp[2 * j], kp[2 * j + 1]], 1000, 1002);
            assert_eq!([input[2 * j], input[2 * j + 1]], want);
        }
        // Normalized input passes through unchanged.
        let n = spec(KeypointLayout::H36m17, Coordinates::Normalized);
        assert_eq!(&model_input(&n, &kp).unwrap()[..], &kp[..]);
        // COCO goes through blapose-core's conversion.
        let c = spec(KeypointLayout::Coco17, Coordinates::Normalized);
        let coco: Vec<f32> = (0..34).map(|i| (i as f32).sin()).collect();
        let points: Vec<[f32; 2]> = coco.chunks(2).map(|p| [p[0], p[1]]).collect();
        let want = KeypointLayout::Coco17.to_h36m17(&points).unwrap();
        let got = model_input(&c, &coco).unwrap();
        for j in 0..17 {
            assert_eq!([got[2 * j], got[2 * j + 1]], want[j]);
        }
    }

    #[test]
    fn bad_keypoints_are_refused_with_a_precise_message() {
        let s = spec(KeypointLayout::Sh16, Coordinates::Normalized);
        let err = model_input(&s, &[0.0; 34]).unwrap_err();
        assert_eq!(
            err.to_string(),
            "keypoints_2d has 34 values, expected 32 (16 joints x 2) for KEYPOINT_LAYOUT_SH_16"
        );
        let mut kp = vec![0.1; 32];
        kp[5] = f32::NAN;
        assert!(matches!(
            model_input(&s, &kp),
            Err(InvalidInput::NonFiniteKeypoint { joint: 2, .. })
        ));
        kp[5] = f32::NEG_INFINITY;
        assert!(matches!(
            model_input(&s, &kp),
            Err(InvalidInput::NonFiniteKeypoint { joint: 2, .. })
        ));
        kp[5] = 3e7;
        assert!(matches!(
            model_input(&s, &kp),
            Err(InvalidInput::KeypointOutOfRange { joint: 2, .. })
        ));
        kp[5] = 0.1;
        assert!(model_input(&s, &kp).is_ok());
        assert!(matches!(
            detected_input(&s, &kp, &[1.0; 17]),
            Err(InvalidInput::ConfidenceCount {
                got: 17,
                expected: 16
            })
        ));
        let mut conf = vec![0.9; 16];
        conf[3] = -0.5;
        assert!(matches!(
            detected_input(&s, &kp, &conf),
            Err(InvalidInput::BadConfidence { joint: 3, .. })
        ));
        conf[3] = f32::NAN;
        assert!(matches!(
            detected_input(&s, &kp, &conf),
            Err(InvalidInput::BadConfidence { joint: 3, .. })
        ));
        conf[3] = 0.0;
        assert!(detected_input(&s, &kp, &conf).is_ok());
        assert_eq!(err.to_status().code(), tonic::Code::InvalidArgument);
    }

    #[test]
    fn bad_poses_are_refused() {
        let good = standing_pose();
        assert!(pose(&good).is_ok());
        assert_eq!(pose(&good[..50]), Err(InvalidInput::PoseCount { got: 50 }));
        let mut p = good.clone();
        p[3 * 5 + 1] = f32::NAN;
        assert!(matches!(
            pose(&p),
            Err(InvalidInput::Pose(BoneError::NonFiniteJoint {
                joint: 5,
                ..
            }))
        ));
        let mut p = good.clone();
        p[3 * 16] = f32::INFINITY;
        assert!(matches!(
            pose(&p),
            Err(InvalidInput::Pose(BoneError::NonFiniteJoint {
                joint: 16,
                ..
            }))
        ));
        let mut p = good.clone();
        p[3 * 7 + 2] = -2e4;
        assert!(matches!(
            pose(&p),
            Err(InvalidInput::PoseOutOfRange { joint: 7, .. })
        ));
        // Zero-length bone: the left wrist on the left elbow (bone 12).
        let mut p = good.clone();
        p.copy_within(3 * 12..3 * 13, 3 * 13);
        let err = pose(&p).unwrap_err();
        assert!(
            matches!(
                err,
                InvalidInput::Pose(BoneError::ZeroLengthBone { bone: 12, .. })
            ),
            "{err}"
        );
        assert!(err.to_string().contains("l_forearm"), "{err}");
    }

    #[test]
    fn lifting_frames_carry_keypoints_only() {
        let s = spec(KeypointLayout::Coco17, Coordinates::Normalized);
        let kp: Vec<f32> = (0..34).map(|i| (i as f32).cos()).collect();
        let mut f = pb::Frame {
            frame_index: 4,
            keypoints_2d: kp.clone(),
            confidence: vec![],
            pose_3d: vec![],
        };
        assert_eq!(
            keypoints_frame(&s, &f),
            model_input(&s, &kp).map(|input| (input, [true; NUM_JOINTS])),
            "the same input as a client-pose frame"
        );
        // Nothing detected: nothing to lift (the session is unchanged).
        f.confidence = vec![0.0; 17];
        assert_eq!(keypoints_frame(&s, &f), Err(InvalidInput::NothingToLift));
        f.confidence = vec![1.0; 17];
        f.confidence[0] = 0.0;
        f.keypoints_2d[0] = f32::NAN;
        let (_, present) = keypoints_frame(&s, &f).unwrap();
        assert!(!present[JOINT_NAMES.iter().position(|n| *n == "neck_nose").unwrap()]);
        f.keypoints_2d[0] = kp[0];
        f.confidence.clear();
        f.pose_3d = standing_pose();
        let err = keypoints_frame(&s, &f).unwrap_err();
        assert_eq!(err, InvalidInput::PoseInLiftingSession { got: 51 });
        assert!(err.to_string().contains("server lifter"), "{err}");
        f.pose_3d.clear();
        f.keypoints_2d.pop();
        assert!(matches!(
            keypoints_frame(&s, &f),
            Err(InvalidInput::KeypointCount { got: 33, .. })
        ));
        // Lifted poses are checked like client poses.
        let good = pose(&standing_pose()).unwrap();
        assert_eq!(lifted_pose(&good), Ok(good));
        let mut flat = good;
        flat[3] = flat[2];
        assert!(matches!(
            lifted_pose(&flat),
            Err(InvalidInput::Pose(BoneError::ZeroLengthBone { .. }))
        ));
    }

    #[test]
    fn sequences_are_checked_frame_by_frame() {
        let fmt = format(1, Some(pb::input_format::Coordinates::Normalized(true)));
        let mut req = pb::AdjustSequenceRequest {
            input_format: Some(fmt),
            model: 0,
            num_frames: 3,
            keypoints_2d: vec![0.1; 3 * 34],
            confidence: vec![],
            poses_3d: standing_pose().repeat(3),
            camera: None,
            subject: None,
            motion: None,
        };
        let ok = sequence(&req, None).unwrap();
        assert_eq!(ok.model, ModelKind::BiGru);
        assert_eq!(ok.inputs.len(), 3 * INPUT_DIM);
        assert_eq!(ok.poses.len(), 3);

        req.poses_3d[51 + 4] = f32::NAN;
        let err = sequence(&req, None).unwrap_err();
        assert!(err.to_string().starts_with("frame 1: pose_3d:"), "{err}");
        req.poses_3d[51 + 4] = 0.0;

        req.num_frames = 4;
        assert!(matches!(
            sequence(&req, None),
            Err(InvalidInput::SequenceLength {
                field: "keypoints_2d",
                got: 102,
                expected: 136,
                ..
            })
        ));
        req.num_frames = 0;
        assert_eq!(sequence(&req, None), Err(InvalidInput::NoFrames));
        req.num_frames = u32::MAX;
        assert!(matches!(
            sequence(&req, None),
            Err(InvalidInput::SequenceLength { .. })
        ));
        req.num_frames = 3;
        req.confidence = vec![1.0; 5];
        assert!(matches!(
            sequence(&req, None),
            Err(InvalidInput::SequenceLength {
                field: "confidence",
                ..
            })
        ));
    }

    pub(crate) fn calibration() -> pb::CameraCalibration {
        // Looking 12 degrees down, centred principal point.
        let tilt = 12f32.to_radians();
        pb::CameraCalibration {
            up: vec![0.0, -tilt.cos(), -tilt.sin()],
            focal_x: 1150.0,
            focal_y: 1150.0,
            principal_x: 500.0,
            principal_y: 500.0,
            image_size: None,
            height: 0.0,
            distortion: vec![],
        }
    }

    #[test]
    fn cameras_are_checked_against_the_input_and_the_server() {
        let pixels = spec(
            KeypointLayout::H36m17,
            Coordinates::Pixels {
                width: 1000,
                height: 1000,
            },
        );
        let normalized = spec(KeypointLayout::H36m17, Coordinates::Normalized);
        let c = calibration();
        assert_eq!(camera(None, &pixels, None), Ok(None));
        let got = camera(Some(&c), &pixels, Some(&ANY_CAMERA))
            .unwrap()
            .unwrap();
        assert_eq!(got.calibration, c);
        assert_eq!(got.view.image_size, (1000, 1000));
        assert_eq!(got.view.camera_height, None);
        assert_eq!(
            camera(Some(&c), &pixels, None),
            Err(InvalidInput::NoCameraAwareModel)
        );
        assert_eq!(
            camera(Some(&c), &normalized, Some(&ANY_CAMERA)),
            Err(InvalidInput::CameraImageSizeMissing)
        );
        let sized = pb::CameraCalibration {
            image_size: Some(pb::ImageSize {
                width: 1000,
                height: 1000,
            }),
            ..c.clone()
        };
        // The same camera, whether its image comes from the input or itself.
        assert_eq!(
            camera(Some(&sized), &normalized, Some(&ANY_CAMERA))
                .unwrap()
                .unwrap()
                .view,
            got.view
        );
        let other = pb::CameraCalibration {
            image_size: Some(pb::ImageSize {
                width: 1920,
                height: 1080,
            }),
            ..c.clone()
        };
        assert!(matches!(
            camera(Some(&other), &pixels, Some(&ANY_CAMERA)),
            Err(InvalidInput::CameraImageSizeMismatch {
                camera_width: 1920,
                ..
            })
        ));
        let short = pb::CameraCalibration {
            up: vec![0.0, -1.0],
            ..c.clone()
        };
        assert_eq!(
            camera(Some(&short), &pixels, Some(&ANY_CAMERA)),
            Err(InvalidInput::CameraUpCount { got: 2 })
        );
        for bad in [
            pb::CameraCalibration {
                focal_x: f32::NAN,
                ..c.clone()
            },
            pb::CameraCalibration {
                focal_y: -3.0,
                ..c.clone()
            },
            pb::CameraCalibration {
                up: vec![0.0, 0.0, 0.0],
                ..c.clone()
            },
            pb::CameraCalibration {
                up: vec![0.0, -0.1, -1.0],
                ..c.clone()
            },
        ] {
            let err = camera(Some(&bad), &pixels, Some(&ANY_CAMERA)).unwrap_err();
            assert!(matches!(err, InvalidInput::Camera(_)), "{err}");
            assert!(err.to_string().starts_with("camera: "), "{err}");
        }
    }

    /// Camera-aware models that read plain rectified keypoints from any
    /// camera.
    pub(crate) const ANY_CAMERA: ModelInput = ModelInput::level();

    #[test]
    fn wide_camera_models_need_the_height_and_a_calibration_they_were_trained_for() {
        let pixels = spec(
            KeypointLayout::H36m17,
            Coordinates::Pixels {
                width: 1000,
                height: 1000,
            },
        );
        let wide = ModelInput::from_training(true, true, true);
        assert_eq!(wide.trained_cameras, Some(level::WIDE_CAMERA_ENVELOPE));
        // 10 degrees down, 47 degrees across, 1.5 m up: served.
        let c = pb::CameraCalibration {
            height: 1.5,
            ..calibration()
        };
        let got = camera(Some(&c), &pixels, Some(&wide)).unwrap().unwrap();
        assert_eq!(got.view.camera_height, Some(1.5));
        let refused =
            |c: pb::CameraCalibration| camera(Some(&c), &pixels, Some(&wide)).unwrap_err();
        assert_eq!(
            refused(pb::CameraCalibration {
                height: 0.0,
                ..c.clone()
            }),
            InvalidInput::CameraHeightRequired
        );
        for (bad, field) in [
            (
                pb::CameraCalibration {
                    height: 4.0,
                    ..c.clone()
                },
                "camera.height",
            ),
            (
                pb::CameraCalibration {
                    // 50 degrees down.
                    up: vec![0.0, -50f32.to_radians().cos(), -50f32.to_radians().sin()],
                    ..c.clone()
                },
                "camera.up",
            ),
            (
                pb::CameraCalibration {
                    // 28 degrees across.
                    focal_x: 2000.0,
                    focal_y: 2000.0,
                    ..c.clone()
                },
                "camera.focal_x",
            ),
        ] {
            let err = refused(bad);
            assert!(
                matches!(&err, InvalidInput::OutsideTrainedCameras(e) if e.field == field),
                "{err}"
            );
            assert!(err.to_string().starts_with(field), "{err}");
        }
        // The same calibrations are fine for models trained on any camera.
        let far = pb::CameraCalibration {
            height: 4.0,
            ..c.clone()
        };
        assert!(camera(Some(&far), &pixels, Some(&ANY_CAMERA)).is_ok());
    }

    #[test]
    fn a_lens_distortion_is_read_or_refused_by_name() {
        let pixels = spec(
            KeypointLayout::H36m17,
            Coordinates::Pixels {
                width: 1000,
                height: 1000,
            },
        );
        let with = |distortion: Vec<f32>| pb::CameraCalibration {
            distortion,
            ..calibration()
        };
        let plain = camera(Some(&calibration()), &pixels, Some(&ANY_CAMERA))
            .unwrap()
            .unwrap();
        assert_eq!(plain.view.lens, None);
        for ok in [
            vec![-0.2, 0.05, 0.001, -0.001],
            vec![-0.2, 0.05, 0.001, -0.001, 0.01],
        ] {
            let lens = camera(Some(&with(ok.clone())), &pixels, Some(&ANY_CAMERA))
                .unwrap()
                .unwrap();
            // Echoed as sent, and read into the view.
            assert_eq!(lens.calibration.distortion, ok);
            assert!(lens.view.lens.is_some());
        }
        for bad in [
            vec![0.1, 0.2, 0.3],
            vec![-0.2, f32::NAN, 0.0, 0.0],
            // Folds over within the picture.
            vec![-2.0, 0.0, 0.0, 0.0],
        ] {
            let err = camera(Some(&with(bad.clone())), &pixels, Some(&ANY_CAMERA)).unwrap_err();
            assert!(
                matches!(err, InvalidInput::CameraDistortion(_)),
                "{bad:?}: {err}"
            );
            assert!(err.to_string().starts_with("camera.distortion"), "{err}");
        }
    }
}

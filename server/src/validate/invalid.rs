//! What the validate stage refuses, each error naming the value that is
//! wrong and what was expected (all INVALID_ARGUMENT), and the bounds the
//! messages quote.

use blapose_core::bones::BoneError;
use blapose_core::lens::LensError;
use blapose_core::level::{LevelError, OutsideEnvelope, MAX_CAMERA_HEIGHT, MIN_CAMERA_HEIGHT};
use blapose_core::missing::MISSING_CONFIDENCE;
use blapose_core::pose::POSE_VALUES;
use blapose_model::input::ContractError;
use blapose_model::stature::{MAX_STATURE_M, MIN_STATURE_M};

/// Largest accepted magnitude of a 2D keypoint value (pixels or normalized).
pub const MAX_KEYPOINT_ABS: f32 = 1e6;
/// Largest accepted magnitude of a 3D pose coordinate, in metres.
pub const MAX_POSE_ABS: f32 = 1e4;

/// A client input the server refuses (INVALID_ARGUMENT).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum InvalidInput {
    /// `input_format` is absent.
    #[error("input_format is required (keypoint layout and image size or normalized=true)")]
    MissingInputFormat,
    /// Layout not set.
    #[error(
        "input_format.layout is KEYPOINT_LAYOUT_UNSPECIFIED; choose H36M_17, SH_16 or COCO_17"
    )]
    UnspecifiedLayout,
    /// Layout number unknown to this server.
    #[error("input_format.layout {0} is not a known KeypointLayout (known: 1 H36M_17, 2 SH_16, 3 COCO_17)")]
    UnknownLayout(i32),
    /// Neither image size nor normalized.
    #[error("input_format needs either image_size or normalized=true")]
    MissingCoordinates,
    /// Width or height is zero.
    #[error("input_format.image_size must be positive, got {width}x{height}")]
    BadImageSize {
        /// Width given.
        width: u32,
        /// Height given.
        height: u32,
    },
    /// `normalized: false`.
    #[error("input_format.normalized was set to false; set it to true or give image_size instead")]
    NormalizedFalse,
    /// A model number this server does not know.
    #[error("model {0} is not a known Model (known: 1 MODEL_ONLINE_GRU, 2 MODEL_OFFLINE_BIGRU)")]
    UnknownModel(i32),
    /// The Bi-GRU on a stream.
    #[error("MODEL_OFFLINE_BIGRU needs the whole sequence; use AdjustSequence, or MODEL_ONLINE_GRU for streaming")]
    OfflineModelOnStream,
    /// `server_lifter` on a server started without a lifter.
    #[error("server_lifter was requested but this server has no lifter (it was started with --no-lifter, or built without the embedded one: drop the flag or give --lifter-weights FILE); otherwise send pose_3d with every frame")]
    NoServerLifter,
    /// A pose in a session whose poses the server lifts.
    #[error("pose_3d has {got} values, but this session's poses come from the server lifter (it was opened with server_lifter): send keypoints_2d only, with pose_3d empty")]
    PoseInLiftingSession {
        /// Values given.
        got: usize,
    },
    /// Wrong keypoint value count.
    #[error(
        "keypoints_2d has {got} values, expected {expected} ({joints} joints x 2) for {layout}"
    )]
    KeypointCount {
        /// Values given.
        got: usize,
        /// Values expected.
        expected: usize,
        /// Joints of the layout.
        joints: usize,
        /// The layout name.
        layout: &'static str,
    },
    /// A keypoint value is NaN or infinite.
    #[error("keypoints_2d joint {joint} ({name}) is not finite")]
    NonFiniteKeypoint {
        /// Joint index in the client's layout.
        joint: usize,
        /// Joint name in that layout.
        name: &'static str,
    },
    /// A keypoint value is absurdly large.
    #[error(
        "keypoints_2d joint {joint} ({name}) has value {value}, outside +-{MAX_KEYPOINT_ABS:e}"
    )]
    KeypointOutOfRange {
        /// Joint index in the client's layout.
        joint: usize,
        /// Joint name in that layout.
        name: &'static str,
        /// The value.
        value: f32,
    },
    /// Wrong confidence count.
    #[error("confidence has {got} values, expected 0 or {expected} (one per joint)")]
    ConfidenceCount {
        /// Values given.
        got: usize,
        /// Joints of the layout.
        expected: usize,
    },
    /// A confidence is negative or not finite.
    #[error("confidence of joint {joint} is {value}; it must be finite and >= 0")]
    BadConfidence {
        /// Joint index in the client's layout.
        joint: usize,
        /// The value.
        value: f32,
    },
    /// Wrong pose value count.
    #[error("pose_3d has {got} values, expected {POSE_VALUES} (17 joints x 3, metres)")]
    PoseCount {
        /// Values given.
        got: usize,
    },
    /// A pose coordinate is absurdly large.
    #[error("pose_3d joint {joint} ({name}) has coordinate {value}, outside +-{MAX_POSE_ABS:e} m")]
    PoseOutOfRange {
        /// Joint index.
        joint: usize,
        /// Joint name.
        name: &'static str,
        /// The value.
        value: f32,
    },
    /// The pose cannot be adjusted (non-finite joint, zero-length bone).
    #[error("pose_3d: {0}")]
    Pose(BoneError),
    /// `num_frames` is zero.
    #[error("num_frames must be >= 1")]
    NoFrames,
    /// `subject.height_m` outside the stature model's range.
    #[error("subject.height_m is {0} m; it must be between {MIN_STATURE_M} and {MAX_STATURE_M} m")]
    SubjectHeight(f32),
    /// `subject.sex` is not a known value.
    #[error("subject.sex {0} is not a known value (0 unspecified, 1 female, 2 male)")]
    SubjectSex(i32),
    /// A lifting session's frame has no detected joint: nothing to lift.
    #[error("every joint is missing (confidence below {MISSING_CONFIDENCE}): a server_lifter session has nothing to lift; the session is unchanged")]
    NothingToLift,
    /// Every joint of every frame has a confidence below
    /// [`MISSING_CONFIDENCE`]: there is nothing to read.
    #[error("every joint of every frame is missing (confidence below {MISSING_CONFIDENCE}): nothing to read")]
    NothingDetected,
    /// A sequence buffer has the wrong length.
    #[error("{field} has {got} values, expected {expected} ({frames} frames x {per_frame})")]
    SequenceLength {
        /// The field.
        field: &'static str,
        /// Values given.
        got: usize,
        /// Values expected.
        expected: usize,
        /// Frames declared.
        frames: usize,
        /// Values per frame.
        per_frame: usize,
    },
    /// `camera.up` does not have 3 values.
    #[error(
        "camera.up has {got} values, expected 3 (world up in camera x right, y down, z forward)"
    )]
    CameraUpCount {
        /// Values given.
        got: usize,
    },
    /// Normalized keypoints but no image size for the pixel calibration.
    #[error("camera.image_size is required when the keypoints are normalized (the calibration is in pixels of that image)")]
    CameraImageSizeMissing,
    /// The calibration's image differs from the keypoints' image.
    #[error("camera.image_size {camera_width}x{camera_height} differs from input_format.image_size {width}x{height}; leave it out or make them equal")]
    CameraImageSizeMismatch {
        /// The calibration's width.
        camera_width: u32,
        /// The calibration's height.
        camera_height: u32,
        /// The input's width.
        width: u32,
        /// The input's height.
        height: u32,
    },
    /// The calibration cannot be used.
    #[error("camera: {0}")]
    Camera(LevelError),
    /// The camera height is not 0 (unknown) or a plausible height.
    #[error("camera.height {0} is not 0 (not given) or a height of {MIN_CAMERA_HEIGHT} to {MAX_CAMERA_HEIGHT} m")]
    CameraHeight(f32),
    /// Models that read keypoints scaled to the floor, without the camera
    /// height.
    #[error("camera.height is required: the camera-aware models read a person's size relative to the camera's height above the floor (metres; measure it with a tape)")]
    CameraHeightRequired,
    /// `camera.distortion` is not a usable lens model.
    #[error("camera.distortion: {0}")]
    CameraDistortion(LensError),
    /// A calibration the camera-aware models were not trained for.
    #[error("{0}")]
    OutsideTrainedCameras(OutsideEnvelope),
    /// A calibration the camera-aware models' input contract cannot read
    /// for another reason than the ones above.
    #[error("camera: {0}")]
    CameraContract(ContractError),
    /// A camera on a server without camera-aware models.
    #[error("a camera calibration was sent but this server has no camera-aware models (it was started with --no-camera-aware); leave camera out")]
    NoCameraAwareModel,
    /// A problem in one frame of a sequence.
    #[error("frame {frame}: {source}")]
    InFrame {
        /// Frame index in the sequence.
        frame: usize,
        /// The problem.
        source: Box<InvalidInput>,
    },
}

/// What a model's input contract refuses in a calibration, named as the
/// checks of [`camera`] name it.
impl From<ContractError> for InvalidInput {
    fn from(e: ContractError) -> Self {
        match e {
            ContractError::CameraHeightRequired => InvalidInput::CameraHeightRequired,
            ContractError::Level(e) => InvalidInput::Camera(e),
            other => InvalidInput::CameraContract(other),
        }
    }
}

impl InvalidInput {
    /// As a gRPC status.
    pub fn to_status(&self) -> tonic::Status {
        tonic::Status::invalid_argument(self.to_string())
    }
}

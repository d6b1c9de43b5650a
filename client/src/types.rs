//! Typed mirrors of the wire messages.
//!
//! The generated protobuf types carry flat `Vec<f32>`s and bare `i32` enum
//! numbers; callers of the library should instead see poses as
//! [`blapose_core::Pose`] and layouts as an enum, with the conversion (and
//! its validation) done once, here. A server answer whose arrays have the
//! wrong length is a protocol violation, reported as such rather than
//! turning into a panic or a silently truncated pose.
//!
//! What client and server share is not written here: the layouts,
//! [`Coordinates`] and [`InputFormat`] are blapose-core's (re-exported),
//! their wire mapping is `blapose_proto::convert`'s, and a calibration's
//! value checks and height limits are `blapose_core::level`'s, the server's
//! own. This module adds the client's view: its error messages, the replay
//! file's layout codes and the messages only a client reads.

use std::collections::BTreeMap;
use std::fmt;
use std::str::FromStr;
use std::time::Duration;

use blapose_core::camera::Camera;
use blapose_core::lens::{LensDistortion, LensError};
use blapose_core::level::{self, CalibrationError};
use blapose_core::skeleton::NUM_BONES;
use blapose_core::{BoneLengths, Pose};
use blapose_proto::v1 as pb;

use crate::error::ClientError;

pub use blapose_core::layouts::{Coordinates, InputFormat, KeypointLayout};
pub use blapose_core::level::{MAX_CAMERA_HEIGHT, MIN_CAMERA_HEIGHT};
pub use blapose_proto::convert::{layout_from_proto, layout_to_proto};

/// The code a replay file stores in its `layout` array: the wire number
/// (1 = H36M-17, 2 = SH-16, 3 = COCO-17).
pub const fn layout_code(layout: KeypointLayout) -> u32 {
    layout_to_proto(layout) as u32
}

/// The layout a replay file's `layout` code names.
pub fn layout_from_code(code: u32) -> Option<KeypointLayout> {
    i32::try_from(code).ok().and_then(layout_from_proto)
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

/// A camera's calibration, for the server's camera-aware models.
///
/// A session (or offline request) that sends one is served by the
/// camera-aware models: the server turns its keypoints into what a level
/// camera at the same place would see before the model reads them. With
/// `distortion` the server first undoes the lens (keypoints detected in the
/// raw image); without it keypoints are taken as undistorted pixels.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CameraCalibration {
    /// Direction of world "up" (against gravity) in camera coordinates
    /// (x right, y down, z along the optical axis), any non-zero length:
    /// for world-to-camera rotation `R` and world z up, `R`'s third column.
    pub up: [f32; 3],
    /// `[fx, fy]` focal lengths in pixels, both > 0.
    pub focal: [f32; 2],
    /// `[cx, cy]` principal point in pixels.
    pub principal: [f32; 2],
    /// `(width, height)` of the image these pixel values refer to. Required
    /// with normalized keypoints; with pixel keypoints `None` means the
    /// input format's size, and a size given must equal it.
    pub image_size: Option<(u32, u32)>,
    /// The camera's height above the floor in metres, [`MIN_CAMERA_HEIGHT`]
    /// to [`MAX_CAMERA_HEIGHT`]; `None` = not given (0 on the wire). A
    /// rectified picture does not show it (seen from a camera k times
    /// higher, a scene looks like one k times smaller): camera-aware models
    /// trained height-normalized predict lengths as seen from 1.56 m and
    /// the server scales them by `height / 1.56`, assuming 1.56 m when it is
    /// not given. Other models ignore it.
    pub height: Option<f32>,
    /// The lens's distortion in OpenCV's model and order, `[k1, k2, p1,
    /// p2, k3]` (what `cv2.calibrateCamera` reports; k3 = 0 for a
    /// four-coefficient calibration), for keypoints detected in the raw
    /// image; `None`: the keypoints are undistorted pixels.
    pub distortion: Option<[f32; 5]>,
}

/// Why a [`CameraCalibration`] cannot be used.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum CameraError {
    /// A value is NaN or infinite.
    #[error("{field} is not finite")]
    NonFinite {
        /// Which field: `up`, `focal`, `principal` or `height`.
        field: &'static str,
    },
    /// The up direction has no length.
    #[error("up {0:?} has no length (it must be a direction)")]
    ZeroUp([f32; 3]),
    /// A focal length is not positive.
    #[error("focal lengths must be > 0, got {0:?}")]
    Focal([f32; 2]),
    /// The height is outside [`MIN_CAMERA_HEIGHT`]..=[`MAX_CAMERA_HEIGHT`].
    #[error("height {0} m is not a camera height of {MIN_CAMERA_HEIGHT} to {MAX_CAMERA_HEIGHT} m (leave it out when unknown)")]
    Height(f32),
    /// The image size has a zero side.
    #[error("image_size must be positive, got {width}x{height}")]
    ImageSize {
        /// Width in pixels.
        width: u32,
        /// Height in pixels.
        height: u32,
    },
    /// Normalized keypoints, but no image size to relate them to pixels.
    #[error("image_size is required with normalized keypoints (the calibration is in pixels)")]
    ImageSizeMissing,
    /// The distortion is not a usable lens model.
    #[error("distortion: {0}")]
    Distortion(LensError),
    /// The calibration's image size differs from the pixel keypoints'.
    #[error("image_size {camera_width}x{camera_height} differs from the keypoints' image size {width}x{height}")]
    ImageSizeMismatch {
        /// The calibration's width.
        camera_width: u32,
        /// The calibration's height.
        camera_height: u32,
        /// The keypoints' width.
        width: u32,
        /// The keypoints' height.
        height: u32,
    },
}

impl CameraError {
    /// The calibration field at fault: `up`, `focal`, `principal`,
    /// `image_size`, `height` or `distortion`.
    pub const fn field(&self) -> &'static str {
        match self {
            CameraError::NonFinite { field } => field,
            CameraError::ZeroUp(_) => "up",
            CameraError::Focal(_) => "focal",
            CameraError::Height(_) => "height",
            CameraError::Distortion(_) => "distortion",
            CameraError::ImageSize { .. }
            | CameraError::ImageSizeMissing
            | CameraError::ImageSizeMismatch { .. } => "image_size",
        }
    }

    /// What a failed shared check ([`blapose_core::level`]) means for
    /// `calibration`, in this crate's words.
    fn from_check(error: CalibrationError, calibration: &CameraCalibration) -> Self {
        match error {
            CalibrationError::NonFinite { field } => CameraError::NonFinite { field },
            CalibrationError::ZeroUp { .. } => CameraError::ZeroUp(calibration.up),
            CalibrationError::InvalidFocal { .. } => CameraError::Focal(calibration.focal),
            CalibrationError::InvalidImageSize { width, height } => {
                CameraError::ImageSize { width, height }
            }
            CalibrationError::ImageSizeMissing => CameraError::ImageSizeMissing,
            CalibrationError::ImageSizeMismatch {
                camera_width,
                camera_height,
                width,
                height,
            } => CameraError::ImageSizeMismatch {
                camera_width,
                camera_height,
                width,
                height,
            },
        }
    }
}

impl CameraCalibration {
    /// The calibration of `camera`: `up` is the third column of its
    /// world-to-camera rotation, the image size its resolution and the
    /// height its centre's z. This assumes world z up with the floor at
    /// z = 0 (as in Human3.6M and the CMU examples); for another world
    /// frame, set `up` and `height` yourself. Values are rounded to `f32`;
    /// the distortion is dropped (Human3.6M's lens model is not OpenCV's).
    pub fn from_camera(camera: &Camera) -> Self {
        let r = &camera.rotation;
        CameraCalibration {
            up: [r[0][2], r[1][2], r[2][2]].map(|v| v as f32),
            focal: camera.focal.map(|v| v as f32),
            principal: camera.principal.map(|v| v as f32),
            image_size: Some((camera.width, camera.height)),
            height: Some(camera.center[2] as f32),
            distortion: None,
        }
    }

    /// Check the values the protocol requires, with the server's own checks
    /// ([`blapose_core::level`]): everything finite, focal lengths > 0, `up`
    /// of non-zero length, a given image size positive, a given height
    /// within [`MIN_CAMERA_HEIGHT`]..=[`MAX_CAMERA_HEIGHT`]. (The server also
    /// refuses an optical axis more than
    /// [`MAX_TILT_DEG`](blapose_core::level::MAX_TILT_DEG) degrees off the
    /// horizon; that is left to it, so a file's calibration can be loaded
    /// and replayed without it.)
    pub fn validate(&self) -> Result<(), CameraError> {
        let error = |e| CameraError::from_check(e, self);
        level::check_calibration(
            self.up.map(f64::from),
            self.focal.map(f64::from),
            self.principal.map(f64::from),
        )
        .map_err(error)?;
        if let Some((width, height)) = self.image_size {
            level::check_image_size(width, height).map_err(error)?;
        }
        if let Some(height) = self.height {
            if !height.is_finite() {
                return Err(CameraError::NonFinite { field: "height" });
            }
            if !level::is_camera_height(height) {
                return Err(CameraError::Height(height));
            }
        }
        LensDistortion::checked(
            self.distortion.as_ref().map_or(&[][..], |d| &d[..]),
            self.focal.map(f64::from),
            self.principal.map(f64::from),
            self.image_size,
        )
        .map_err(CameraError::Distortion)?;
        Ok(())
    }

    /// [`validate`](Self::validate), and check that the image size fits
    /// keypoints in `coordinates`: required for normalized ones, equal to
    /// theirs (or absent) for pixels.
    pub fn validate_for(&self, coordinates: Coordinates) -> Result<(), CameraError> {
        self.validate()?;
        level::calibration_image_size(coordinates, self.image_size)
            .map(|_| ())
            .map_err(|e| CameraError::from_check(e, self))
    }

    /// The wire message.
    pub fn to_proto(&self) -> pb::CameraCalibration {
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

    /// Parse the wire message (as echoed by the server). Only the shape is
    /// checked (`up` must have 3 values); see [`validate`](Self::validate).
    /// A height of 0 is "not given" (`None`).
    pub fn from_proto(msg: &pb::CameraCalibration) -> Result<Self, ClientError> {
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
}

impl fmt::Display for CameraCalibration {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "up [{:.3}, {:.3}, {:.3}], focal [{}, {}] px, principal [{}, {}] px",
            self.up[0],
            self.up[1],
            self.up[2],
            self.focal[0],
            self.focal[1],
            self.principal[0],
            self.principal[1]
        )?;
        if let Some((w, h)) = self.image_size {
            write!(f, ", image {w}x{h}")?;
        }
        if let Some(height) = self.height {
            write!(f, ", height {height} m")?;
        }
        if let Some(d) = self.distortion {
            write!(f, ", distortion {d:?}")?;
        }
        Ok(())
    }
}

/// Which bone-length model adjusts the poses.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum ModelChoice {
    /// The causal online GRU (streams; also offline, giving what a stream
    /// would up to float rounding in the last bits).
    OnlineGru,
    /// The offline Bi-GRU over the whole sequence (offline RPC only).
    OfflineBiGru,
}

impl ModelChoice {
    /// The wire enum.
    pub const fn to_proto(self) -> pb::Model {
        match self {
            ModelChoice::OnlineGru => pb::Model::OnlineGru,
            ModelChoice::OfflineBiGru => pb::Model::OfflineBigru,
        }
    }

    /// The model with this wire number; `None` for UNSPECIFIED or unknown.
    pub fn from_proto(value: i32) -> Option<ModelChoice> {
        [ModelChoice::OnlineGru, ModelChoice::OfflineBiGru]
            .into_iter()
            .find(|m| m.to_proto() as i32 == value)
    }

    /// Short name used on the command line.
    pub const fn as_str(self) -> &'static str {
        match self {
            ModelChoice::OnlineGru => "gru",
            ModelChoice::OfflineBiGru => "bigru",
        }
    }
}

impl fmt::Display for ModelChoice {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

impl FromStr for ModelChoice {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s
            .trim()
            .to_ascii_lowercase()
            .replace(['-', '_'], "")
            .as_str()
        {
            "gru" | "online" | "onlinegru" => Ok(ModelChoice::OnlineGru),
            "bigru" | "offline" | "offlinebigru" => Ok(ModelChoice::OfflineBiGru),
            _ => Err(format!("unknown model {s:?} (expected gru or bigru)")),
        }
    }
}

/// One frame to send on a session.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameInput {
    /// Client's frame number, echoed back in the answer.
    pub frame_index: u64,
    /// 2D keypoints, `J` joints in the session's layout.
    pub keypoints_2d: Vec<[f32; 2]>,
    /// Optional per-joint confidence (empty or `J` values).
    pub confidence: Vec<f32>,
    /// The lifted 3D pose to adjust (metres, Human3.6M order); `None` in a
    /// session whose poses the server lifts (keypoints only).
    pub pose_3d: Option<Pose>,
}

impl FrameInput {
    /// The wire message.
    pub fn to_proto(&self) -> pb::Frame {
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
        Ok(AdjustedFrame {
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

/// A person's sex, when the client knows it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Sex {
    /// Female.
    Female,
    /// Male.
    Male,
}

/// The person's body as far as the client knows it (`OpenSession.subject`,
/// `AdjustSequenceRequest.subject`): with it the server answers with the
/// stature regression's lengths for that height (and sex). The server
/// accepts statures of 1.0 to 2.3 m and refuses others, naming the field.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Subject {
    /// Stature, metres.
    pub height_m: f32,
    /// Sex, if known.
    pub sex: Option<Sex>,
}

impl Subject {
    /// As the proto message.
    pub fn to_proto(&self) -> pb::Subject {
        pb::Subject {
            height_m: self.height_m,
            sex: match self.sex {
                None => pb::Sex::Unspecified,
                Some(Sex::Female) => pb::Sex::Female,
                Some(Sex::Male) => pb::Sex::Male,
            } as i32,
        }
    }

    /// From the proto message (an unknown sex reads as unknown).
    pub fn from_proto(msg: &pb::Subject) -> Self {
        Subject {
            height_m: msg.height_m,
            sex: match pb::Sex::try_from(msg.sex) {
                Ok(pb::Sex::Female) => Some(Sex::Female),
                Ok(pb::Sex::Male) => Some(Sex::Male),
                _ => None,
            },
        }
    }
}

impl std::fmt::Display for Subject {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{:.2} m", self.height_m)?;
        match self.sex {
            Some(Sex::Female) => write!(f, ", female"),
            Some(Sex::Male) => write!(f, ", male"),
            None => Ok(()),
        }
    }
}

/// What the server said when a session was opened or resumed.
#[derive(Debug, Clone, PartialEq)]
pub struct SessionInfo {
    /// Opaque session id (keep it to resume or close the session).
    pub session_id: String,
    /// True when this answers a resume.
    pub resumed: bool,
    /// Frames processed so far.
    pub frames_seen: u64,
    /// Current estimate; `None` before the first frame.
    pub bone_lengths: Option<BoneLengths>,
    /// The session's input format.
    pub input_format: InputFormat,
    /// The model serving the session.
    pub model: ModelChoice,
    /// How long a detached session survives without a stream.
    pub ttl: Duration,
    /// The server lifter lifting this session's poses; `None` when the
    /// client sends them.
    pub lifter: Option<String>,
    /// The session's camera calibration as opened: `Some` when the session
    /// is served by the camera-aware model, `None` for the default one.
    pub camera: Option<CameraCalibration>,
    /// A session token for the state at this answer (`frames_seen`):
    /// `Some` when the server has a session key, `None` otherwise.
    pub token: Option<SessionToken>,
    /// The session's subject as opened (its lengths are the stature
    /// regression's); `None` when it has none.
    pub subject: Option<Subject>,
}

/// A session token: the session's whole state, opaque and authenticated by
/// the server's session key, as of `frames_seen` processed frames. Resuming
/// with it ([`Client::resume_session_with_token`](crate::Client::resume_session_with_token))
/// restores the session on a server that does not hold it (another replica
/// sharing the key, or the same server after a restart).
#[derive(Clone, PartialEq, Eq)]
pub struct SessionToken {
    /// The opaque bytes (about 4.5 kB).
    pub token: Vec<u8>,
    /// Frames processed in the state it holds.
    pub frames_seen: u64,
}

impl std::fmt::Debug for SessionToken {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "SessionToken {{ {} bytes, frames_seen: {} }}",
            self.token.len(),
            self.frames_seen
        )
    }
}

impl SessionInfo {
    pub(crate) fn from_proto(msg: pb::SessionOpened) -> Result<Self, ClientError> {
        let input_format = msg
            .input_format
            .as_ref()
            .ok_or_else(|| ClientError::Protocol("SessionOpened without input_format".into()))
            .and_then(input_format_from_proto)?;
        let model = ModelChoice::from_proto(msg.model)
            .ok_or_else(|| ClientError::Protocol(format!("unknown model {}", msg.model)))?;
        Ok(SessionInfo {
            session_id: msg.session_id,
            resumed: msg.resumed,
            frames_seen: msg.frames_seen,
            bone_lengths: optional_lengths(&msg.bone_lengths)?,
            input_format,
            model,
            ttl: Duration::from_millis(msg.session_ttl_ms),
            lifter: (!msg.lifter.is_empty()).then_some(msg.lifter),
            camera: msg
                .camera
                .as_ref()
                .map(CameraCalibration::from_proto)
                .transpose()?,
            token: (!msg.session_token.is_empty()).then_some(SessionToken {
                token: msg.session_token,
                frames_seen: msg.frames_seen,
            }),
            subject: msg.subject.as_ref().map(Subject::from_proto),
        })
    }
}

/// A session's final state, returned when it is closed.
#[derive(Debug, Clone, PartialEq)]
pub struct SessionSummary {
    /// The closed session (empty when closed through `CloseSession`, whose
    /// answer does not repeat it).
    pub session_id: String,
    /// Frames processed over the session's life.
    pub frames_seen: u64,
    /// Final estimate; `None` if no frame was processed.
    pub bone_lengths: Option<BoneLengths>,
}

impl SessionSummary {
    pub(crate) fn from_closed(msg: pb::SessionClosed) -> Result<Self, ClientError> {
        Ok(SessionSummary {
            bone_lengths: optional_lengths(&msg.bone_lengths)?,
            session_id: msg.session_id,
            frames_seen: msg.frames_seen,
        })
    }

    pub(crate) fn from_close_response(
        id: &str,
        msg: pb::CloseSessionResponse,
    ) -> Result<Self, ClientError> {
        Ok(SessionSummary {
            session_id: id.to_string(),
            frames_seen: msg.frames_seen,
            bone_lengths: optional_lengths(&msg.bone_lengths)?,
        })
    }
}

/// One loaded model, as the server describes it.
#[derive(Debug, Clone, PartialEq)]
pub struct ModelDescription {
    /// Which model (`None` if the server reports one this client does not know).
    pub model: Option<ModelChoice>,
    /// Human-readable name.
    pub name: String,
    /// Trainable parameters.
    pub parameter_count: u64,
    /// GRU hidden size.
    pub hidden_size: u32,
    /// "embedded" or the weights file path.
    pub weights_source: String,
    /// SHA-256 of the weights file.
    pub weights_sha256: String,
    /// Safetensors metadata.
    pub metadata: BTreeMap<String, String>,
    /// True: serves the sessions and requests that send a
    /// [`CameraCalibration`]; false: the others.
    pub camera_aware: bool,
}

/// The server's lifter (sessions may ask it to lift their poses).
#[derive(Debug, Clone, PartialEq)]
pub struct LifterDescription {
    /// Name, e.g. `videopose27-causal`.
    pub name: String,
    /// Frames in one input window.
    pub receptive_field: u32,
    /// Trainable parameters.
    pub parameter_count: u64,
    /// Whether the pose belongs to the window's last frame.
    pub causal: bool,
    /// The weights file path the server was started with.
    pub weights_source: String,
    /// SHA-256 of the weights file.
    pub weights_sha256: String,
    /// Training provenance and conventions from the weights file.
    pub metadata: BTreeMap<String, String>,
}

/// What the server runs and its limits.
#[derive(Debug, Clone, PartialEq)]
pub struct ModelInfo {
    /// Loaded models.
    pub models: Vec<ModelDescription>,
    /// Accepted keypoint layouts.
    pub layouts: Vec<KeypointLayout>,
    /// Server version.
    pub server_version: String,
    /// Protocol package.
    pub protocol: String,
    /// Joint names (Human3.6M order).
    pub joint_names: Vec<String>,
    /// Bone names (bone order).
    pub bone_names: Vec<String>,
    /// Maximum open sessions.
    pub max_sessions: u32,
    /// Detached-session TTL.
    pub session_ttl: Duration,
    /// Maximum frames per batched GRU step.
    pub max_batch: u32,
    /// Maximum request message size in bytes.
    pub max_message_bytes: u64,
    /// The server lifter, if the server runs one.
    pub lifter: Option<LifterDescription>,
    /// What frames and sessions may carry besides keypoints and poses, in
    /// words (empty from servers that predate it).
    pub accepts: Vec<String>,
}

impl ModelInfo {
    pub(crate) fn from_proto(msg: pb::ModelInfoResponse) -> Self {
        ModelInfo {
            models: msg
                .models
                .into_iter()
                .map(|m| ModelDescription {
                    model: ModelChoice::from_proto(m.model),
                    name: m.name,
                    parameter_count: m.parameter_count,
                    hidden_size: m.hidden_size,
                    weights_source: m.weights_source,
                    weights_sha256: m.weights_sha256,
                    metadata: m.metadata.into_iter().collect(),
                    camera_aware: m.camera_aware,
                })
                .collect(),
            layouts: msg
                .layouts
                .into_iter()
                .filter_map(layout_from_proto)
                .collect(),
            server_version: msg.server_version,
            protocol: msg.protocol,
            joint_names: msg.joint_names,
            bone_names: msg.bone_names,
            max_sessions: msg.max_sessions,
            session_ttl: Duration::from_millis(msg.session_ttl_ms),
            max_batch: msg.max_batch,
            max_message_bytes: msg.max_message_bytes,
            lifter: msg.lifter.map(|l| LifterDescription {
                name: l.name,
                receptive_field: l.receptive_field,
                parameter_count: l.parameter_count,
                causal: l.causal,
                weights_source: l.weights_source,
                weights_sha256: l.weights_sha256,
                metadata: l.metadata.into_iter().collect(),
            }),
            accepts: msg.accepts,
        }
    }
}

impl fmt::Display for ModelInfo {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(
            f,
            "server:       blapose-server {} ({})",
            self.server_version, self.protocol
        )?;
        let layouts: Vec<&str> = self.layouts.iter().map(|l| l.name()).collect();
        writeln!(f, "layouts:      {}", layouts.join(", "))?;
        for (i, line) in self.accepts.iter().enumerate() {
            let head = if i == 0 { "accepts:" } else { "" };
            writeln!(f, "{head:<14}{line}")?;
        }
        writeln!(
            f,
            "limits:       {} sessions, session TTL {:.1} s, batch {}, message {} bytes",
            self.max_sessions,
            self.session_ttl.as_secs_f64(),
            self.max_batch,
            self.max_message_bytes
        )?;
        for m in &self.models {
            let kind = m.model.map_or("unknown", |k| k.as_str());
            let family = if m.camera_aware {
                " (camera-aware)"
            } else {
                ""
            };
            writeln!(f, "model {kind}{family}:")?;
            writeln!(f, "  name:       {}", m.name)?;
            writeln!(
                f,
                "  camera:     {}",
                if m.camera_aware {
                    "aware (serves sessions and requests that send a camera calibration)"
                } else {
                    "default (serves sessions and requests without a camera calibration)"
                }
            )?;
            writeln!(f, "  parameters: {}", m.parameter_count)?;
            writeln!(f, "  hidden:     {}", m.hidden_size)?;
            writeln!(
                f,
                "  weights:    {} (sha256 {})",
                m.weights_source, m.weights_sha256
            )?;
            for (k, v) in &m.metadata {
                writeln!(f, "  {k}: {v}")?;
            }
        }
        match &self.lifter {
            None => writeln!(f, "lifter:       none (clients send their 3D poses)")?,
            Some(l) => {
                writeln!(
                    f,
                    "lifter:       {} (sessions may send 2D keypoints only)",
                    l.name
                )?;
                writeln!(
                    f,
                    "  frames:     {}{}",
                    l.receptive_field,
                    if l.causal { ", causal" } else { "" }
                )?;
                writeln!(f, "  parameters: {}", l.parameter_count)?;
                writeln!(
                    f,
                    "  weights:    {} (sha256 {})",
                    l.weights_source, l.weights_sha256
                )?;
                for (k, v) in &l.metadata {
                    writeln!(f, "  {k}: {v}")?;
                }
            }
        }
        Ok(())
    }
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

fn optional_lengths(values: &[f32]) -> Result<Option<BoneLengths>, ClientError> {
    if values.is_empty() {
        Ok(None)
    } else {
        lengths_from_flat(values, "bone_lengths").map(Some)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use blapose_core::NUM_JOINTS;

    #[test]
    fn layout_codes_are_the_wire_numbers() {
        assert_eq!(layout_code(KeypointLayout::H36m17), 1);
        assert_eq!(layout_code(KeypointLayout::Sh16), 2);
        assert_eq!(layout_code(KeypointLayout::Coco17), 3);
        for l in KeypointLayout::ALL {
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

    fn calibration() -> CameraCalibration {
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
        assert_eq!(CameraCalibration::from_proto(&msg).unwrap(), c);
        let no_size = CameraCalibration {
            image_size: None,
            ..c
        };
        assert_eq!(no_size.to_proto().image_size, None);
        assert_eq!(
            CameraCalibration::from_proto(&no_size.to_proto()).unwrap(),
            no_size
        );
        for up in [vec![], vec![0.0, -1.0], vec![0.0, -1.0, 0.0, 1.0]] {
            let msg = pb::CameraCalibration { up, ..msg.clone() };
            let err = CameraCalibration::from_proto(&msg).unwrap_err();
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
        let back = CameraCalibration::from_proto(&msg).unwrap();
        assert_eq!(back.height, Some(1.75));
        // Not given: 0 on the wire, None again when read back.
        let unknown = CameraCalibration { height: None, ..c };
        let msg = unknown.to_proto();
        assert_eq!(msg.height, 0.0);
        assert_eq!(
            CameraCalibration::from_proto(&msg).unwrap(),
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
        assert_eq!(CameraCalibration::from_proto(&old).unwrap().height, None);
        // Any other value is kept for validate to judge.
        let odd = pb::CameraCalibration {
            height: 50.0,
            ..c.to_proto()
        };
        assert_eq!(
            CameraCalibration::from_proto(&odd).unwrap().height,
            Some(50.0)
        );
    }

    #[test]
    fn camera_height_is_checked_and_named() {
        let c = calibration();
        for ok in [
            None,
            Some(MIN_CAMERA_HEIGHT),
            Some(1.4),
            Some(MAX_CAMERA_HEIGHT),
        ] {
            CameraCalibration { height: ok, ..c }
                .validate()
                .unwrap_or_else(|e| panic!("{ok:?}: {e}"));
        }
        for bad in [
            f32::NAN,
            f32::INFINITY,
            f32::NEG_INFINITY,
            0.1,
            50.0,
            0.0,
            -1.4,
            0.29,
            10.01,
        ] {
            let cal = CameraCalibration {
                height: Some(bad),
                ..c
            };
            let err = cal.validate().unwrap_err();
            assert_eq!(err.field(), "height", "{bad}: {err}");
            assert!(err.to_string().contains("height"), "{err}");
            if bad.is_finite() {
                assert_eq!(err, CameraError::Height(bad));
            } else {
                assert_eq!(err, CameraError::NonFinite { field: "height" });
            }
            // validate_for checks it too.
            assert_eq!(cal.validate_for(Coordinates::Normalized).unwrap_err(), err);
        }
    }

    #[test]
    fn camera_display_shows_the_height_when_given() {
        let c = calibration();
        let text = c.to_string();
        assert!(text.ends_with(", image 1000x1002, height 1.75 m"), "{text}");
        let text = CameraCalibration { height: None, ..c }.to_string();
        assert!(!text.contains("height"), "{text}");
        assert!(text.ends_with(", image 1000x1002"), "{text}");
    }

    #[test]
    fn camera_values_are_checked_and_the_field_named() {
        let c = calibration();
        c.validate().unwrap();
        let cases = [
            (
                CameraCalibration {
                    focal: [0.0, 1000.0],
                    ..c
                },
                "focal",
            ),
            (
                CameraCalibration {
                    focal: [1000.0, -3.0],
                    ..c
                },
                "focal",
            ),
            (
                CameraCalibration {
                    focal: [f32::NAN, 1000.0],
                    ..c
                },
                "focal",
            ),
            (
                CameraCalibration {
                    up: [0.0, f32::INFINITY, 0.0],
                    ..c
                },
                "up",
            ),
            (CameraCalibration { up: [0.0; 3], ..c }, "up"),
            (
                CameraCalibration {
                    principal: [500.0, f32::NEG_INFINITY],
                    ..c
                },
                "principal",
            ),
            (
                CameraCalibration {
                    image_size: Some((0, 1000)),
                    ..c
                },
                "image_size",
            ),
        ];
        for (bad, field) in cases {
            let err = bad.validate().unwrap_err();
            assert_eq!(err.field(), field, "{bad:?}: {err}");
            assert!(err.to_string().contains(field), "{err}");
        }
        // The image size against the keypoints' coordinates.
        c.validate_for(Coordinates::Pixels {
            width: 1000,
            height: 1002,
        })
        .unwrap();
        c.validate_for(Coordinates::Normalized).unwrap();
        assert!(matches!(
            c.validate_for(Coordinates::Pixels {
                width: 1002,
                height: 1000
            }),
            Err(CameraError::ImageSizeMismatch { .. })
        ));
        let no_size = CameraCalibration {
            image_size: None,
            ..c
        };
        no_size
            .validate_for(Coordinates::Pixels {
                width: 640,
                height: 480,
            })
            .unwrap();
        assert_eq!(
            no_size.validate_for(Coordinates::Normalized),
            Err(CameraError::ImageSizeMissing)
        );
    }

    #[test]
    fn calibration_from_a_camera_takes_the_third_column_as_up() {
        // Looking along world +y, tilted 10 degrees down: R is not
        // symmetric, so a row would give a different vector.
        let (s, c) = 10f64.to_radians().sin_cos();
        let forward = [0.0, c, -s];
        let right = [1.0, 0.0, 0.0];
        let down = [0.0, -s, -c];
        let camera = Camera {
            id: "t".into(),
            rotation: [right, down, forward],
            center: [0.0, -5.0, 1.4],
            focal: [1150.0, 1149.0],
            principal: [500.0, 499.0],
            radial: [0.0; 3],
            tangential: [0.0; 2],
            width: 1000,
            height: 998,
        };
        camera.validate().unwrap();
        let cal = CameraCalibration::from_camera(&camera);
        // World up (0, 0, 1) as a direction in camera coordinates.
        let a = camera.world_to_camera([0.3, 0.2, 1.0]);
        let b = camera.world_to_camera([0.3, 0.2, 2.0]);
        for k in 0..3 {
            assert!(
                (f64::from(cal.up[k]) - (b[k] - a[k])).abs() < 1e-6,
                "{:?} vs {:?}",
                cal.up,
                [b[0] - a[0], b[1] - a[1], b[2] - a[2]]
            );
        }
        assert!(cal.up[1] < 0.0, "up points to smaller image y");
        assert_eq!(cal.focal, [1150.0, 1149.0]);
        assert_eq!(cal.principal, [500.0, 499.0]);
        assert_eq!(cal.image_size, Some((1000, 998)));
        // World z up with the floor at z = 0: the centre's z.
        assert_eq!(cal.height, Some(1.4));
        let high = Camera {
            center: [0.0, -5.0, 3.25],
            ..camera.clone()
        };
        assert_eq!(CameraCalibration::from_camera(&high).height, Some(3.25));
        cal.validate().unwrap();
    }

    #[test]
    fn session_info_and_model_info_carry_the_camera_family() {
        let opened = pb::SessionOpened {
            session_id: "ab".into(),
            input_format: Some(InputFormat::pixels(KeypointLayout::H36m17, 1000, 1002).into()),
            model: pb::Model::OnlineGru as i32,
            ..Default::default()
        };
        assert_eq!(
            SessionInfo::from_proto(opened.clone()).unwrap().camera,
            None
        );
        let with_camera = pb::SessionOpened {
            camera: Some(calibration().to_proto()),
            ..opened.clone()
        };
        assert_eq!(
            SessionInfo::from_proto(with_camera).unwrap().camera,
            Some(calibration())
        );
        let broken = pb::SessionOpened {
            camera: Some(pb::CameraCalibration::default()),
            ..opened
        };
        assert!(matches!(
            SessionInfo::from_proto(broken),
            Err(ClientError::Protocol(_))
        ));

        let model = |camera_aware| pb::ModelDescription {
            model: pb::Model::OnlineGru as i32,
            name: "bone_length_gru".into(),
            camera_aware,
            ..Default::default()
        };
        let info = ModelInfo::from_proto(pb::ModelInfoResponse {
            models: vec![model(false), model(true)],
            ..Default::default()
        });
        let aware: Vec<bool> = info.models.iter().map(|m| m.camera_aware).collect();
        assert_eq!(aware, [false, true]);
        let text = info.to_string();
        assert!(text.contains("model gru:"), "{text}");
        assert!(text.contains("model gru (camera-aware):"), "{text}");
        assert_eq!(text.matches("camera:     aware").count(), 1, "{text}");
        assert_eq!(text.matches("camera:     default").count(), 1, "{text}");
    }

    #[test]
    fn model_names_parse() {
        assert_eq!(
            "bigru".parse::<ModelChoice>().unwrap(),
            ModelChoice::OfflineBiGru
        );
        assert_eq!(
            "GRU".parse::<ModelChoice>().unwrap(),
            ModelChoice::OnlineGru
        );
        assert!("lstm".parse::<ModelChoice>().is_err());
    }
}

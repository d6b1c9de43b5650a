//! Typed mirrors of the wire messages.
//!
//! The generated protobuf types carry flat `Vec<f32>`s and bare `i32` enum
//! numbers; callers of the library should instead see poses as
//! [`blapose_core::Pose`] and layouts as an enum, with the conversion (and
//! its validation) done once, here. A server answer whose arrays have the
//! wrong length is a protocol violation, reported as such rather than
//! turning into a panic or a silently truncated pose.

use std::collections::BTreeMap;
use std::fmt;
use std::str::FromStr;
use std::time::Duration;

use blapose_core::skeleton::{NUM_BONES, NUM_JOINTS};
use blapose_core::{BoneLengths, Pose};
use blapose_proto::v1 as pb;

use crate::error::ClientError;

pub use blapose_core::layouts::KeypointLayout;

/// The wire enum of a keypoint layout.
pub const fn layout_to_proto(layout: KeypointLayout) -> pb::KeypointLayout {
    match layout {
        KeypointLayout::H36m17 => pb::KeypointLayout::H36m17,
        KeypointLayout::Sh16 => pb::KeypointLayout::Sh16,
        KeypointLayout::Coco17 => pb::KeypointLayout::Coco17,
    }
}

/// The layout with this wire number (`KeypointLayout` value); `None` for
/// UNSPECIFIED and numbers this client does not know.
pub fn layout_from_proto(value: i32) -> Option<KeypointLayout> {
    KeypointLayout::ALL
        .into_iter()
        .find(|l| layout_to_proto(*l) as i32 == value)
}

/// The code a replay file stores in its `layout` array: the wire number
/// (1 = H36M-17, 2 = SH-16, 3 = COCO-17).
pub const fn layout_code(layout: KeypointLayout) -> u32 {
    layout_to_proto(layout) as u32
}

/// The layout a replay file's `layout` code names.
pub fn layout_from_code(code: u32) -> Option<KeypointLayout> {
    i32::try_from(code).ok().and_then(layout_from_proto)
}

/// How keypoints are expressed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Coordinates {
    /// Pixels of an image of this size; the server normalizes.
    Pixels {
        /// Image width in pixels.
        width: u32,
        /// Image height in pixels.
        height: u32,
    },
    /// Already normalized screen coordinates (`x/w*2-1`, `y/w*2-h/w`).
    Normalized,
}

/// Layout plus coordinate convention of a session's (or a sequence's)
/// keypoints.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct InputFormat {
    /// Joint order.
    pub layout: KeypointLayout,
    /// Pixels or normalized coordinates.
    pub coordinates: Coordinates,
}

impl InputFormat {
    /// Pixel keypoints of an image `width` x `height`.
    pub const fn pixels(layout: KeypointLayout, width: u32, height: u32) -> Self {
        InputFormat {
            layout,
            coordinates: Coordinates::Pixels { width, height },
        }
    }

    /// The wire message.
    pub fn to_proto(self) -> pb::InputFormat {
        let coordinates = match self.coordinates {
            Coordinates::Pixels { width, height } => {
                pb::input_format::Coordinates::ImageSize(pb::ImageSize { width, height })
            }
            Coordinates::Normalized => pb::input_format::Coordinates::Normalized(true),
        };
        pb::InputFormat {
            layout: layout_to_proto(self.layout) as i32,
            coordinates: Some(coordinates),
        }
    }

    /// Parse the wire message (as echoed by the server).
    pub fn from_proto(msg: &pb::InputFormat) -> Result<Self, ClientError> {
        let layout = layout_from_proto(msg.layout).ok_or_else(|| {
            ClientError::Protocol(format!("unknown keypoint layout {}", msg.layout))
        })?;
        let coordinates = match msg.coordinates {
            Some(pb::input_format::Coordinates::ImageSize(s)) => Coordinates::Pixels {
                width: s.width,
                height: s.height,
            },
            Some(pb::input_format::Coordinates::Normalized(_)) => Coordinates::Normalized,
            None => {
                return Err(ClientError::Protocol(
                    "input format without coordinates".into(),
                ))
            }
        };
        Ok(InputFormat {
            layout,
            coordinates,
        })
    }
}

/// Which bone-length model adjusts the poses.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum ModelChoice {
    /// The causal online GRU (streams; also offline, giving exactly what a
    /// stream would).
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
}

impl SessionInfo {
    pub(crate) fn from_proto(msg: pb::SessionOpened) -> Result<Self, ClientError> {
        let input_format = msg
            .input_format
            .as_ref()
            .ok_or_else(|| ClientError::Protocol("SessionOpened without input_format".into()))
            .and_then(InputFormat::from_proto)?;
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
            writeln!(f, "model {kind}:")?;
            writeln!(f, "  name:       {}", m.name)?;
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
    if values.len() != NUM_JOINTS * 3 {
        return Err(ClientError::Protocol(format!(
            "{what} has {} values, expected {}",
            values.len(),
            NUM_JOINTS * 3
        )));
    }
    Ok(std::array::from_fn(|j| {
        [values[3 * j], values[3 * j + 1], values[3 * j + 2]]
    }))
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
            assert_eq!(InputFormat::from_proto(&f.to_proto()).unwrap(), f);
        }
        let bad = pb::InputFormat {
            layout: 0,
            coordinates: None,
        };
        assert!(matches!(
            InputFormat::from_proto(&bad),
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

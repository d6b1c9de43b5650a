//! What the server runs: its models, lifter, layouts and limits
//! (`ModelInfo`), and the summary `blapose-client info` prints.

use std::collections::BTreeMap;
use std::fmt;
use std::time::Duration;

use blapose_core::layouts::KeypointLayout;
use blapose_core::ModelKind;
use blapose_proto::convert::{layout_from_proto, model_from_proto};
use blapose_proto::v1 as pb;

/// One loaded model, as the server describes it.
#[derive(Debug, Clone, PartialEq)]
pub struct ModelDescription {
    /// Which model (`None` if the server reports one this client does not know).
    pub model: Option<ModelKind>,
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
    /// [`CameraCalibration`](crate::CameraCalibration); false: the others.
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
                    model: model_from_proto(m.model),
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn model_info_carries_the_camera_family() {
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
        assert_eq!(info.models[0].model, Some(ModelKind::Gru));
        let text = info.to_string();
        assert!(text.contains("model gru:"), "{text}");
        assert!(text.contains("model gru (camera-aware):"), "{text}");
        assert_eq!(text.matches("camera:     aware").count(), 1, "{text}");
        assert_eq!(text.matches("camera:     default").count(), 1, "{text}");
        let unknown = ModelInfo::from_proto(pb::ModelInfoResponse {
            models: vec![pb::ModelDescription {
                model: 0,
                ..model(false)
            }],
            ..Default::default()
        });
        assert_eq!(unknown.models[0].model, None);
        assert!(unknown.to_string().contains("model unknown:"));
    }
}

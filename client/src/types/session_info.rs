//! What the server says about a session: when it opens or resumes, in its
//! tokens, and when it closes.

use std::time::Duration;

use blapose_core::layouts::InputFormat;
use blapose_core::{BoneLengths, ModelKind};
use blapose_data::replay::{CameraCalibration, Subject};
use blapose_proto::v1 as pb;

use super::wire::{
    camera_from_proto, input_format_from_proto, model_from_answer, optional_lengths,
    subject_from_proto,
};
use crate::error::ClientError;

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
    pub model: ModelKind,
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
        let model = model_from_answer(msg.model)?;
        Ok(SessionInfo {
            session_id: msg.session_id,
            resumed: msg.resumed,
            frames_seen: msg.frames_seen,
            bone_lengths: optional_lengths(&msg.bone_lengths)?,
            input_format,
            model,
            ttl: Duration::from_millis(msg.session_ttl_ms),
            lifter: (!msg.lifter.is_empty()).then_some(msg.lifter),
            camera: msg.camera.as_ref().map(camera_from_proto).transpose()?,
            token: (!msg.session_token.is_empty()).then_some(SessionToken {
                token: msg.session_token,
                frames_seen: msg.frames_seen,
            }),
            subject: msg.subject.as_ref().map(subject_from_proto),
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::types::wire::tests::calibration;
    use crate::types::wire::ToProto;
    use blapose_core::layouts::KeypointLayout;

    #[test]
    fn session_info_carries_the_camera_family() {
        let opened = pb::SessionOpened {
            session_id: "ab".into(),
            input_format: Some(InputFormat::pixels(KeypointLayout::H36m17, 1000, 1002).into()),
            model: pb::Model::OnlineGru as i32,
            ..Default::default()
        };
        let info = SessionInfo::from_proto(opened.clone()).unwrap();
        assert_eq!((info.camera, info.model), (None, ModelKind::Gru));
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
            ..opened.clone()
        };
        assert!(matches!(
            SessionInfo::from_proto(broken),
            Err(ClientError::Protocol(_))
        ));
        let unspecified = pb::SessionOpened {
            model: pb::Model::Unspecified as i32,
            ..opened
        };
        assert!(matches!(
            SessionInfo::from_proto(unspecified),
            Err(ClientError::Protocol(m)) if m == "unknown model 0"
        ));
    }
}

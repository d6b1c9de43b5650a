//! A stream's attachment to its session: the first message opens a
//! session, resumes one this server holds, or restores one from a session
//! token (any replica's); and the tokens the stream sends of it.
//!
//! Apart from the frame loop ([`crate::stream`]) because none of it runs
//! per frame: it is the checks a session's configuration goes through
//! once (input format, model, server lifter, camera, subject, and for a
//! token its authenticity, age, weights and lifter), and what the stream's
//! `SessionOpened` says.

use blapose_proto::v1 as pb;
use pb::stream_request::Kind as Req;
use pb::stream_response::Kind as Resp;
use tonic::Status;

use crate::answer;
use crate::metrics;
use crate::motion::{self, SessionMotion};
use crate::quota::ClientId;
use crate::restore_check;
use crate::session::{
    Attachment, Session, SessionConfig, SessionError, SessionSnapshot, StateCopy, TokenStamp,
    MAX_LABEL_BYTES,
};
use crate::state::AppState;
use crate::token::{PortableMotion, PortableState};
use crate::validate;

/// The attachment, and whether the client asked for periodic session
/// tokens.
pub fn open_or_resume(
    state: &AppState,
    client: ClientId,
    first: Result<Option<pb::StreamRequest>, Status>,
) -> Result<(Attachment, bool), Status> {
    let request = match first {
        Ok(Some(r)) => r,
        Ok(None) => {
            return Err(Status::failed_precondition(
                "the stream ended before an open or resume request",
            ))
        }
        Err(status) => return Err(status),
    };
    match request.kind {
        Some(Req::Open(open)) => {
            let input =
                validate::input_format(open.input_format.as_ref()).map_err(|e| e.to_status())?;
            validate::stream_model(open.model).map_err(|e| e.to_status())?;
            let lifter_frames = if open.server_lifter {
                let lifter = state
                    .lifter
                    .as_ref()
                    .ok_or_else(|| validate::InvalidInput::NoServerLifter.to_status())?;
                Some(lifter.lifter.receptive_field())
            } else {
                None
            };
            let camera =
                validate::camera(open.camera.as_ref(), &input, state.camera_models().as_ref())
                    .map_err(|e| e.to_status())?;
            let subject = validate::subject(open.subject.as_ref())
                .map_err(|e| e.to_status())?
                .map(|s| answer::subject(s, &state.stature));
            let motion = motion::options(open.motion.as_ref())?
                .map(|rate| SessionMotion::new(rate, &input, camera.as_ref().map(|c| &c.view)));
            let label = truncate_label(&open.client_label);
            state
                .budget
                .admit(crate::budget::SESSION_BYTES)
                .map_err(|e| e.to_status())?;
            let attachment = state
                .store
                .open_for(
                    SessionConfig {
                        input,
                        label,
                        lifter_frames,
                        camera,
                        subject,
                        motion,
                    },
                    client,
                    state.limits.sessions_per_client,
                )
                .map_err(session_status)?;
            tracing::info!(
                session = %attachment.session.id(),
                label = %attachment.session.config().label,
                layout = %input.layout,
                server_lifter = open.server_lifter,
                camera = open.camera.is_some(),
                subject = open.subject.is_some(),
                motion = motion.is_some(),
                "session opened"
            );
            Ok((attachment, open.session_tokens))
        }
        Some(Req::Resume(resume)) => {
            // With a token (and a key) the token names the state to continue
            // from, held here or not; without one, the held state.
            let attachment = if !resume.session_token.is_empty() && state.tokens.is_some() {
                restore(state, client, &resume)?
            } else {
                match state.store.resume(&resume.session_id) {
                    Ok(a) => a,
                    Err(SessionError::NotFound { .. }) if !resume.session_token.is_empty() => {
                        restore(state, client, &resume)?
                    }
                    Err(e) => return Err(session_status(e)),
                }
            };
            tracing::info!(session = %attachment.session.id(), frames_seen = attachment.snapshot.frames_seen, "session resumed");
            Ok((attachment, resume.session_tokens))
        }
        Some(Req::TokenRequest(_)) => Err(Status::failed_precondition(
            "a token request arrived before the session was opened: send open or resume first",
        )),
        Some(Req::Frame(_)) => Err(Status::failed_precondition(
            "a frame arrived before the session was opened: send open or resume first",
        )),
        Some(Req::Close(_)) => Err(Status::failed_precondition(
            "close arrived before the session was opened: send open or resume first",
        )),
        None => Err(Status::invalid_argument(
            "empty StreamRequest: set open, resume, frame or close",
        )),
    }
}

/// Restore a session this server does not hold from the resume's token.
fn restore(
    state: &AppState,
    client: ClientId,
    resume: &pb::ResumeSession,
) -> Result<Attachment, Status> {
    let tokens = state.tokens.as_ref().ok_or_else(|| {
        Status::failed_precondition(format!(
            "no session {:?} on this server, and it has no session key (--session-key), so it \
             cannot restore sessions from tokens",
            truncate_label(&resume.session_id)
        ))
    })?;
    state
        .budget
        .admit(crate::budget::SESSION_BYTES)
        .map_err(|e| e.to_status())?;
    let portable =
        PortableState::open(&resume.session_token, &tokens.key).map_err(|e| e.to_status())?;
    // Authentic is not the same as sane: check it like input.
    restore_check::check(&portable, crate::token::now_ms(), state.limits.token_ttl).map_err(
        |e| {
            if matches!(e, restore_check::RestoreError::Expired { .. }) {
                metrics::limited("token_ttl");
            }
            e.to_status()
        },
    )?;
    if !portable
        .session_id
        .to_string()
        .eq_ignore_ascii_case(&resume.session_id)
    {
        return Err(Status::invalid_argument(format!(
            "the session token is for session {}, not {:?}",
            portable.session_id,
            truncate_label(&resume.session_id)
        )));
    }
    let camera = validate::camera(
        portable.camera.as_ref(),
        &portable.input,
        state.camera_models().as_ref(),
    )
    .map_err(|e| {
        Status::failed_precondition(format!(
            "the session token's camera calibration cannot be served here: {e}"
        ))
    })?;
    let subject = validate::subject(portable.subject.as_ref())
        .map_err(|e| {
            Status::failed_precondition(format!(
                "the session token's subject cannot be served here: {e}"
            ))
        })?
        .map(|s| answer::subject(s, &state.stature));
    let served = tokens.weights_for(camera.is_some());
    if served != Some(portable.weights_id) {
        return Err(Status::failed_precondition(format!(
            "the session token was made for other weights (online GRU sha256 {}) than this \
             server runs ({}): its state would not continue the same model",
            hex(&portable.weights_id),
            served.map_or_else(|| "none".to_string(), |w| hex(&w)),
        )));
    }
    let lifter_frames =
        match (&portable.window, tokens.lifter) {
            (None, _) => None,
            (Some(w), Some((id, frames))) if w.lifter_id == id && w.receptive_field == frames => {
                Some(frames)
            }
            (Some(w), Some(_)) => {
                return Err(Status::failed_precondition(format!(
                    "the session token was made for another server lifter (sha256 {}) than this \
                 server runs",
                    hex(&w.lifter_id)
                )))
            }
            (Some(_), None) => return Err(Status::failed_precondition(
                "the session token is for a server_lifter session, and this server runs no lifter",
            )),
        };
    let motion = match &portable.motion {
        Some(m) => {
            let rate = motion::frame_rate(m.rate_hz as f32).map_err(|e| {
                Status::failed_precondition(format!(
                    "the session token's motion stage cannot be served here: {}",
                    e.message()
                ))
            })?;
            Some(SessionMotion::new(
                rate,
                &portable.input,
                camera.as_ref().map(|c| &c.view),
            ))
        }
        None => None,
    };
    let id = portable.session_id;
    let origin_ms = portable.expiry_origin_ms();
    let stamp = TokenStamp {
        issued_ms: portable.issued_at_ms,
        owner: portable.owner.map(ClientId::from_bytes),
    };
    let config = SessionConfig {
        input: portable.input,
        label: truncate_label(&portable.label),
        lifter_frames,
        camera,
        subject,
        motion,
    };
    let copy = StateCopy {
        hidden: portable.hidden.into_boxed_slice(),
        lengths: portable.lengths,
        window: portable.window.map(|w| w.frames),
        held: portable.held,
        skipped: portable.skipped,
        motion: portable.motion.map(|m| m.state),
        // Its tokens expire with the one it came from, whatever chain of
        // restores follows.
        origin_ms: Some(origin_ms),
    };
    let attachment = state
        .store
        .restore(
            id,
            config,
            copy,
            client,
            state.limits.sessions_per_client,
            stamp,
        )
        .map_err(session_status)?;
    tracing::info!(session = %id, frames_seen = attachment.snapshot.frames_seen, "session restored from a token");
    Ok(attachment)
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// A token for `copy` of `session`'s state, with the frames it has seen;
/// `None` on a server without a key.
pub fn seal(state: &AppState, session: &Session, copy: StateCopy) -> Option<(Vec<u8>, u64)> {
    let tokens = state.tokens.as_ref()?;
    let config = session.config();
    let weights = tokens.weights_for(config.camera.is_some())?;
    let lifter = if config.lifting() {
        tokens.lifter
    } else {
        None
    };
    let frames_seen = copy.frames_seen();
    let motion_state = copy.motion.clone();
    let mut portable = PortableState::new(
        session.id(),
        weights,
        config.input,
        &config.label,
        config.camera.as_ref().map(|c| &c.calibration),
        lifter,
        copy,
    );
    portable.subject = config.subject.as_ref().map(|s| s.subject);
    portable.owner = Some(*session.client().as_bytes());
    portable.motion = match (&config.motion, motion_state) {
        (Some(m), Some(state)) => Some(PortableMotion {
            rate_hz: m.rate_hz,
            state,
        }),
        _ => None,
    };
    {
        let mut st = session.lock();
        st.newest_token = st.newest_token.max(frames_seen);
    }
    Some((portable.seal(&tokens.key), frames_seen))
}

pub fn token_response((token, frames_seen): (Vec<u8>, u64)) -> pb::StreamResponse {
    pb::StreamResponse {
        kind: Some(Resp::Token(pb::SessionToken { token, frames_seen })),
    }
}

/// The gRPC status for a store error.
pub fn session_status(e: SessionError) -> Status {
    match e {
        SessionError::TooManySessions { .. } | SessionError::Quota(_) => {
            Status::resource_exhausted(e.to_string())
        }
        SessionError::Closed { .. }
        | SessionError::Rollback { .. }
        | SessionError::Forgotten { .. } => Status::failed_precondition(e.to_string()),
        SessionError::NotFound { .. } => Status::not_found(e.to_string()),
        SessionError::Rng(_) => Status::internal(e.to_string()),
        SessionError::Restore(_) => Status::failed_precondition(e.to_string()),
    }
}

fn truncate_label(label: &str) -> String {
    let mut end = label.len().min(MAX_LABEL_BYTES);
    while !label.is_char_boundary(end) {
        end -= 1;
    }
    // Labels go into logs: keep them on one line.
    label[..end]
        .chars()
        .map(|c| if c.is_control() { ' ' } else { c })
        .collect()
}

pub fn opened_response(state: &AppState, a: &Attachment) -> pb::StreamResponse {
    // The state at attach time: frames of older epochs are refused from
    // now on and this stream has sent none yet.
    let session_token = if state.tokens.is_some() {
        let copy = a.session.lock().copy_state();
        seal(state, &a.session, copy)
            .map(|t| t.0)
            .unwrap_or_default()
    } else {
        Vec::new()
    };
    pb::StreamResponse {
        kind: Some(Resp::Opened(pb::SessionOpened {
            session_id: a.session.id().to_string(),
            resumed: a.epoch > 1,
            frames_seen: a.snapshot.frames_seen,
            bone_lengths: lengths_vec(&a.snapshot),
            input_format: Some(validate::input_format_to_proto(&a.session.config().input)),
            model: pb::Model::OnlineGru as i32,
            session_ttl_ms: u64::try_from(state.store.ttl().as_millis()).unwrap_or(u64::MAX),
            lifter: session_lifter(state, a).to_string(),
            camera: a
                .session
                .config()
                .camera
                .as_ref()
                .map(|c| c.calibration.clone()),
            session_token,
            subject: a.session.config().subject.as_ref().map(|s| s.subject),
            motion: a
                .session
                .config()
                .motion
                .as_ref()
                .map(SessionMotion::to_proto),
        })),
    }
}

/// The name of the lifter lifting this session's poses; empty when the
/// client sends them.
pub fn session_lifter<'a>(state: &'a AppState, a: &Attachment) -> &'a str {
    match &state.lifter {
        Some(l) if a.session.config().lifting() => l.name(),
        _ => "",
    }
}

pub fn lengths_vec(s: &SessionSnapshot) -> Vec<f32> {
    s.bone_lengths.map(|l| l.to_vec()).unwrap_or_default()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn labels_are_bounded_and_single_line() {
        assert_eq!(truncate_label("cam 1\nrm -rf"), "cam 1 rm -rf");
        let long = "é".repeat(200);
        let t = truncate_label(&long);
        assert!(t.len() <= MAX_LABEL_BYTES);
        assert!(t.chars().all(|c| c == 'é'));
    }

    #[test]
    fn store_errors_map_to_grpc_codes() {
        assert_eq!(
            session_status(SessionError::TooManySessions { max: 1 }).code(),
            tonic::Code::ResourceExhausted
        );
        assert_eq!(
            session_status(SessionError::NotFound { id: "x".into() }).code(),
            tonic::Code::NotFound
        );
    }
}

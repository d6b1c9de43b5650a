//! The answer stage: what a frame's model output becomes, from the
//! session's state to the message the client reads.
//!
//! A finite step result is committed to its session under one lock (GRU
//! state, held joints, lifter window, the running mean of the per-frame
//! predictions, and a copy of that state when a session token is due), so a
//! frame refused anywhere before this point leaves the session as it was.
//! The lengths a session answers with are its running estimate, or its
//! subject's stature-regression lengths ([`subject`]); the pose is the
//! client's (or the server lifter's) rebuilt with them, root kept.
//! `AdjustSequence` answers through the same rules ([`adjust_frames`],
//! [`sequence_response`]), so a whole sequence and a stream of the same
//! frames agree.

use std::time::Instant;

use blapose_core::bones::{self, ZeroBonePolicy};
use blapose_core::{BoneLengths, ModelKind, Pose};
use blapose_model::stature::StatureModel;
use blapose_proto::v1 as pb;
use pb::stream_response::Kind as Resp;
use tokio::sync::oneshot;
use tonic::Status;

use crate::backend::OUTPUT_DIM;
use crate::frame::{FrameJob, StepError, StepOutput, StepResult};
use crate::metrics;
use crate::session::{SessionState, SessionSubject, StateCopy};
use crate::validate::ValidSubject;

/// A validated subject with the lengths the stature model gives them,
/// which its session or request answers with.
pub fn subject(valid: ValidSubject, model: &StatureModel) -> SessionSubject {
    SessionSubject {
        subject: valid.subject,
        lengths: model.predict(valid.subject.height_m, valid.sex),
    }
}

/// The state copy a job asked for, if this frame makes it due.
fn due_state(job: &FrameJob, st: &SessionState, frames_seen: u64) -> Option<Box<StateCopy>> {
    (job.state_every > 0 && frames_seen.is_multiple_of(job.state_every))
        .then(|| Box::new(st.copy_state()))
}

/// Answer a frame without a detected joint (`st`: its session's state,
/// locked, owned by the frame's stream): it counts among the frames seen
/// and changes nothing else.
pub fn skipped(job: &FrameJob, st: &mut SessionState) -> StepOutput {
    st.skipped += 1;
    let frames_seen = st.frames_seen();
    StepOutput {
        lengths: job.session.config().served(st.estimate()),
        frames_seen,
        lifted: None,
        state: due_state(job, st, frames_seen),
        motion: None,
    }
}

/// Write one successful row back and answer it: the GRU state, the held
/// joints, for a lifting frame the frame into the lifter's window, and the
/// prediction into the running estimate, all under one lock.
pub fn commit(job: &FrameJob, hidden: &[f32], lengths: &[f32], lifted: Option<Pose>) -> StepResult {
    if !hidden.iter().chain(lengths).all(|v| v.is_finite()) {
        return Err(StepError::NonFinite);
    }
    if job.lift && lifted.is_none() {
        return Err(StepError::Lifter("the frame was not lifted".into()));
    }
    let mut st = job.session.lock();
    if !st.accepts(job.epoch) {
        return Err(StepError::Superseded);
    }
    if job.lift && st.window.is_none() {
        return Err(StepError::Lifter("the session has no lifter window".into()));
    }
    let mut prediction = [0.0f32; OUTPUT_DIM];
    prediction.copy_from_slice(lengths);
    let mut running = st.lengths;
    let estimate = running.push(&prediction);
    let served = job.session.config().served(Some(estimate));
    // The motion stage first: it is the one step here that can fail, and
    // a failed frame must leave the session as it was.
    let motion = match (&job.session.config().motion, &mut st.motion) {
        (Some(settings), Some(stage)) => {
            let pose = job.pose.or(lifted).ok_or_else(|| {
                StepError::Motion("the frame has neither a client pose nor a lifted one".into())
            })?;
            let served = served.unwrap_or(estimate);
            let adjusted =
                bones::adjust_pose(&pose, &served).map_err(|e| StepError::Motion(e.to_string()))?;
            Some(
                settings
                    .frame(stage, &adjusted, &served, &job.input, &job.present)
                    .map_err(|e| StepError::Motion(e.to_string()))?,
            )
        }
        _ => None,
    };
    if job.lift {
        if let Some(window) = st.window.as_deref_mut() {
            window.push(job.keypoints());
        }
    }
    st.hidden.copy_from_slice(hidden);
    st.held.remember(&job.input, &job.present);
    st.lengths = running;
    let frames_seen = st.frames_seen();
    let state = due_state(job, &st, frames_seen);
    Ok(StepOutput {
        lengths: served,
        frames_seen,
        lifted: if job.lift { lifted } else { None },
        state,
        motion,
    })
}

/// A frame's in-band error (counted in the metrics).
pub fn frame_error(frame_index: u64, code: tonic::Code, message: String) -> pb::StreamResponse {
    metrics::frame_error(code);
    pb::StreamResponse {
        kind: Some(Resp::Error(pb::FrameError {
            frame_index,
            code: code as i32,
            message,
        })),
    }
}

/// A streamed frame's answer: its pose (the client's, or the one the
/// server lifted, named `lifter`) adjusted to the session's lengths, or
/// why it was not processed.
pub fn frame_response(
    frame_index: u64,
    client_pose: Option<Pose>,
    lifter: &str,
    received: Instant,
    result: Result<StepResult, oneshot::error::RecvError>,
) -> pb::StreamResponse {
    let output = match result {
        Ok(Ok(output)) => output,
        Ok(Err(e)) => return frame_error(frame_index, e.code(), e.to_string()),
        Err(_) => {
            return frame_error(
                frame_index,
                tonic::Code::Unavailable,
                "the batcher stopped before this frame".into(),
            )
        }
    };
    // The client's pose, or the one the server lifted for this frame.
    let (pose, lifted) = match (client_pose, output.lifted) {
        (Some(pose), _) => (pose, None),
        (None, Some(lifted)) => (lifted, Some(lifted)),
        (None, None) => {
            return frame_error(
                frame_index,
                tonic::Code::Internal,
                "the frame has neither a client pose nor a lifted one".into(),
            )
        }
    };
    // No estimate yet (a first frame without a detected joint): the pose
    // as it is, with its own lengths.
    let lengths = output.lengths.unwrap_or_else(|| bones::bone_lengths(&pose));
    let adjusted = match &output.motion {
        Some(m) => Ok(m.pose),
        None => bones::adjust_pose(&pose, &lengths),
    };
    let motion = output.motion.as_ref();
    match adjusted {
        Ok(adjusted) => {
            metrics::frame_ok(received.elapsed());
            pb::StreamResponse {
                kind: Some(Resp::Frame(pb::AdjustedFrame {
                    frame_index,
                    root_position: motion
                        .and_then(|m| m.root)
                        .map(|r| r.iter().map(|&v| v as f32).collect())
                        .unwrap_or_default(),
                    focal_assumed: motion.is_some_and(|m| m.focal_assumed),
                    world_pose_3d: motion
                        .and_then(|m| m.world)
                        .map(|w| w.iter().flatten().copied().collect())
                        .unwrap_or_default(),
                    adjusted_pose_3d: adjusted.iter().flatten().copied().collect(),
                    bone_lengths: lengths.to_vec(),
                    frames_seen: output.frames_seen,
                    lifter: if lifted.is_some() {
                        lifter.to_string()
                    } else {
                        String::new()
                    },
                    lifted_pose_3d: lifted
                        .map(|p| p.iter().flatten().copied().collect())
                        .unwrap_or_default(),
                })),
            }
        }
        // Validation guarantees a pose the adjustment accepts; report
        // rather than panic if that ever stops holding.
        Err(e) => frame_error(
            frame_index,
            tonic::Code::Internal,
            format!("adjustment failed: {e}"),
        ),
    }
}

/// Each frame's pose rebuilt with that frame's lengths.
pub fn adjust_frames(poses: &[Pose], lengths: &[BoneLengths]) -> Result<Vec<Pose>, Status> {
    bones::adjust_sequence_per_frame(poses, lengths, ZeroBonePolicy::Error)
        .map_err(|e| Status::internal(format!("adjustment failed: {e}")))
}

/// A whole sequence's answer: the adjusted poses and the lengths applied
/// to each frame.
pub fn sequence_response(
    model: ModelKind,
    poses: &[Pose],
    lengths: &[f32],
) -> pb::AdjustSequenceResponse {
    pb::AdjustSequenceResponse {
        model: pb::Model::from(model) as i32,
        adjusted_poses_3d: poses.iter().flatten().flatten().copied().collect(),
        bone_lengths: lengths.to_vec(),
        ..Default::default()
    }
}

/// A whole sequence's poses rebuilt with its subject's lengths (no model
/// runs).
pub fn subject_frames(poses: &[Pose], subject: &SessionSubject) -> Result<Vec<Pose>, Status> {
    bones::adjust_sequence(poses, &subject.lengths)
        .map_err(|e| Status::internal(format!("adjustment failed: {e}")))
}

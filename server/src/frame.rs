//! What a frame is as it passes the stages, and what it comes out as.
//!
//! A streamed frame leaves [`crate::validate`] as a [`FrameJob`], waits in
//! [`crate::batch`]'s queue, and on the batcher thread
//! ([`crate::pipeline`]) goes through [`crate::prepare`], [`crate::step`]
//! and [`crate::answer`], which hands back a [`StepResult`] on the job's
//! oneshot. Every stage reads and writes these types, so they live apart
//! from all of them: no stage has to import another just for its types.

use std::sync::Arc;

use blapose_core::{BoneLengths, Keypoints2d, Pose, NUM_JOINTS};
use tokio::sync::oneshot;

use crate::backend::INPUT_DIM;
use crate::motion::FrameMotion;
use crate::session::{Session, StateCopy};

/// One frame to run.
#[derive(Debug)]
pub struct FrameJob {
    /// Its session.
    pub session: Arc<Session>,
    /// The epoch of the stream that sent it.
    pub epoch: u64,
    /// Normalized Human3.6M-17 keypoints, joint-major (x, y); a missing
    /// joint's pair is a placeholder, replaced by its held position
    /// ([`blapose_core::missing::HeldJoints`]) when the frame runs.
    pub input: [f32; INPUT_DIM],
    /// Which joints were detected.
    pub present: [bool; NUM_JOINTS],
    /// Lift the pose from the session's window and `input` with the server
    /// lifter (the session must have been opened lifting).
    pub lift: bool,
    /// The client's pose (`None` when the server lifts it): what the
    /// motion stage smooths, for sessions opened with motion.
    pub pose: Option<Pose>,
    /// Copy the session's state into the answer ([`StepOutput::state`])
    /// when this frame makes its frames seen a multiple of this (0: never);
    /// the copy is taken under the same lock as the update, so it is
    /// exactly the state after this frame (for periodic session tokens).
    pub state_every: u64,
    /// Where the answer goes.
    pub reply: oneshot::Sender<StepResult>,
}

impl FrameJob {
    /// The frame's keypoints (its model input) as a keypoint frame: what
    /// the server lifter's window holds.
    pub fn keypoints(&self) -> Keypoints2d {
        std::array::from_fn(|j| [self.input[2 * j], self.input[2 * j + 1]])
    }
}

/// A processed frame.
#[derive(Debug, Clone, PartialEq)]
pub struct StepOutput {
    /// The lengths the session answers with after this frame
    /// ([`SessionConfig::served`](crate::session::SessionConfig::served):
    /// its running-mean estimate, or its subject's); `None` for a frame
    /// without a detected joint before any frame was read (no estimate
    /// yet).
    pub lengths: Option<BoneLengths>,
    /// Frames processed in the session, this one included.
    pub frames_seen: u64,
    /// The server lifter's pose for this frame (root at 0), for a lifting
    /// frame; `None` when the client sent the pose.
    pub lifted: Option<Pose>,
    /// The session's state right after this frame, when the job asked for
    /// it ([`FrameJob::state_every`]).
    pub state: Option<Box<StateCopy>>,
    /// What the motion stage made of the frame (sessions opened with
    /// motion; `None` for a frame without a detected joint).
    pub motion: Option<FrameMotion>,
}

/// Why an accepted frame was not processed. The session is unchanged.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum StepError {
    /// Another stream resumed the session, or it was closed, after the frame
    /// was queued.
    #[error("the session was resumed by another stream or closed before this frame ran")]
    Superseded,
    /// The model failed on the whole batch.
    #[error("the model failed: {0}")]
    Model(String),
    /// The model produced NaN or infinity for this frame.
    #[error(
        "the model produced a non-finite result for this frame; the session state was not updated"
    )]
    NonFinite,
    /// The server lifter failed on this frame.
    #[error("the server lifter failed: {0}; the session state was not updated")]
    Lifter(String),
    /// The motion stage could not smooth the frame's pose.
    #[error("the motion stage failed: {0}; the session state was not updated")]
    Motion(String),
    /// The server lifter's pose cannot be adjusted (non-finite, out of
    /// bounds or a zero-length bone).
    #[error("the server lifter produced a pose that cannot be adjusted ({0}); the session state was not updated")]
    LiftedPose(String),
}

impl StepError {
    /// The gRPC code this error is reported with.
    pub fn code(&self) -> tonic::Code {
        match self {
            StepError::Superseded => tonic::Code::Aborted,
            StepError::Model(_)
            | StepError::NonFinite
            | StepError::Lifter(_)
            | StepError::Motion(_)
            | StepError::LiftedPose(_) => tonic::Code::Internal,
        }
    }
}

/// Result of one frame.
pub type StepResult = Result<StepOutput, StepError>;

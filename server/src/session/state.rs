//! One session: what it was opened with ([`SessionConfig`]), the model
//! state its frames leave ([`SessionState`], behind the session's one
//! mutex with the owning stream's epoch), and the copies of that state a
//! session token carries ([`StateCopy`]).

use std::sync::{Arc, Mutex, MutexGuard, PoisonError};

use blapose_core::missing::HeldJoints;
use blapose_core::motion::{CausalMotion, MotionState};
use blapose_core::BoneLengths;
use blapose_lifters::SlidingWindow;
use blapose_model::input::{InputCamera, ViewCalibration};
use blapose_proto::v1 as pb;
use tokio::sync::watch;

use crate::motion::SessionMotion;
use crate::quota::ClientId;
use crate::session::error::SessionError;
use crate::session::id::SessionId;

/// Floats of recurrent state per session (two GRUs x 512).
pub const STATE_DIM: usize = blapose_model::STATE_DIM;

/// How a session's 2D keypoints are expressed (the client library's type
/// too, so both ends mean the same thing).
pub use blapose_core::layouts::Coordinates;

/// What a session was opened with, fixed for its life: the keypoints'
/// layout and units (blapose-core's definition, shared with the client).
pub use blapose_core::layouts::InputFormat;

/// A session's camera: the calibration as the client sent it (echoed on
/// open and resume, carried by session tokens) and the camera the
/// camera-aware model reads the session's keypoints through
/// ([`crate::validate::camera`], built once when the calibration arrives).
#[derive(Debug, Clone, PartialEq)]
pub struct SessionCamera {
    /// As sent in `OpenSession.camera`.
    pub calibration: pb::CameraCalibration,
    /// What the camera-aware model's input contract makes of it (`None`
    /// for a contract that reads screen coordinates).
    pub input: Option<InputCamera>,
    /// Its checked view (intrinsics, lens, up, height): what the motion
    /// stage places the person through.
    pub view: ViewCalibration,
}

/// A session's (or request's) subject: the person's stature and sex as
/// sent, and the lengths the stature model gives them, which the session
/// answers with.
#[derive(Debug, Clone, PartialEq)]
pub struct SessionSubject {
    /// As sent in `OpenSession.subject`.
    pub subject: pb::Subject,
    /// The stature regression's lengths for it.
    pub lengths: BoneLengths,
}

/// Immutable description of a session.
#[derive(Debug, Clone)]
pub struct SessionConfig {
    /// Input format of every frame.
    pub input: InputFormat,
    /// Free-form client label for logs (truncated).
    pub label: String,
    /// `Some(frames)`: the server lifts this session's poses with a lifter
    /// whose window holds `frames` frames; `None`: the client sends them.
    pub lifter_frames: Option<usize>,
    /// `Some`: the camera-aware model serves the session, fed its keypoints
    /// through this camera; `None`: the default model.
    pub camera: Option<SessionCamera>,
    /// `Some`: the session answers with its subject's stature-regression
    /// lengths instead of the model's running estimate.
    pub subject: Option<SessionSubject>,
    /// `Some`: the causal motion stage runs on every answer
    /// ([`crate::motion`]).
    pub motion: Option<SessionMotion>,
}

impl SessionConfig {
    /// Whether the server lifts this session's poses.
    pub fn lifting(&self) -> bool {
        self.lifter_frames.is_some()
    }

    /// The lengths the session answers with, given its model's running
    /// estimate: its subject's when it has one.
    pub fn served(&self, estimate: Option<BoneLengths>) -> Option<BoneLengths> {
        match &self.subject {
            Some(s) => Some(s.lengths),
            None => estimate,
        }
    }
}

/// Longest client label kept, in bytes.
pub const MAX_LABEL_BYTES: usize = 128;

/// The online estimate: the mean of every per-frame length prediction so
/// far (the BLAPose reference's online rule), blapose-model's one
/// definition of it.
pub use blapose_model::RunningMean;

/// Mutable per-session model state; only the batcher writes `hidden` and
/// `lengths`.
#[derive(Debug)]
pub struct SessionState {
    /// Current owner; work stamped with another epoch is refused.
    pub epoch: u64,
    /// Set once the session is closed or evicted.
    pub closed: bool,
    /// GRU hidden states, `STATE_DIM` floats.
    pub hidden: Box<[f32]>,
    /// Running-mean length estimate and frames seen.
    pub lengths: RunningMean,
    /// The server lifter's window of this session's accepted frames
    /// (normalized Human3.6M-17 keypoints); `None` unless the session lifts.
    /// Only the batcher pushes to it, together with `hidden` and `lengths`.
    pub window: Option<Box<SlidingWindow>>,
    /// Each joint's last detected position (normalized Human3.6M-17), what
    /// a missing joint is read as ([`blapose_core::missing`]).
    pub held: HeldJoints,
    /// Frames answered without a detected joint: they changed nothing
    /// else, and count among the frames seen.
    pub skipped: u64,
    /// Frames seen in the newest session token issued (or restored) here:
    /// once the session ends, an older token is refused as a rollback.
    pub newest_token: u64,
    /// The causal motion stage's filters (sessions opened with motion).
    pub motion: Option<CausalMotion>,
    /// For a session restored from a token: the issue time (ms since the
    /// Unix epoch) its tokens expire from, the first token of its chain's,
    /// so that no chain of restores outlives that token's TTL.
    pub token_origin_ms: Option<u64>,
}

impl SessionState {
    /// Frames processed: those the model read, and those without a
    /// detected joint.
    pub fn frames_seen(&self) -> u64 {
        self.lengths.count() + self.skipped
    }

    /// The running-mean length estimate; `None` before the first frame.
    pub fn estimate(&self) -> Option<BoneLengths> {
        self.lengths.mean()
    }

    /// Whether work stamped with `epoch` may still change this session.
    pub fn accepts(&self, epoch: u64) -> bool {
        !self.closed && self.epoch == epoch
    }

    /// A copy of the model state (what a session token carries).
    pub fn copy_state(&self) -> StateCopy {
        StateCopy {
            hidden: self.hidden.clone(),
            lengths: self.lengths,
            window: self.window.as_deref().map(|w| w.iter().copied().collect()),
            held: self.held,
            skipped: self.skipped,
            motion: self.motion.as_ref().map(CausalMotion::state),
            origin_ms: self.token_origin_ms,
        }
    }
}

/// A copy of a session's model state at one moment: what a session token
/// holds besides the session's fixed configuration.
#[derive(Debug, Clone, PartialEq)]
pub struct StateCopy {
    /// GRU hidden states, `STATE_DIM` floats.
    pub hidden: Box<[f32]>,
    /// Running mean and frames seen.
    pub lengths: RunningMean,
    /// The lifter window's frames, oldest first (lifting sessions).
    pub window: Option<Vec<blapose_core::Keypoints2d>>,
    /// Each joint's last detected position.
    pub held: HeldJoints,
    /// Frames answered without a detected joint.
    pub skipped: u64,
    /// The motion stage's filter state (sessions opened with motion).
    pub motion: Option<MotionState>,
    /// The issue time its tokens expire from, for a session restored from
    /// a token ([`SessionState::token_origin_ms`]); `None`: each token's own.
    pub origin_ms: Option<u64>,
}

impl StateCopy {
    /// Frames processed in this state ([`SessionState::frames_seen`]).
    pub fn frames_seen(&self) -> u64 {
        self.lengths.count() + self.skipped
    }
}

/// Who owns a session now, as the attached stream watches it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Ownership {
    /// Current epoch.
    pub epoch: u64,
    /// Closed (by CloseSession or eviction).
    pub closed: bool,
}

/// One session. Shared (`Arc`) between the store, its stream and queued
/// frames.
#[derive(Debug)]
pub struct Session {
    id: SessionId,
    key: u64,
    config: SessionConfig,
    client: ClientId,
    state: Mutex<SessionState>,
    owner: watch::Sender<Ownership>,
}

impl Session {
    pub(super) fn new(id: SessionId, key: u64, config: SessionConfig, client: ClientId) -> Self {
        let state = SessionState {
            epoch: 1,
            closed: false,
            hidden: vec![0.0; STATE_DIM].into_boxed_slice(),
            lengths: RunningMean::new(),
            window: config
                .lifter_frames
                .map(|frames| Box::new(SlidingWindow::new(frames))),
            held: HeldJoints::default(),
            skipped: 0,
            newest_token: 0,
            motion: config.motion.as_ref().map(SessionMotion::stage),
            token_origin_ms: None,
        };
        let (owner, _) = watch::channel(Ownership {
            epoch: 1,
            closed: false,
        });
        Self {
            id,
            key,
            config,
            client,
            state: Mutex::new(state),
            owner,
        }
    }

    /// Public id.
    pub fn id(&self) -> SessionId {
        self.id
    }

    /// Small process-unique key (cheap to hash; used by the batcher).
    pub fn key(&self) -> u64 {
        self.key
    }

    /// The session's fixed configuration.
    pub fn config(&self) -> &SessionConfig {
        &self.config
    }

    /// The client the session counts against.
    pub fn client(&self) -> ClientId {
        self.client
    }

    /// Lock the model state. A poisoned lock (a panic elsewhere while
    /// holding it) still yields the state: every writer leaves it consistent
    /// between statements, so there is nothing to recover.
    pub fn lock(&self) -> MutexGuard<'_, SessionState> {
        self.state.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Watch ownership changes (takeover, close).
    pub fn watch(&self) -> watch::Receiver<Ownership> {
        self.owner.subscribe()
    }

    pub(super) fn publish(&self, st: &SessionState) {
        self.owner.send_replace(Ownership {
            epoch: st.epoch,
            closed: st.closed,
        });
    }
}

/// A snapshot of a session at attach or close time.
#[derive(Debug, Clone)]
pub struct SessionSnapshot {
    /// Frames processed.
    pub frames_seen: u64,
    /// Running-mean estimate (`None` before the first frame).
    pub bone_lengths: Option<BoneLengths>,
}

/// A stream's claim on a session.
#[derive(Debug, Clone)]
pub struct Attachment {
    /// The session.
    pub session: Arc<Session>,
    /// The epoch this stream owns.
    pub epoch: u64,
    /// State at attach time.
    pub snapshot: SessionSnapshot,
}

/// Load a copy of a session's state (a token's) into `st`.
pub(crate) fn load(st: &mut SessionState, state: &StateCopy) -> Result<(), SessionError> {
    if state.hidden.len() != STATE_DIM {
        return Err(SessionError::Restore(format!(
            "a hidden state of {} floats, expected {STATE_DIM}",
            state.hidden.len()
        )));
    }
    match (st.window.as_deref_mut(), &state.window) {
        (Some(window), Some(frames)) => {
            if frames.len() > window.frames() {
                return Err(SessionError::Restore(format!(
                    "a lifter window of {} frames, the lifter holds {}",
                    frames.len(),
                    window.frames()
                )));
            }
            *window = SlidingWindow::new(window.frames());
            for frame in frames {
                window.push(*frame);
            }
        }
        (None, None) => {}
        _ => {
            return Err(SessionError::Restore(
                "the lifter window does not match the session's configuration".into(),
            ))
        }
    }
    st.motion = match (&st.motion, &state.motion) {
        (Some(stage), Some(filters)) => Some(
            CausalMotion::restore(*stage.config(), filters).ok_or_else(|| {
                SessionError::Restore("the motion state does not fit the motion stage".into())
            })?,
        ),
        (None, None) => None,
        _ => {
            return Err(SessionError::Restore(
                "the motion state does not match the session's configuration".into(),
            ))
        }
    };
    st.hidden.copy_from_slice(&state.hidden);
    st.lengths = state.lengths;
    st.held = state.held;
    st.skipped = state.skipped;
    st.newest_token = state.frames_seen();
    // The expiry origin is not loaded: a session held here keeps its own
    // (it is no fork); a new one takes the token's in `SessionStore::restore`.
    Ok(())
}

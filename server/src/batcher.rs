//! Cross-session batching of online GRU steps (Triton's "oldest" sequence
//! batching).
//!
//! A GRU step costs almost the same for 1 session as for 32 (the weights are
//! read once either way), so frames from all streams wait in one bounded
//! queue and a dedicated thread runs them together. The rules:
//!
//! * **At most one frame per session per batch**: a session's next frame
//!   needs the hidden state its previous frame produces, so a session's
//!   frames run one batch after another, in the order they were submitted.
//! * **Oldest first**: sessions enter a batch in the order of their oldest
//!   waiting frame; a session with more frames waiting goes to the back.
//! * **Bounded wait**: a partial batch runs as soon as every attached stream
//!   has a frame waiting (nobody else can contribute), or when the oldest
//!   frame has waited `max_queue_delay`, whichever comes first. A lone
//!   pipelined stream therefore never waits for company.
//! * **Explicit backpressure**: a full queue refuses the frame
//!   ([`SubmitError::QueueFull`] -> RESOURCE_EXHAUSTED); nothing is dropped
//!   silently. Every accepted frame is answered exactly once through its
//!   oneshot, including at shutdown (the queue is drained first).
//! * **Off the async runtime**: model execution happens on the batcher's own
//!   OS thread, never on a tokio worker.
//!
//! Hidden states stay in their sessions; the batcher gathers them into one
//! contiguous buffer, runs one [`Backend::step`], checks every row is finite
//! and scatters them back. A row whose session changed owner meanwhile, or
//! whose outputs are not finite, is not written back: a bad step never
//! corrupts a session.
//!
//! **Server lifter.** Frames of sessions whose poses the server lifts are
//! lifted here too, before the GRU step, because this is where a session's
//! frames are processed strictly one after another: the lifter's window for
//! frame `t` must hold exactly the frames before `t` that were *accepted*,
//! which is only known once frame `t - 1` has been through its step. Each
//! lifting row's window plus its new frame is copied out (the session's
//! window is not touched), all of a batch's windows run through the lifter
//! in one call, every pose is checked as a client's pose would be, and the
//! new frame is pushed into the session's window in the same locked scatter
//! that writes its GRU state, so a frame refused at any point (lifting, the
//! step, a takeover) leaves the window as it was. A lifter failure, even a
//! panic, fails only the rows it concerns.
//!
//! **Camera-aware sessions.** Sessions opened with a camera calibration are
//! served by a second model ([`OnlineBackends::camera_aware`]) that reads
//! keypoints as a level camera would see them. A batch's rows are grouped by
//! model, the camera-aware rows' inputs rectified with their session's
//! [`blapose_core::level::LevelCamera`] as they are gathered (the lifter
//! windows keep the keypoints as sent), and each group runs as its own step.

use std::collections::{HashMap, VecDeque};
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard, PoisonError};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use blapose_core::{BoneLengths, Keypoints2d, Pose, NUM_JOINTS};
use blapose_lifters::trained::FRAME_VALUES;
use tokio::sync::oneshot;

use crate::backend::{Backend, BackendError, INPUT_DIM, OUTPUT_DIM, STATE_DIM};
use crate::metrics;
use crate::models::LoadedLifter;
use crate::session::{add_prediction, Session, SessionState, StateCopy};
use crate::validate;

/// Batching limits.
#[derive(Debug, Clone, Copy)]
pub struct BatcherConfig {
    /// Most frames per step (>= 1).
    pub max_batch: usize,
    /// Longest wait for more sessions before running a partial batch.
    pub max_queue_delay: Duration,
    /// Most frames waiting at once, all sessions together (>= 1).
    pub queue_capacity: usize,
}

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
    /// Copy the session's state into the answer ([`StepOutput::state`])
    /// when this frame makes its frames seen a multiple of this (0: never);
    /// the copy is taken under the same lock as the update, so it is
    /// exactly the state after this frame (for periodic session tokens).
    pub state_every: u64,
    /// Where the answer goes.
    pub reply: oneshot::Sender<StepResult>,
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
            | StepError::LiftedPose(_) => tonic::Code::Internal,
        }
    }
}

/// Result of one frame.
pub type StepResult = Result<StepOutput, StepError>;

/// Why a frame was refused at submission (it was never queued).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum SubmitError {
    /// The queue holds `capacity` frames already.
    #[error("server busy: the frame queue is full ({capacity} frames waiting); retry after earlier answers arrive")]
    QueueFull {
        /// The queue's capacity.
        capacity: usize,
    },
    /// The batcher is shutting down.
    #[error("the server is shutting down")]
    ShuttingDown,
}

impl SubmitError {
    /// The gRPC code this error is reported with.
    pub fn code(&self) -> tonic::Code {
        match self {
            SubmitError::QueueFull { .. } => tonic::Code::ResourceExhausted,
            SubmitError::ShuttingDown => tonic::Code::Unavailable,
        }
    }
}

#[derive(Debug)]
struct Queued {
    job: FrameJob,
    enqueued: Instant,
}

#[derive(Debug, Default)]
struct Queue {
    /// Waiting frames per session key, in submission order.
    per_session: HashMap<u64, VecDeque<Queued>>,
    /// Session keys with waiting frames, oldest first; each key once.
    ready: VecDeque<u64>,
    /// Total waiting frames.
    len: usize,
    closed: bool,
}

impl Queue {
    fn oldest(&self) -> Option<Instant> {
        let key = self.ready.front()?;
        self.per_session.get(key)?.front().map(|q| q.enqueued)
    }
}

struct Shared {
    queue: Mutex<Queue>,
    available: Condvar,
    config: BatcherConfig,
    active_streams: AtomicUsize,
    lifter: Option<Arc<LoadedLifter>>,
}

impl std::fmt::Debug for Shared {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Shared")
            .field("config", &self.config)
            .field("lifter", &self.lifter.as_ref().map(|l| l.name()))
            .finish()
    }
}

impl Shared {
    fn lock(&self) -> MutexGuard<'_, Queue> {
        self.queue.lock().unwrap_or_else(PoisonError::into_inner)
    }
}

/// The batcher: a queue plus the thread that drains it.
#[derive(Debug)]
pub struct Batcher {
    shared: Arc<Shared>,
    thread: Mutex<Option<JoinHandle<()>>>,
}

/// Counts an attached stream while alive (the batcher stops waiting for
/// more frames once every attached stream has one queued).
#[derive(Debug)]
pub struct StreamGuard {
    shared: Arc<Shared>,
}

impl Drop for StreamGuard {
    fn drop(&mut self) {
        self.shared.active_streams.fetch_sub(1, Ordering::Relaxed);
        self.shared.available.notify_one();
    }
}

/// The online models a batcher runs.
#[derive(Debug)]
pub struct OnlineBackends<B> {
    /// For sessions without a camera calibration.
    pub default: B,
    /// For sessions with one (fed rectified keypoints); `None`: the server
    /// has no camera-aware model and refuses such sessions at open.
    pub camera_aware: Option<B>,
}

/// Run one step on zero inputs and check the outputs are finite, so a
/// server reports SERVING only with a model that works.
pub fn warm_up<B: Backend>(backend: &mut B) -> Result<(), BackendError> {
    let inputs = [0.0f32; INPUT_DIM];
    let mut hidden = vec![0.0f32; STATE_DIM];
    let mut lengths = [0.0f32; OUTPUT_DIM];
    backend.step(&inputs, &mut hidden, &mut lengths, 1)?;
    if hidden.iter().chain(lengths.iter()).all(|v| v.is_finite()) {
        Ok(())
    } else {
        Err(BackendError::Model(
            "warm-up step produced non-finite values".into(),
        ))
    }
}

/// Lift one window of zeros and check the pose is finite, so a server
/// reports SERVING only with a lifter that works.
pub fn warm_up_lifter(lifter: &LoadedLifter) -> Result<(), BackendError> {
    let windows = vec![0.0f32; lifter.lifter.receptive_field() * FRAME_VALUES];
    match guarded(|| lifter.lifter.lift_windows(&windows, 1)) {
        Ok(poses) if poses.iter().flatten().flatten().all(|v| v.is_finite()) => Ok(()),
        Ok(_) => Err(BackendError::Model(
            "lifter warm-up produced non-finite values".into(),
        )),
        Err(e) => Err(BackendError::Model(format!("lifter warm-up failed: {e}"))),
    }
}

impl Batcher {
    /// Warm the backend up and start the batcher thread (no camera-aware
    /// model, no lifter).
    pub fn start<B: Backend>(backend: B, config: BatcherConfig) -> Result<Self, BackendError> {
        Self::start_with_lifter(backend, config, None)
    }

    /// [`Batcher::start`] with a server lifter for the frames of lifting
    /// sessions (warmed up too).
    pub fn start_with_lifter<B: Backend>(
        backend: B,
        config: BatcherConfig,
        lifter: Option<Arc<LoadedLifter>>,
    ) -> Result<Self, BackendError> {
        let backends = OnlineBackends {
            default: backend,
            camera_aware: None,
        };
        Self::start_with(backends, config, lifter)
    }

    /// Warm every model (and the lifter) up and start the batcher thread.
    pub fn start_with<B: Backend>(
        mut backends: OnlineBackends<B>,
        config: BatcherConfig,
        lifter: Option<Arc<LoadedLifter>>,
    ) -> Result<Self, BackendError> {
        let config = BatcherConfig {
            max_batch: config.max_batch.max(1),
            queue_capacity: config.queue_capacity.max(1),
            ..config
        };
        warm_up(&mut backends.default)?;
        if let Some(camera_aware) = &mut backends.camera_aware {
            warm_up(camera_aware)?;
        }
        if let Some(lifter) = &lifter {
            warm_up_lifter(lifter)?;
        }
        let shared = Arc::new(Shared {
            queue: Mutex::new(Queue::default()),
            available: Condvar::new(),
            config,
            active_streams: AtomicUsize::new(0),
            lifter,
        });
        let worker = shared.clone();
        let thread = std::thread::Builder::new()
            .name("blapose-batcher".into())
            .spawn(move || run(worker, backends))
            .map_err(|e| BackendError::Model(format!("cannot start the batcher thread: {e}")))?;
        Ok(Self {
            shared,
            thread: Mutex::new(Some(thread)),
        })
    }

    /// The limits in force.
    pub fn config(&self) -> BatcherConfig {
        self.shared.config
    }

    /// Register an attached stream for the duration of the guard.
    pub fn stream_guard(&self) -> StreamGuard {
        self.shared.active_streams.fetch_add(1, Ordering::Relaxed);
        StreamGuard {
            shared: self.shared.clone(),
        }
    }

    /// Frames waiting now.
    pub fn queue_len(&self) -> usize {
        self.shared.lock().len
    }

    /// Queue a frame; its answer arrives on `job.reply`. Never blocks.
    pub fn submit(&self, job: FrameJob) -> Result<(), SubmitError> {
        let mut q = self.shared.lock();
        if q.closed {
            return Err(SubmitError::ShuttingDown);
        }
        let capacity = self.shared.config.queue_capacity;
        if q.len >= capacity {
            return Err(SubmitError::QueueFull { capacity });
        }
        let key = job.session.key();
        let frames = q.per_session.entry(key).or_default();
        let first = frames.is_empty();
        frames.push_back(Queued {
            job,
            enqueued: Instant::now(),
        });
        if first {
            q.ready.push_back(key);
        }
        q.len += 1;
        drop(q);
        self.shared.available.notify_one();
        Ok(())
    }

    /// Stop accepting frames; the thread answers every queued frame, then
    /// exits. Idempotent.
    pub fn close(&self) {
        self.shared.lock().closed = true;
        self.shared.available.notify_all();
    }

    /// [`close`](Self::close) and wait for the thread to finish (blocking).
    pub fn join(&self) {
        self.close();
        let handle = self
            .thread
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .take();
        if let Some(handle) = handle {
            if handle.join().is_err() {
                tracing::error!("the batcher thread panicked");
            }
        }
    }
}

impl Drop for Batcher {
    fn drop(&mut self) {
        self.join();
    }
}

/// Preallocated step buffers (no allocation per batch; the lifter's grow
/// to the largest batch of lifting rows seen, and stay empty without one).
struct Buffers {
    inputs: Vec<f32>,
    hidden: Vec<f32>,
    lengths: Vec<f32>,
    /// For each buffer row, its index in the batch.
    rows: Vec<usize>,
    /// Lifter windows of the lifting rows, one after the other.
    windows: Vec<f32>,
    /// For each lifter window, its index in the batch.
    lift_rows: Vec<usize>,
    /// For each batch index, the lifted pose (lifting rows that succeeded).
    lifted: Vec<Option<Pose>>,
}

fn run<B: Backend>(shared: Arc<Shared>, mut backends: OnlineBackends<B>) {
    let max = shared.config.max_batch;
    let mut buffers = Buffers {
        inputs: vec![0.0; max * INPUT_DIM],
        hidden: vec![0.0; max * STATE_DIM],
        lengths: vec![0.0; max * OUTPUT_DIM],
        rows: Vec::with_capacity(max),
        windows: Vec::new(),
        lift_rows: Vec::new(),
        lifted: Vec::with_capacity(max),
    };
    let mut batch: Vec<Queued> = Vec::with_capacity(max);
    while next_batch(&shared, &mut batch) {
        run_batch(&mut backends, &mut batch, &mut buffers, &shared);
    }
}

/// What the batcher does with the frames waiting.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Gather {
    /// Take a batch now.
    Run,
    /// Wait for more sessions' frames, until this instant at the latest.
    WaitUntil(Instant),
}

/// The batching rule, apart from the clock so it can be tested without
/// one: with `ready` sessions having a frame waiting, `streams` streams
/// attached and the oldest frame queued at `oldest`, run once every stream
/// that could contribute has a frame waiting (at most `max_batch`; a lone
/// stream never waits), the queue is closing, or the oldest frame has
/// waited `max_queue_delay`; otherwise wait until that deadline.
fn gather(
    config: &BatcherConfig,
    ready: usize,
    streams: usize,
    closed: bool,
    oldest: Instant,
    now: Instant,
) -> Gather {
    let target = config.max_batch.min(streams.max(1));
    let deadline = oldest + config.max_queue_delay;
    if closed || ready >= target || now >= deadline {
        Gather::Run
    } else {
        Gather::WaitUntil(deadline)
    }
}

/// Wait for frames and take the next batch; `false` once closed and empty.
fn next_batch(shared: &Shared, batch: &mut Vec<Queued>) -> bool {
    let config = shared.config;
    let mut q = shared.lock();
    while q.len == 0 {
        if q.closed {
            return false;
        }
        q = shared
            .available
            .wait(q)
            .unwrap_or_else(PoisonError::into_inner);
    }
    if let Some(oldest) = q.oldest() {
        loop {
            let streams = shared.active_streams.load(Ordering::Relaxed);
            let now = Instant::now();
            let wait = match gather(&config, q.ready.len(), streams, q.closed, oldest, now) {
                Gather::Run => break,
                Gather::WaitUntil(deadline) => deadline - now,
            };
            q = shared
                .available
                .wait_timeout(q, wait)
                .unwrap_or_else(PoisonError::into_inner)
                .0;
        }
    }
    let mut more = Vec::new();
    while batch.len() < config.max_batch {
        let Some(key) = q.ready.pop_front() else {
            break;
        };
        let Some(frames) = q.per_session.get_mut(&key) else {
            continue;
        };
        let Some(item) = frames.pop_front() else {
            q.per_session.remove(&key);
            continue;
        };
        if frames.is_empty() {
            q.per_session.remove(&key);
        } else {
            more.push(key);
        }
        batch.push(item);
    }
    q.ready.extend(more);
    q.len -= batch.len();
    true
}

fn run_batch<B: Backend>(
    backends: &mut OnlineBackends<B>,
    batch: &mut Vec<Queued>,
    buf: &mut Buffers,
    shared: &Shared,
) {
    let started = Instant::now();
    buf.rows.clear();
    let mut answers: Vec<Option<StepResult>> = batch.iter().map(|_| None).collect();
    for (item, answer) in batch.iter_mut().zip(answers.iter_mut()) {
        *answer = fill_missing(&mut item.job);
    }
    buf.lifted.clear();
    buf.lifted.resize(batch.len(), None);
    if let Some(lifter) = &shared.lifter {
        lift_rows(&lifter.lifter, batch, &mut answers, buf);
    } else {
        for (item, answer) in batch.iter().zip(answers.iter_mut()) {
            if item.job.lift {
                *answer = Some(Err(StepError::Lifter("this server has no lifter".into())));
            }
        }
    }
    for item in batch.iter() {
        metrics::queue_wait(started.saturating_duration_since(item.enqueued));
    }
    // The default model's rows first, then the camera-aware ones, each
    // group one step.
    let split = gather_rows(batch, &mut answers, buf, false);
    let n = gather_rows(batch, &mut answers, buf, true);
    step_rows(&mut backends.default, batch, &mut answers, buf, 0..split);
    if split < n {
        match &mut backends.camera_aware {
            Some(backend) => step_rows(backend, batch, &mut answers, buf, split..n),
            None => {
                for &i in &buf.rows[split..n] {
                    answers[i] = Some(Err(StepError::Model(
                        "this server has no camera-aware model".into(),
                    )));
                }
            }
        }
    }
    let queue_depth = shared.lock().len;
    metrics::batch(n, started.elapsed(), queue_depth);
    for (item, answer) in batch.drain(..).zip(answers) {
        // `None` cannot happen (every row was answered above); be explicit
        // rather than panic.
        let answer = answer.unwrap_or_else(|| Err(StepError::Model("frame was not run".into())));
        // A dropped receiver means the stream went away; nothing to do.
        let _ = item.job.reply.send(answer);
    }
}

/// Append to the buffers the rows of sessions with (`camera_aware`) or
/// without a camera that are still owned by the frame's stream and not yet
/// answered, rectifying camera-aware inputs; returns the rows gathered so
/// far.
fn gather_rows(
    batch: &[Queued],
    answers: &mut [Option<StepResult>],
    buf: &mut Buffers,
    camera_aware: bool,
) -> usize {
    for (i, item) in batch.iter().enumerate() {
        let camera = item.job.session.config().camera.as_ref();
        if answers[i].is_some() || camera.is_some() != camera_aware {
            continue;
        }
        let st = item.job.session.lock();
        if !st.accepts(item.job.epoch) {
            answers[i] = Some(Err(StepError::Superseded));
            continue;
        }
        let r = buf.rows.len();
        buf.hidden[r * STATE_DIM..(r + 1) * STATE_DIM].copy_from_slice(&st.hidden);
        drop(st);
        let input = &mut buf.inputs[r * INPUT_DIM..(r + 1) * INPUT_DIM];
        input.copy_from_slice(&item.job.input);
        if let Some(camera) = camera {
            camera.level.rectify_frames(input);
        }
        buf.rows.push(i);
    }
    buf.rows.len()
}

/// Run the buffer rows `range` through `backend` as one step and answer
/// them.
fn step_rows<B: Backend>(
    backend: &mut B,
    batch: &[Queued],
    answers: &mut [Option<StepResult>],
    buf: &mut Buffers,
    range: std::ops::Range<usize>,
) {
    let n = range.len();
    if n == 0 {
        return;
    }
    let (start, end) = (range.start, range.end);
    let result = backend.step(
        &buf.inputs[start * INPUT_DIM..end * INPUT_DIM],
        &mut buf.hidden[start * STATE_DIM..end * STATE_DIM],
        &mut buf.lengths[start * OUTPUT_DIM..end * OUTPUT_DIM],
        n,
    );
    let rows = &buf.rows[range];
    match result {
        // Scatter: only finite rows of sessions whose owner is unchanged.
        Ok(()) => {
            for (r, &i) in (start..end).zip(rows) {
                let hidden = &buf.hidden[r * STATE_DIM..(r + 1) * STATE_DIM];
                let lengths = &buf.lengths[r * OUTPUT_DIM..(r + 1) * OUTPUT_DIM];
                answers[i] = Some(scatter(&batch[i].job, hidden, lengths, buf.lifted[i]));
            }
        }
        // The engine refuses a whole batch for one bad row; isolate it by
        // re-running the rows one at a time, so one session's problem
        // never fails another session's frame.
        Err(e) if n > 1 => {
            tracing::warn!(error = %e, batch = n, "batched step failed; retrying its rows one by one");
            for (r, &i) in (start..end).zip(rows) {
                let input = &buf.inputs[r * INPUT_DIM..(r + 1) * INPUT_DIM];
                answers[i] = Some(step_alone(backend, &batch[i].job, input, buf.lifted[i]));
            }
        }
        Err(e) => {
            for &i in rows {
                answers[i] = Some(Err(StepError::Model(e.to_string())));
            }
        }
    }
}

/// Run `f`, turning a panic into an error: the lifter is a large numeric
/// library call on the batcher thread, and a panic there must fail its rows,
/// not stop the thread that serves every session.
fn guarded<T>(f: impl FnOnce() -> blapose_lifters::Result<T>) -> Result<T, String> {
    match catch_unwind(AssertUnwindSafe(f)) {
        Ok(Ok(v)) => Ok(v),
        Ok(Err(e)) => Err(e.to_string()),
        Err(panic) => Err(format!(
            "panicked: {}",
            panic
                .downcast_ref::<&str>()
                .map(|s| s.to_string())
                .or_else(|| panic.downcast_ref::<String>().cloned())
                .unwrap_or_else(|| "unknown cause".into())
        )),
    }
}

/// The model input as a keypoint frame.
fn keypoints(input: &[f32; INPUT_DIM]) -> Keypoints2d {
    std::array::from_fn(|j| [input[2 * j], input[2 * j + 1]])
}

/// Lift every lifting row of `batch`: copy each session's window plus its
/// new frame out (the window itself is not changed), run all windows in one
/// lifter call, and check each pose. Rows that fail get their answer here;
/// the others get their pose in `buf.lifted`.
fn lift_rows(
    lifter: &blapose_lifters::TrainedLifter,
    batch: &[Queued],
    answers: &mut [Option<StepResult>],
    buf: &mut Buffers,
) {
    buf.windows.clear();
    buf.lift_rows.clear();
    for (i, item) in batch.iter().enumerate() {
        if !item.job.lift {
            continue;
        }
        let st = item.job.session.lock();
        if !st.accepts(item.job.epoch) {
            answers[i] = Some(Err(StepError::Superseded));
            continue;
        }
        let Some(window) = st.window.as_deref() else {
            answers[i] = Some(Err(StepError::Lifter(
                "the session has no lifter window".into(),
            )));
            continue;
        };
        if window.frames() != lifter.receptive_field() {
            answers[i] = Some(Err(StepError::Lifter(format!(
                "the session's window holds {} frames, the lifter needs {}",
                window.frames(),
                lifter.receptive_field()
            ))));
            continue;
        }
        window.extend_with_next(&keypoints(&item.job.input), &mut buf.windows);
        buf.lift_rows.push(i);
    }
    let n = buf.lift_rows.len();
    if n == 0 {
        return;
    }
    let started = Instant::now();
    let per_window = lifter.receptive_field() * FRAME_VALUES;
    match guarded(|| lifter.lift_windows(&buf.windows, n)) {
        Ok(poses) if poses.len() == n => {
            for (&i, pose) in buf.lift_rows.iter().zip(poses) {
                accept_lifted(i, pose, answers, &mut buf.lifted);
            }
        }
        // Isolate the row that broke the call: one window at a time.
        failed => {
            let reason = match failed {
                Ok(poses) => format!("{} poses for {n} windows", poses.len()),
                Err(e) => e,
            };
            if n > 1 {
                tracing::warn!(error = %reason, rows = n, "batched lift failed; retrying its rows one by one");
            }
            for (r, &i) in buf.lift_rows.iter().enumerate() {
                let window = &buf.windows[r * per_window..(r + 1) * per_window];
                match guarded(|| lifter.lift_windows(window, 1)).map(|mut p| p.pop()) {
                    Ok(Some(pose)) => accept_lifted(i, pose, answers, &mut buf.lifted),
                    Ok(None) => answers[i] = Some(Err(StepError::Lifter("no pose".into()))),
                    Err(e) => answers[i] = Some(Err(StepError::Lifter(e))),
                }
            }
        }
    }
    metrics::lift(n, started.elapsed());
}

fn accept_lifted(
    i: usize,
    pose: Pose,
    answers: &mut [Option<StepResult>],
    lifted: &mut [Option<Pose>],
) {
    match validate::lifted_pose(&pose) {
        Ok(pose) => lifted[i] = Some(pose),
        Err(e) => answers[i] = Some(Err(StepError::LiftedPose(e.to_string()))),
    }
}

/// Run one frame on its own (state re-read from the session, since a failed
/// step may have touched the gathered buffer).
fn step_alone<B: Backend>(
    backend: &mut B,
    job: &FrameJob,
    input: &[f32],
    lifted: Option<Pose>,
) -> StepResult {
    let mut hidden = vec![0.0f32; STATE_DIM];
    {
        let st = job.session.lock();
        if !st.accepts(job.epoch) {
            return Err(StepError::Superseded);
        }
        hidden.copy_from_slice(&st.hidden);
    }
    let mut lengths = [0.0f32; OUTPUT_DIM];
    match backend.step(input, &mut hidden, &mut lengths, 1) {
        Ok(()) => scatter(job, &hidden, &lengths, lifted),
        Err(e) => Err(StepError::Model(e.to_string())),
    }
}

/// Fill the frame's missing joints from its session's held ones. A frame
/// without a detected joint is answered here and leaves the model state,
/// the estimate and the held joints as they were: it only counts among the
/// frames seen. `Some` when the frame is answered (or superseded).
fn fill_missing(job: &mut FrameJob) -> Option<StepResult> {
    if !job.present.contains(&false) {
        return None;
    }
    let mut st = job.session.lock();
    if !st.accepts(job.epoch) {
        return Some(Err(StepError::Superseded));
    }
    if st.held.fill(&mut job.input, &job.present) {
        return None;
    }
    st.skipped += 1;
    let frames_seen = st.frames_seen();
    Some(Ok(StepOutput {
        lengths: job.session.config().served(st.estimate()),
        frames_seen,
        lifted: None,
        state: due_state(job, &st, frames_seen),
    }))
}

/// The state copy a job asked for, if this frame makes it due.
fn due_state(job: &FrameJob, st: &SessionState, frames_seen: u64) -> Option<Box<StateCopy>> {
    (job.state_every > 0 && frames_seen.is_multiple_of(job.state_every))
        .then(|| Box::new(st.copy_state()))
}

/// Write one successful row back: the GRU state, the prediction, the
/// detected joints and, for a lifting frame, the frame into the lifter's
/// window, all under one lock.
fn scatter(job: &FrameJob, hidden: &[f32], lengths: &[f32], lifted: Option<Pose>) -> StepResult {
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
    if job.lift {
        let Some(window) = st.window.as_deref_mut() else {
            return Err(StepError::Lifter("the session has no lifter window".into()));
        };
        window.push(keypoints(&job.input));
    }
    st.hidden.copy_from_slice(hidden);
    st.held.remember(&job.input, &job.present);
    let mut prediction = [0.0f32; OUTPUT_DIM];
    prediction.copy_from_slice(lengths);
    // A height-normalized model's lengths, back at the camera's height.
    let scale = job
        .session
        .config()
        .camera
        .as_ref()
        .map_or(1.0, |camera| camera.length_scale);
    let estimate = add_prediction(&mut st.lengths, &prediction, scale);
    let frames_seen = st.frames_seen();
    let state = due_state(job, &st, frames_seen);
    Ok(StepOutput {
        lengths: job.session.config().served(Some(estimate)),
        frames_seen,
        lifted: if job.lift { lifted } else { None },
        state,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::session::{Coordinates, InputFormat, SessionConfig, SessionStore};
    use crate::testing::StepGate;
    use blapose_core::layouts::KeypointLayout;
    use std::sync::atomic::AtomicBool;

    /// A fake model: the new state is `h + x[0]` in every slot, the
    /// prediction is the new `h[0]` for every bone. So after frames with
    /// x[0] = a1, a2, ... a session's state is the running sum of its
    /// inputs, which reveals lost, duplicated, reordered or mixed-up frames.
    /// It also records batch sizes and the sessions (by first input slot 1)
    /// in each batch. With a [`StepGate`] every step waits until it opens,
    /// so a test controls what is queued while a step runs (no sleeps).
    #[derive(Clone, Default)]
    struct Fake {
        log: Log,
        gate: Option<Arc<StepGate>>,
        fail: Arc<AtomicBool>,
    }

    /// The fake's record: the tags of each step's rows.
    type Log = Arc<Mutex<Vec<Vec<f32>>>>;

    /// A fake whose steps wait at a gate that is closed once the batcher
    /// has warmed up (the warm-up step passes an open gate).
    fn gated_batcher(config: BatcherConfig) -> (Batcher, Arc<StepGate>, Log) {
        let gate = Arc::new(StepGate::new());
        gate.set_open(true);
        let fake = Fake {
            gate: Some(gate.clone()),
            ..Fake::default()
        };
        let log = fake.log.clone();
        let batcher = Batcher::start(fake, config).unwrap();
        gate.close_and_reset();
        (batcher, gate, log)
    }

    /// A bound on how long a test waits for an answer, far beyond any
    /// step: reaching it means the frame was never answered (a hang), not
    /// that something was slow.
    const HANG: Duration = Duration::from_secs(120);

    async fn answer(rx: oneshot::Receiver<StepResult>) -> StepResult {
        tokio::time::timeout(HANG, rx)
            .await
            .expect("the frame is answered")
            .expect("the batcher answers")
    }

    impl Backend for Fake {
        fn step(
            &mut self,
            inputs: &[f32],
            hidden: &mut [f32],
            out: &mut [f32],
            batch: usize,
        ) -> Result<(), BackendError> {
            crate::backend::check_step_shapes(inputs, hidden, out, batch)?;
            if self.fail.load(Ordering::Relaxed) {
                return Err(BackendError::Model("fake failure".into()));
            }
            // x[2] = 999 makes the whole call fail, as the real engine does
            // when one row goes non-finite.
            if let Some(gate) = &self.gate {
                gate.pass();
            }
            if inputs.chunks_exact(INPUT_DIM).any(|x| x[2] == 999.0) {
                return Err(BackendError::Model("row refused".into()));
            }
            let mut tags = Vec::new();
            for b in 0..batch {
                let x = &inputs[b * INPUT_DIM..(b + 1) * INPUT_DIM];
                tags.push(x[1]);
                let h = &mut hidden[b * STATE_DIM..(b + 1) * STATE_DIM];
                for v in h.iter_mut() {
                    *v += x[0];
                }
                // x[2] = NaN asks for a poisoned row.
                let p = if x[2].is_nan() { f32::NAN } else { h[0] };
                out[b * OUTPUT_DIM..(b + 1) * OUTPUT_DIM].fill(p);
            }
            self.log.lock().unwrap().push(tags);
            Ok(())
        }
    }

    fn config(max_batch: usize, delay_ms: u64, capacity: usize) -> BatcherConfig {
        BatcherConfig {
            max_batch,
            max_queue_delay: Duration::from_millis(delay_ms),
            queue_capacity: capacity,
        }
    }

    fn session_config() -> SessionConfig {
        SessionConfig {
            input: InputFormat {
                layout: KeypointLayout::H36m17,
                coordinates: Coordinates::Normalized,
            },
            label: String::new(),
            lifter_frames: None,
            camera: None,
            subject: None,
        }
    }

    fn job(
        session: &Arc<Session>,
        epoch: u64,
        value: f32,
        tag: f32,
    ) -> (FrameJob, oneshot::Receiver<StepResult>) {
        let (tx, rx) = oneshot::channel();
        let mut input = [0.0; INPUT_DIM];
        input[0] = value;
        input[1] = tag;
        (
            FrameJob {
                session: session.clone(),
                epoch,
                input,
                present: [true; NUM_JOINTS],
                lift: false,
                state_every: 0,
                reply: tx,
            },
            rx,
        )
    }

    #[tokio::test]
    async fn camera_sessions_run_rectified_on_the_camera_aware_model() {
        let (default, camera_aware) = (Fake::default(), Fake::default());
        let (default_log, aware_log) = (default.log.clone(), camera_aware.log.clone());
        let backends = OnlineBackends {
            default,
            camera_aware: Some(camera_aware),
        };
        let batcher = Batcher::start_with(backends, config(8, 50, 100), None).unwrap();
        let (store, _g) = SessionStore::new(10, Duration::from_secs(60));
        let level =
            blapose_core::level::LevelCamera::new([0.0, -0.95, -0.31], [2.3, 2.3], [0.0, 0.02])
                .unwrap();
        let plain = store.open(session_config()).unwrap();
        let aware = store
            .open(SessionConfig {
                camera: Some(crate::session::SessionCamera {
                    calibration: Default::default(),
                    level: level.clone(),
                    length_scale: 1.0,
                }),
                ..session_config()
            })
            .unwrap();
        let _guards = [batcher.stream_guard(), batcher.stream_guard()];
        let (j1, r1) = job(&plain.session, plain.epoch, 0.25, 0.5);
        let (j2, r2) = job(&aware.session, aware.epoch, 0.25, 0.5);
        batcher.submit(j1).unwrap();
        batcher.submit(j2).unwrap();
        let (a, b) = (r1.await.unwrap().unwrap(), r2.await.unwrap().unwrap());
        // What the camera-aware model must have been given.
        let mut rectified = [0.0f32; INPUT_DIM];
        (rectified[0], rectified[1]) = (0.25, 0.5);
        level.rectify_frames(&mut rectified);
        assert_ne!(rectified[..2], [0.25, 0.5]);
        // Each log starts with its model's warm-up step.
        assert_eq!(default_log.lock().unwrap()[1..], [vec![0.5]]);
        assert_eq!(aware_log.lock().unwrap()[1..], [vec![rectified[1]]]);
        assert_eq!(a.lengths.unwrap()[0], 0.25);
        assert_eq!(b.lengths.unwrap()[0], rectified[0]);
        batcher.close();
    }

    #[tokio::test]
    async fn frames_run_in_order_at_most_one_per_session_per_batch() {
        let fake = Fake::default();
        let log = fake.log.clone();
        // A delay no test waits out: a batch runs only once every attached
        // stream has a frame waiting.
        let batcher = Batcher::start(fake, config(8, 3_600_000, 1000)).unwrap();
        let (store, _g) = SessionStore::new(100, Duration::from_secs(60));
        let sessions: Vec<_> = (0..5)
            .map(|_| store.open(session_config()).unwrap())
            .collect();
        let _guards: Vec<_> = sessions.iter().map(|_| batcher.stream_guard()).collect();
        let mut rxs = Vec::new();
        // 20 pipelined frames per session, interleaved; values 1..=20.
        for f in 1..=20 {
            for (s, a) in sessions.iter().enumerate() {
                let (j, rx) = job(&a.session, a.epoch, f as f32, s as f32);
                batcher.submit(j).unwrap();
                rxs.push((s, f, rx));
            }
        }
        let mut expected_sum = [0.0f32; 5];
        for (s, f, rx) in rxs {
            let out = answer(rx).await.unwrap();
            expected_sum[s] += f as f32;
            // Running sum of inputs as state => in-order, exactly-once.
            assert_eq!(out.frames_seen, f as u64, "session {s}");
            let mean_of_running_sums: f32 =
                (1..=f).map(|k| (k * (k + 1) / 2) as f32).sum::<f32>() / f as f32;
            assert!(
                (out.lengths.unwrap()[0] - mean_of_running_sums).abs() < 1e-3,
                "session {s} frame {f}"
            );
        }
        for (s, a) in sessions.iter().enumerate() {
            assert_eq!(a.session.lock().hidden[5], expected_sum[s]);
        }
        let log = log.lock().unwrap();
        // The first entry is the warm-up step.
        let log = &log[1..];
        assert_eq!(log.iter().map(Vec::len).sum::<usize>(), 100);
        for tags in log.iter() {
            assert!(tags.len() <= 8);
            let mut sorted = tags.clone();
            sorted.sort_by(f32::total_cmp);
            sorted.dedup();
            assert_eq!(
                sorted.len(),
                tags.len(),
                "a session appears twice in batch {tags:?}"
            );
        }
        // Every stream always has a frame waiting until the last batch, so
        // every batch is full-width: one frame of each of the 5 sessions.
        assert!(log.iter().all(|t| t.len() == 5), "batches: {log:?}");
        assert_eq!(log.len(), 20);
    }

    #[tokio::test]
    async fn full_queue_refuses_instead_of_dropping() {
        let (batcher, gate, _) = gated_batcher(config(1, 0, 3));
        let (store, _g) = SessionStore::new(100, Duration::from_secs(60));
        let a = store.open(session_config()).unwrap();
        let mut accepted = Vec::new();
        let mut refused = 0;
        // The first frame's step holds at the gate: 3 more fill the queue.
        let (j, rx) = job(&a.session, a.epoch, 1.0, 0.0);
        batcher.submit(j).unwrap();
        accepted.push(rx);
        gate.wait_entered(1);
        for f in 1..10 {
            let (j, rx) = job(&a.session, a.epoch, 1.0, f as f32);
            match batcher.submit(j) {
                Ok(()) => accepted.push(rx),
                Err(e) => {
                    assert_eq!(e, SubmitError::QueueFull { capacity: 3 });
                    assert_eq!(e.code(), tonic::Code::ResourceExhausted);
                    refused += 1;
                }
            }
        }
        assert_eq!(refused, 6);
        gate.set_open(true);
        let n = accepted.len();
        // Every accepted frame is answered; the state counts exactly those.
        for (k, rx) in accepted.into_iter().enumerate() {
            assert_eq!(answer(rx).await.unwrap().frames_seen, k as u64 + 1);
        }
        assert_eq!(a.session.lock().frames_seen(), n as u64);
    }

    #[test]
    fn the_batching_rule() {
        let t0 = Instant::now();
        let ms = Duration::from_millis;
        let cfg = config(4, 200, 100);
        let at = |elapsed: u64| t0 + ms(elapsed);
        // A lone stream never waits, however long the delay.
        assert_eq!(gather(&cfg, 1, 1, false, t0, t0), Gather::Run);
        assert_eq!(gather(&cfg, 1, 0, false, t0, t0), Gather::Run);
        // Two streams, one frame: wait for the other up to the delay ...
        assert_eq!(
            gather(&cfg, 1, 2, false, t0, t0),
            Gather::WaitUntil(at(200))
        );
        assert_eq!(
            gather(&cfg, 1, 2, false, t0, at(199)),
            Gather::WaitUntil(at(200))
        );
        // ... and no longer.
        assert_eq!(gather(&cfg, 1, 2, false, t0, at(200)), Gather::Run);
        assert_eq!(gather(&cfg, 1, 2, false, t0, at(5000)), Gather::Run);
        // Every stream has a frame: go.
        assert_eq!(gather(&cfg, 2, 2, false, t0, at(1)), Gather::Run);
        // More streams than a batch holds: a full batch goes.
        assert_eq!(gather(&cfg, 4, 100, false, t0, at(1)), Gather::Run);
        assert_eq!(
            gather(&cfg, 3, 100, false, t0, at(1)),
            Gather::WaitUntil(at(200))
        );
        // Closing: the queue drains without waiting.
        assert_eq!(gather(&cfg, 1, 2, true, t0, t0), Gather::Run);
        // The deadline counts from the oldest frame, not from now.
        assert_eq!(
            gather(&cfg, 1, 2, false, at(150), at(300)),
            Gather::WaitUntil(at(350))
        );
    }

    #[tokio::test]
    async fn lone_stream_does_not_wait_for_the_queue_delay() {
        let fake = Fake::default();
        let log = fake.log.clone();
        // A delay no test waits out: the frames are answered only because
        // a lone stream does not wait for company.
        let batcher = Batcher::start(fake, config(64, 3_600_000, 100)).unwrap();
        let (store, _g) = SessionStore::new(10, Duration::from_secs(60));
        let a = store.open(session_config()).unwrap();
        let _guard = batcher.stream_guard();
        for f in 0..20 {
            let (j, rx) = job(&a.session, a.epoch, 1.0, f as f32);
            batcher.submit(j).unwrap();
            answer(rx).await.unwrap();
        }
        // Warm-up, then one batch per frame.
        assert_eq!(log.lock().unwrap().len(), 21);
    }

    #[tokio::test]
    async fn partial_batch_waits_for_other_streams_up_to_the_delay() {
        let fake = Fake::default();
        let log = fake.log.clone();
        // A delay no test waits out: a's frame can only run once b's frame
        // is there too, in the same batch.
        let batcher = Batcher::start(fake, config(64, 3_600_000, 100)).unwrap();
        let (store, _g) = SessionStore::new(10, Duration::from_secs(60));
        let a = store.open(session_config()).unwrap();
        let b = store.open(session_config()).unwrap();
        let _ga = batcher.stream_guard();
        let _gb = batcher.stream_guard();
        let (ja, ra) = job(&a.session, a.epoch, 1.0, 0.0);
        batcher.submit(ja).unwrap();
        let (jb, rb) = job(&b.session, b.epoch, 1.0, 1.0);
        batcher.submit(jb).unwrap();
        answer(ra).await.unwrap();
        answer(rb).await.unwrap();
        assert_eq!(log.lock().unwrap()[1..], [vec![0.0, 1.0]]);
        drop(batcher);

        // With only stream a's frame ever arriving, the delay ends the wait
        // (how long it waits is `the_batching_rule`'s business).
        let fake = Fake::default();
        let log = fake.log.clone();
        let batcher = Batcher::start(fake, config(64, 10, 100)).unwrap();
        let _ga = batcher.stream_guard();
        let _gb = batcher.stream_guard();
        let (ja, ra) = job(&a.session, a.epoch, 1.0, 0.0);
        batcher.submit(ja).unwrap();
        answer(ra).await.unwrap();
        assert_eq!(log.lock().unwrap()[1..], [vec![0.0]]);
    }

    #[tokio::test]
    async fn bad_rows_and_failed_steps_leave_sessions_untouched() {
        let fake = Fake::default();
        let fail = fake.fail.clone();
        let batcher = Batcher::start(fake, config(8, 0, 100)).unwrap();
        let (store, _g) = SessionStore::new(10, Duration::from_secs(60));
        let a = store.open(session_config()).unwrap();
        let b = store.open(session_config()).unwrap();
        let (j, rx) = job(&a.session, a.epoch, 2.0, 0.0);
        batcher.submit(j).unwrap();
        rx.await.unwrap().unwrap();
        // A poisoned row for a, next to a good row for b.
        let (mut ja, ra) = job(&a.session, a.epoch, 5.0, 0.0);
        ja.input[2] = f32::NAN;
        let (jb, rb) = job(&b.session, b.epoch, 3.0, 1.0);
        batcher.submit(ja).unwrap();
        batcher.submit(jb).unwrap();
        assert_eq!(ra.await.unwrap(), Err(StepError::NonFinite));
        assert_eq!(rb.await.unwrap().unwrap().frames_seen, 1);
        {
            let st = a.session.lock();
            assert_eq!(st.frames_seen(), 1);
            assert!(st.hidden.iter().all(|&v| v == 2.0));
        }
        // A failing backend answers INTERNAL and changes nothing.
        fail.store(true, Ordering::Relaxed);
        let (j, rx) = job(&a.session, a.epoch, 7.0, 0.0);
        batcher.submit(j).unwrap();
        let err = rx.await.unwrap().unwrap_err();
        assert!(matches!(err, StepError::Model(_)));
        assert_eq!(err.code(), tonic::Code::Internal);
        assert!(a.session.lock().hidden.iter().all(|&v| v == 2.0));
        fail.store(false, Ordering::Relaxed);
        let (j, rx) = job(&a.session, a.epoch, 1.0, 0.0);
        batcher.submit(j).unwrap();
        assert_eq!(rx.await.unwrap().unwrap().frames_seen, 2);
    }

    #[tokio::test]
    async fn a_row_that_fails_the_whole_step_fails_only_its_own_frame() {
        // The first frame's step holds at the gate while the next two are
        // queued, so they share the next batch.
        let (batcher, gate, log) = gated_batcher(config(8, 0, 100));
        let (store, _g) = SessionStore::new(10, Duration::from_secs(60));
        let a = store.open(session_config()).unwrap();
        let b = store.open(session_config()).unwrap();
        let c = store.open(session_config()).unwrap();
        let (jc, rc) = job(&c.session, c.epoch, 1.0, 2.0);
        batcher.submit(jc).unwrap();
        gate.wait_entered(1);
        let (mut ja, ra) = job(&a.session, a.epoch, 4.0, 0.0);
        ja.input[2] = 999.0;
        let (jb, rb) = job(&b.session, b.epoch, 3.0, 1.0);
        batcher.submit(ja).unwrap();
        batcher.submit(jb).unwrap();
        gate.set_open(true);
        answer(rc).await.unwrap();
        assert!(matches!(answer(ra).await, Err(StepError::Model(_))));
        let ob = answer(rb).await.unwrap();
        assert_eq!(ob.frames_seen, 1);
        assert_eq!(ob.lengths.unwrap()[0], 3.0);
        assert_eq!(a.session.lock().frames_seen(), 0);
        assert!(a.session.lock().hidden.iter().all(|&v| v == 0.0));
        // The retry ran b alone (a batch of one after the failed pair).
        assert_eq!(log.lock().unwrap().last().map(Vec::len), Some(1));
    }

    #[tokio::test]
    async fn frames_of_a_superseded_stream_are_refused() {
        let batcher = Batcher::start(Fake::default(), config(8, 0, 100)).unwrap();
        let (store, _g) = SessionStore::new(10, Duration::from_secs(60));
        let a = store.open(session_config()).unwrap();
        let resumed = store.resume(&a.session.id().to_string()).unwrap();
        let (j, rx) = job(&a.session, a.epoch, 1.0, 0.0);
        batcher.submit(j).unwrap();
        assert_eq!(rx.await.unwrap(), Err(StepError::Superseded));
        let (j, rx) = job(&resumed.session, resumed.epoch, 1.0, 0.0);
        batcher.submit(j).unwrap();
        assert_eq!(rx.await.unwrap().unwrap().frames_seen, 1);
    }

    #[tokio::test]
    async fn close_drains_every_queued_frame_then_refuses() {
        // The gate holds the first step, so frames are still queued when
        // the batcher closes.
        let (batcher, gate, _) = gated_batcher(config(2, 0, 100));
        let (store, _g) = SessionStore::new(10, Duration::from_secs(60));
        let a = store.open(session_config()).unwrap();
        let mut rxs = Vec::new();
        for f in 0..10 {
            let (j, rx) = job(&a.session, a.epoch, 1.0, f as f32);
            batcher.submit(j).unwrap();
            rxs.push(rx);
        }
        gate.wait_entered(1);
        assert!(batcher.queue_len() >= 9, "frames are still queued");
        batcher.close();
        let (j, _rx) = job(&a.session, a.epoch, 1.0, 0.0);
        assert_eq!(batcher.submit(j), Err(SubmitError::ShuttingDown));
        gate.set_open(true);
        tokio::task::spawn_blocking(move || batcher.join())
            .await
            .unwrap();
        for (k, rx) in rxs.into_iter().enumerate() {
            assert_eq!(rx.await.unwrap().unwrap().frames_seen, k as u64 + 1);
        }
    }

    fn test_lifter() -> Arc<LoadedLifter> {
        let arch = blapose_lifters::trained::VideoPoseArch {
            filter_width: 3,
            blocks: 1,
            channels: 16,
            dropout: 0.0,
            causal: true,
        };
        let bytes = blapose_lifters::trained::random_weights_file(arch, 11).unwrap();
        Arc::new(LoadedLifter {
            lifter: blapose_lifters::TrainedLifter::from_bytes(&bytes).unwrap(),
            origin: "test".into(),
            sha256: String::new(),
        })
    }

    fn lifting_config(frames: usize) -> SessionConfig {
        SessionConfig {
            lifter_frames: Some(frames),
            camera: None,
            ..session_config()
        }
    }

    /// A lifting frame: keypoints that vary with `t`, `tag` in x[1].
    fn lift_job(
        session: &Arc<Session>,
        epoch: u64,
        t: usize,
        tag: f32,
    ) -> (FrameJob, oneshot::Receiver<StepResult>) {
        let (mut j, rx) = job(session, epoch, 1.0, tag);
        for (k, v) in j.input.iter_mut().enumerate().skip(2) {
            *v = (0.3 * t as f32 + 0.7 * k as f32).sin() * 0.5;
        }
        j.lift = true;
        (j, rx)
    }

    fn window_len(session: &Session) -> usize {
        session.lock().window.as_deref().map_or(0, |w| w.len())
    }

    #[tokio::test]
    async fn lifted_frames_enter_the_window_only_when_the_whole_frame_succeeds() {
        let fake = Fake::default();
        let fail = fake.fail.clone();
        let lifter = test_lifter();
        let batcher =
            Batcher::start_with_lifter(fake, config(8, 0, 100), Some(lifter.clone())).unwrap();
        let (store, _g) = SessionStore::new(10, Duration::from_secs(60));
        let a = store.open(lifting_config(9)).unwrap();
        // The library path: the same frames through a window of our own.
        let mut mine = lifter.lifter.window();

        let (j, rx) = lift_job(&a.session, a.epoch, 0, 0.0);
        let frame0 = keypoints(&j.input);
        batcher.submit(j).unwrap();
        let out = rx.await.unwrap().unwrap();
        mine.push(frame0);
        assert_eq!(out.lifted, Some(lifter.lifter.lift(&mut mine).unwrap()));
        assert_eq!(out.lifted.unwrap()[0], [0.0; 3]);
        assert_eq!((out.frames_seen, window_len(&a.session)), (1, 1));

        // The GRU step fails: lifted fine, but nothing is kept.
        fail.store(true, Ordering::Relaxed);
        let (j, rx) = lift_job(&a.session, a.epoch, 50, 0.0);
        batcher.submit(j).unwrap();
        assert!(matches!(rx.await.unwrap(), Err(StepError::Model(_))));
        fail.store(false, Ordering::Relaxed);
        assert_eq!(window_len(&a.session), 1);

        // A taken-over stream's lifting frame: refused before the lifter.
        let resumed = store.resume(&a.session.id().to_string()).unwrap();
        let (j, rx) = lift_job(&a.session, a.epoch, 51, 0.0);
        batcher.submit(j).unwrap();
        assert_eq!(rx.await.unwrap(), Err(StepError::Superseded));
        assert_eq!(window_len(&a.session), 1);

        // A pose that cannot be adjusted (here: out of bounds): refused.
        let (mut j, rx) = lift_job(&a.session, resumed.epoch, 52, 0.0);
        j.input[2..].fill(1e6);
        batcher.submit(j).unwrap();
        let err = rx.await.unwrap().unwrap_err();
        assert!(matches!(err, StepError::LiftedPose(_)), "{err}");
        assert_eq!(err.code(), tonic::Code::Internal);
        assert_eq!(window_len(&a.session), 1);

        // The next good frame continues from frame 0 alone.
        let (j, rx) = lift_job(&a.session, resumed.epoch, 1, 0.0);
        let frame1 = keypoints(&j.input);
        batcher.submit(j).unwrap();
        let out = rx.await.unwrap().unwrap();
        mine.push(frame1);
        assert_eq!(out.lifted, Some(lifter.lifter.lift(&mut mine).unwrap()));
        assert_eq!((out.frames_seen, window_len(&a.session)), (2, 2));
    }

    #[tokio::test]
    async fn lifting_and_client_pose_frames_share_a_batch() {
        let fake = Fake::default();
        let log = fake.log.clone();
        let lifter = test_lifter();
        let batcher =
            Batcher::start_with_lifter(fake, config(8, 500, 100), Some(lifter.clone())).unwrap();
        let (store, _g) = SessionStore::new(10, Duration::from_secs(60));
        let a = store.open(lifting_config(9)).unwrap();
        let b = store.open(lifting_config(9)).unwrap();
        let c = store.open(session_config()).unwrap();
        let _guards: Vec<_> = (0..3).map(|_| batcher.stream_guard()).collect();
        let (ja, ra) = lift_job(&a.session, a.epoch, 3, 0.0);
        let (jb, rb) = lift_job(&b.session, b.epoch, 8, 1.0);
        let (jc, rc) = job(&c.session, c.epoch, 1.0, 2.0);
        let (fa, fb) = (keypoints(&ja.input), keypoints(&jb.input));
        for j in [ja, jb, jc] {
            batcher.submit(j).unwrap();
        }
        let (oa, ob, oc) = (
            ra.await.unwrap().unwrap(),
            rb.await.unwrap().unwrap(),
            rc.await.unwrap().unwrap(),
        );
        assert_eq!(
            log.lock().unwrap().last().map(Vec::len),
            Some(3),
            "one batch"
        );
        for (out, frame) in [(oa, fa), (ob, fb)] {
            let mut w = lifter.lifter.window();
            w.push(frame);
            let want = lifter.lifter.lift(&mut w).unwrap();
            let got = out.lifted.expect("lifted");
            for (u, v) in got.iter().flatten().zip(want.iter().flatten()) {
                assert!((u - v).abs() < 1e-5, "{u} vs {v}");
            }
        }
        assert_eq!(oc.lifted, None, "a client pose is not lifted");
        assert!(c.session.lock().window.is_none());
    }

    #[tokio::test]
    async fn a_batcher_without_a_lifter_refuses_lifting_frames() {
        let batcher = Batcher::start(Fake::default(), config(8, 0, 100)).unwrap();
        let (store, _g) = SessionStore::new(10, Duration::from_secs(60));
        let a = store.open(lifting_config(9)).unwrap();
        let (j, rx) = lift_job(&a.session, a.epoch, 0, 0.0);
        batcher.submit(j).unwrap();
        assert!(matches!(rx.await.unwrap(), Err(StepError::Lifter(_))));
        assert_eq!(a.session.lock().frames_seen(), 0);
    }

    #[test]
    fn panics_in_the_lifter_become_errors() {
        let r: Result<(), String> = guarded(|| panic!("boom"));
        assert_eq!(r, Err("panicked: boom".to_string()));
        let r: Result<u8, String> = guarded(|| Ok(3));
        assert_eq!(r, Ok(3));
    }

    #[test]
    fn warm_up_rejects_a_model_that_produces_nan() {
        struct Nan;
        impl Backend for Nan {
            fn step(
                &mut self,
                _: &[f32],
                h: &mut [f32],
                _: &mut [f32],
                _: usize,
            ) -> Result<(), BackendError> {
                h[0] = f32::NAN;
                Ok(())
            }
        }
        assert!(Batcher::start(Nan, config(4, 0, 4)).is_err());
    }
}

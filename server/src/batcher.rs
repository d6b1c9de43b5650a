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

use std::collections::{HashMap, VecDeque};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard, PoisonError};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use blapose_core::BoneLengths;
use tokio::sync::oneshot;

use crate::backend::{Backend, BackendError, INPUT_DIM, OUTPUT_DIM, STATE_DIM};
use crate::metrics;
use crate::session::Session;

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
    /// Normalized Human3.6M-17 keypoints, joint-major (x, y).
    pub input: [f32; INPUT_DIM],
    /// Where the answer goes.
    pub reply: oneshot::Sender<StepResult>,
}

/// A processed frame.
#[derive(Debug, Clone, PartialEq)]
pub struct StepOutput {
    /// The session's running-mean estimate after this frame.
    pub lengths: BoneLengths,
    /// Frames processed in the session, this one included.
    pub frames_seen: u64,
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
}

impl StepError {
    /// The gRPC code this error is reported with.
    pub fn code(&self) -> tonic::Code {
        match self {
            StepError::Superseded => tonic::Code::Aborted,
            StepError::Model(_) | StepError::NonFinite => tonic::Code::Internal,
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

#[derive(Debug)]
struct Shared {
    queue: Mutex<Queue>,
    available: Condvar,
    config: BatcherConfig,
    active_streams: AtomicUsize,
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

impl Batcher {
    /// Warm the backend up and start the batcher thread.
    pub fn start<B: Backend>(mut backend: B, config: BatcherConfig) -> Result<Self, BackendError> {
        let config = BatcherConfig {
            max_batch: config.max_batch.max(1),
            queue_capacity: config.queue_capacity.max(1),
            ..config
        };
        warm_up(&mut backend)?;
        let shared = Arc::new(Shared {
            queue: Mutex::new(Queue::default()),
            available: Condvar::new(),
            config,
            active_streams: AtomicUsize::new(0),
        });
        let worker = shared.clone();
        let thread = std::thread::Builder::new()
            .name("blapose-batcher".into())
            .spawn(move || run(worker, backend))
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

/// Preallocated step buffers (no allocation per batch).
struct Buffers {
    inputs: Vec<f32>,
    hidden: Vec<f32>,
    lengths: Vec<f32>,
    /// For each buffer row, its index in the batch.
    rows: Vec<usize>,
}

fn run<B: Backend>(shared: Arc<Shared>, mut backend: B) {
    let max = shared.config.max_batch;
    let mut buffers = Buffers {
        inputs: vec![0.0; max * INPUT_DIM],
        hidden: vec![0.0; max * STATE_DIM],
        lengths: vec![0.0; max * OUTPUT_DIM],
        rows: Vec::with_capacity(max),
    };
    let mut batch: Vec<Queued> = Vec::with_capacity(max);
    while next_batch(&shared, &mut batch) {
        run_batch(&mut backend, &mut batch, &mut buffers, &shared);
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
        let deadline = oldest + config.max_queue_delay;
        loop {
            let streams = shared.active_streams.load(Ordering::Relaxed).max(1);
            let target = config.max_batch.min(streams);
            if q.closed || q.ready.len() >= target {
                break;
            }
            let now = Instant::now();
            if now >= deadline {
                break;
            }
            q = shared
                .available
                .wait_timeout(q, deadline - now)
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
    backend: &mut B,
    batch: &mut Vec<Queued>,
    buf: &mut Buffers,
    shared: &Shared,
) {
    let started = Instant::now();
    buf.rows.clear();
    let mut answers: Vec<Option<StepResult>> = Vec::with_capacity(batch.len());
    // Gather the states of sessions still owned by the frame's stream.
    for (i, item) in batch.iter().enumerate() {
        metrics::queue_wait(started.saturating_duration_since(item.enqueued));
        let st = item.job.session.lock();
        if !st.accepts(item.job.epoch) {
            answers.push(Some(Err(StepError::Superseded)));
            continue;
        }
        let r = buf.rows.len();
        buf.hidden[r * STATE_DIM..(r + 1) * STATE_DIM].copy_from_slice(&st.hidden);
        drop(st);
        buf.inputs[r * INPUT_DIM..(r + 1) * INPUT_DIM].copy_from_slice(&item.job.input);
        buf.rows.push(i);
        answers.push(None);
    }
    let n = buf.rows.len();
    if n > 0 {
        let result = backend.step(
            &buf.inputs[..n * INPUT_DIM],
            &mut buf.hidden[..n * STATE_DIM],
            &mut buf.lengths[..n * OUTPUT_DIM],
            n,
        );
        match result {
            // Scatter: only finite rows of sessions whose owner is unchanged.
            Ok(()) => {
                for (r, &i) in buf.rows.iter().enumerate() {
                    let hidden = &buf.hidden[r * STATE_DIM..(r + 1) * STATE_DIM];
                    let lengths = &buf.lengths[r * OUTPUT_DIM..(r + 1) * OUTPUT_DIM];
                    answers[i] = Some(scatter(&batch[i].job, hidden, lengths));
                }
            }
            // The engine refuses a whole batch for one bad row; isolate it by
            // re-running the rows one at a time, so one session's problem
            // never fails another session's frame.
            Err(e) if n > 1 => {
                tracing::warn!(error = %e, batch = n, "batched step failed; retrying its rows one by one");
                for (r, &i) in buf.rows.iter().enumerate() {
                    let input = &buf.inputs[r * INPUT_DIM..(r + 1) * INPUT_DIM];
                    answers[i] = Some(step_alone(backend, &batch[i].job, input));
                }
            }
            Err(e) => {
                for &i in &buf.rows {
                    answers[i] = Some(Err(StepError::Model(e.to_string())));
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

/// Run one frame on its own (state re-read from the session, since a failed
/// step may have touched the gathered buffer).
fn step_alone<B: Backend>(backend: &mut B, job: &FrameJob, input: &[f32]) -> StepResult {
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
        Ok(()) => scatter(job, &hidden, &lengths),
        Err(e) => Err(StepError::Model(e.to_string())),
    }
}

fn scatter(job: &FrameJob, hidden: &[f32], lengths: &[f32]) -> StepResult {
    if !hidden.iter().chain(lengths).all(|v| v.is_finite()) {
        return Err(StepError::NonFinite);
    }
    let mut st = job.session.lock();
    if !st.accepts(job.epoch) {
        return Err(StepError::Superseded);
    }
    st.hidden.copy_from_slice(hidden);
    let mut prediction = [0.0f32; OUTPUT_DIM];
    prediction.copy_from_slice(lengths);
    st.lengths.add(&prediction);
    Ok(StepOutput {
        lengths: st.estimate().unwrap_or(prediction),
        frames_seen: st.frames_seen(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::session::{Coordinates, InputSpec, SessionConfig, SessionStore};
    use blapose_core::layouts::KeypointLayout;
    use std::sync::atomic::AtomicBool;

    /// A fake model: the new state is `h + x[0]` in every slot, the
    /// prediction is the new `h[0]` for every bone. So after frames with
    /// x[0] = a1, a2, ... a session's state is the running sum of its
    /// inputs, which reveals lost, duplicated, reordered or mixed-up frames.
    /// It also records batch sizes and the sessions (by first input slot 1)
    /// in each batch.
    #[derive(Clone, Default)]
    struct Fake {
        log: Arc<Mutex<Vec<Vec<f32>>>>,
        delay: Duration,
        fail: Arc<AtomicBool>,
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
            if inputs.chunks_exact(INPUT_DIM).any(|x| x[2] == 999.0) {
                return Err(BackendError::Model("row refused".into()));
            }
            std::thread::sleep(self.delay);
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
            input: InputSpec {
                layout: KeypointLayout::H36m17,
                coordinates: Coordinates::Normalized,
            },
            label: String::new(),
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
                reply: tx,
            },
            rx,
        )
    }

    #[tokio::test]
    async fn frames_run_in_order_at_most_one_per_session_per_batch() {
        let fake = Fake {
            delay: Duration::from_millis(1),
            ..Fake::default()
        };
        let log = fake.log.clone();
        let batcher = Batcher::start(fake, config(8, 2, 1000)).unwrap();
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
            let out = rx.await.unwrap().unwrap();
            expected_sum[s] += f as f32;
            // Running sum of inputs as state => in-order, exactly-once.
            assert_eq!(out.frames_seen, f as u64, "session {s}");
            let mean_of_running_sums: f32 =
                (1..=f).map(|k| (k * (k + 1) / 2) as f32).sum::<f32>() / f as f32;
            assert!(
                (out.lengths[0] - mean_of_running_sums).abs() < 1e-3,
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
        // With 5 pipelined sessions, batches are mostly full-width.
        assert!(
            log.iter().filter(|t| t.len() == 5).count() >= 15,
            "batches: {log:?}"
        );
    }

    #[tokio::test]
    async fn full_queue_refuses_instead_of_dropping() {
        let fake = Fake {
            delay: Duration::from_millis(50),
            ..Fake::default()
        };
        let batcher = Batcher::start(fake, config(1, 0, 3)).unwrap();
        let (store, _g) = SessionStore::new(100, Duration::from_secs(60));
        let a = store.open(session_config()).unwrap();
        let mut accepted = Vec::new();
        let mut refused = 0;
        for f in 0..10 {
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
        assert!(refused >= 6, "only {refused} refused");
        let n = accepted.len();
        // Every accepted frame is answered; the state counts exactly those.
        for (k, rx) in accepted.into_iter().enumerate() {
            assert_eq!(rx.await.unwrap().unwrap().frames_seen, k as u64 + 1);
        }
        assert_eq!(a.session.lock().frames_seen(), n as u64);
    }

    #[tokio::test]
    async fn lone_stream_does_not_wait_for_the_queue_delay() {
        let batcher = Batcher::start(Fake::default(), config(64, 500, 100)).unwrap();
        let (store, _g) = SessionStore::new(10, Duration::from_secs(60));
        let a = store.open(session_config()).unwrap();
        let _guard = batcher.stream_guard();
        let t = std::time::Instant::now();
        for f in 0..20 {
            let (j, rx) = job(&a.session, a.epoch, 1.0, f as f32);
            batcher.submit(j).unwrap();
            rx.await.unwrap().unwrap();
        }
        // 20 sequential frames with a 500 ms max delay: far under 20 x 500 ms.
        assert!(
            t.elapsed() < Duration::from_millis(400),
            "{:?}",
            t.elapsed()
        );
    }

    #[tokio::test]
    async fn partial_batch_waits_for_other_streams_up_to_the_delay() {
        let fake = Fake::default();
        let log = fake.log.clone();
        let batcher = Batcher::start(fake, config(64, 200, 100)).unwrap();
        let (store, _g) = SessionStore::new(10, Duration::from_secs(60));
        let a = store.open(session_config()).unwrap();
        let b = store.open(session_config()).unwrap();
        let _ga = batcher.stream_guard();
        let _gb = batcher.stream_guard();
        let (ja, ra) = job(&a.session, a.epoch, 1.0, 0.0);
        batcher.submit(ja).unwrap();
        tokio::time::sleep(Duration::from_millis(20)).await;
        let (jb, rb) = job(&b.session, b.epoch, 1.0, 1.0);
        batcher.submit(jb).unwrap();
        ra.await.unwrap().unwrap();
        rb.await.unwrap().unwrap();
        // Both in one batch: the first frame waited for the second stream.
        assert_eq!(log.lock().unwrap().last().map(Vec::len), Some(2));
        // With only stream a's frame ever arriving, the delay bounds the wait.
        let t = std::time::Instant::now();
        let (ja, ra) = job(&a.session, a.epoch, 1.0, 0.0);
        batcher.submit(ja).unwrap();
        ra.await.unwrap().unwrap();
        let waited = t.elapsed();
        assert!(
            waited >= Duration::from_millis(190) && waited < Duration::from_secs(2),
            "{waited:?}"
        );
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
        // A long delay on the first frame makes the next two share a batch.
        let fake = Fake {
            delay: Duration::from_millis(30),
            ..Fake::default()
        };
        let log = fake.log.clone();
        let batcher = Batcher::start(fake, config(8, 0, 100)).unwrap();
        let (store, _g) = SessionStore::new(10, Duration::from_secs(60));
        let a = store.open(session_config()).unwrap();
        let b = store.open(session_config()).unwrap();
        let c = store.open(session_config()).unwrap();
        let (jc, rc) = job(&c.session, c.epoch, 1.0, 2.0);
        batcher.submit(jc).unwrap();
        tokio::time::sleep(Duration::from_millis(5)).await;
        let (mut ja, ra) = job(&a.session, a.epoch, 4.0, 0.0);
        ja.input[2] = 999.0;
        let (jb, rb) = job(&b.session, b.epoch, 3.0, 1.0);
        batcher.submit(ja).unwrap();
        batcher.submit(jb).unwrap();
        rc.await.unwrap().unwrap();
        assert!(matches!(ra.await.unwrap(), Err(StepError::Model(_))));
        let ob = rb.await.unwrap().unwrap();
        assert_eq!(ob.frames_seen, 1);
        assert_eq!(ob.lengths[0], 3.0);
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
        let fake = Fake {
            delay: Duration::from_millis(5),
            ..Fake::default()
        };
        let batcher = Batcher::start(fake, config(2, 0, 100)).unwrap();
        let (store, _g) = SessionStore::new(10, Duration::from_secs(60));
        let a = store.open(session_config()).unwrap();
        let mut rxs = Vec::new();
        for f in 0..10 {
            let (j, rx) = job(&a.session, a.epoch, 1.0, f as f32);
            batcher.submit(j).unwrap();
            rxs.push(rx);
        }
        batcher.close();
        let (j, _rx) = job(&a.session, a.epoch, 1.0, 0.0);
        assert_eq!(batcher.submit(j), Err(SubmitError::ShuttingDown));
        tokio::task::spawn_blocking(move || batcher.join())
            .await
            .unwrap();
        for (k, rx) in rxs.into_iter().enumerate() {
            assert_eq!(rx.await.unwrap().unwrap().frames_seen, k as u64 + 1);
        }
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

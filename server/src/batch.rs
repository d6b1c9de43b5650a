//! The batch stage: one bounded queue of frames from every session, and the
//! rule that turns it into batches (Triton's "oldest" sequence batching).
//!
//! A GRU step costs almost the same for 1 session as for 32 (the weights are
//! read once either way), so frames from all streams wait in one queue and
//! one thread runs them together. This module is only that queue and its
//! rule; what a batch goes through once taken is the other stages'
//! ([`crate::prepare`] -> [`crate::step`] -> [`crate::answer`]), which the
//! batcher thread ([`crate::pipeline`], the worker given to
//! [`Batcher::start`]) runs in that order. The rules:
//!
//! * **At most one frame per session per batch**: a session's next frame
//!   needs the hidden state (and the held joints and lifter window) its
//!   previous frame leaves, so a session's frames run one batch after
//!   another, in the order they were submitted.
//! * **Clients in turn**: a batch takes one session of each client with a
//!   frame waiting, then one more of each, and so on ([`Turns`]); within a
//!   client, sessions in the order of their oldest waiting frame, and a
//!   session with more frames waiting goes to the back. So a client holding
//!   many sessions delays another client's frame by one batch at most:
//!   when batches were taken oldest first across all sessions, 8 addresses
//!   with 25 slow-reading sessions each queued enough frames to raise a
//!   new client's p99 from under a millisecond to 23-44 ms
//!   (`tests/abuse/`, `shares8`).
//! * **Short steps between clients**: while frames of more than one client
//!   wait, a batch takes at most `max_mixed_batch` (default 16) instead of
//!   `max_batch` (64), so that the batch in progress, which a newly arrived
//!   frame waits for, is short; one client alone (a load test, a single
//!   integration) still gets full batches. On the 2-core EPYC a step costs
//!   about 50 us a frame whatever its size, so 16 lose no frames/s; beside
//!   8 saturating clients a new client's p50 went from 6.4 to 1.7 ms.
//! * **Bounded wait**: a partial batch runs as soon as every attached stream
//!   has a frame waiting (nobody else can contribute), or when the oldest
//!   frame has waited `max_queue_delay`, whichever comes first. A lone
//!   pipelined stream therefore never waits for company.
//! * **Explicit backpressure**: a full queue refuses the frame
//!   ([`SubmitError::QueueFull`] -> RESOURCE_EXHAUSTED); nothing is dropped
//!   silently. Every accepted frame is answered exactly once through its
//!   oneshot ([`StepResult`](crate::frame::StepResult)), including at
//!   shutdown (the queue is drained first).
//! * **Off the async runtime**: the worker is the batcher's own OS thread,
//!   never a tokio worker.
//!
//! What waits here is a validated frame ([`FrameJob`]): its keypoints in
//! normalized screen coordinates, as the client's frame was checked. The
//! rest of its preparation (missing joints held at their last detection,
//! the server lifter's pose, the camera the model reads it through) reads
//! the state its session's *previous* frame leaves, which is only known
//! once that frame has been through its step, so [`crate::prepare`] does
//! it when its batch is taken.

use std::collections::{HashMap, VecDeque};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard, PoisonError};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use crate::frame::FrameJob;
use crate::quota::{ClientId, QuotaError};

/// Batching limits.
#[derive(Debug, Clone, Copy)]
pub struct BatcherConfig {
    /// Most frames per step (>= 1).
    pub max_batch: usize,
    /// Most frames per step while frames of more than one client wait
    /// (>= 1, at most `max_batch`): the batch in progress is what another
    /// client's frame waits for.
    pub max_mixed_batch: usize,
    /// Longest wait for more sessions before running a partial batch.
    pub max_queue_delay: Duration,
    /// Most frames waiting at once, all sessions together (>= 1).
    pub queue_capacity: usize,
}

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
    /// A per-session or per-client share of the queue is full.
    #[error(transparent)]
    Quota(#[from] QuotaError),
}

impl SubmitError {
    /// The gRPC code this error is reported with.
    pub fn code(&self) -> tonic::Code {
        match self {
            SubmitError::QueueFull { .. } | SubmitError::Quota(_) => tonic::Code::ResourceExhausted,
            SubmitError::ShuttingDown => tonic::Code::Unavailable,
        }
    }
}

/// A frame in the queue, and when it entered it.
#[derive(Debug)]
pub struct Queued {
    /// The frame.
    pub job: FrameJob,
    /// When it was submitted.
    pub enqueued: Instant,
}

/// Sessions with a frame waiting, by client, and whose turn is next: each
/// session once; clients take turns, one session a turn.
#[derive(Debug, Default)]
struct Turns {
    /// Clients with a session waiting, the next to take a turn first.
    clients: VecDeque<ClientId>,
    /// Each such client's waiting sessions, oldest first.
    sessions: HashMap<ClientId, VecDeque<u64>>,
    /// Sessions waiting, all clients together.
    len: usize,
}

impl Turns {
    /// `key` of `client` now has a frame waiting (it must not be here yet).
    fn push(&mut self, client: ClientId, key: u64) {
        let sessions = self.sessions.entry(client).or_default();
        if sessions.is_empty() {
            self.clients.push_back(client);
        }
        sessions.push_back(key);
        self.len += 1;
    }

    /// The next client's oldest waiting session, removed; that client goes
    /// to the back of the turns if it has more.
    fn pop(&mut self) -> Option<(ClientId, u64)> {
        while let Some(client) = self.clients.pop_front() {
            let Some(sessions) = self.sessions.get_mut(&client) else {
                continue;
            };
            let Some(key) = sessions.pop_front() else {
                self.sessions.remove(&client);
                continue;
            };
            if sessions.is_empty() {
                self.sessions.remove(&client);
            } else {
                self.clients.push_back(client);
            }
            self.len -= 1;
            return Some((client, key));
        }
        None
    }

    /// Clients with a session waiting.
    fn clients(&self) -> usize {
        self.sessions.len()
    }

    /// The first waiting session of each client (the oldest frames).
    fn fronts(&self) -> impl Iterator<Item = u64> + '_ {
        self.sessions.values().filter_map(|s| s.front().copied())
    }
}

#[derive(Debug, Default)]
struct Queue {
    /// Waiting frames per session key, in submission order.
    per_session: HashMap<u64, VecDeque<Queued>>,
    /// Sessions with waiting frames, by client, in turn.
    ready: Turns,
    /// Total waiting frames.
    len: usize,
    /// Waiting frames per client (entries removed at zero).
    per_client: HashMap<ClientId, usize>,
    closed: bool,
}

impl Queue {
    fn oldest(&self) -> Option<Instant> {
        self.ready
            .fronts()
            .filter_map(|key| self.per_session.get(&key)?.front())
            .map(|q| q.enqueued)
            .min()
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

/// The worker thread's side of the queue: it takes batches from here.
#[derive(Debug)]
pub struct Batches {
    shared: Arc<Shared>,
}

impl Batches {
    /// The limits in force.
    pub fn config(&self) -> BatcherConfig {
        self.shared.config
    }

    /// Frames waiting now.
    pub fn queue_len(&self) -> usize {
        self.shared.lock().len
    }

    /// Wait for frames and take the next batch into `batch` (empty on
    /// entry); `false` once the queue is closed and empty.
    pub fn next(&self, batch: &mut Vec<Queued>) -> bool {
        next_batch(&self.shared, batch)
    }
}

impl Batcher {
    /// Start the thread that drains the queue: `worker` takes batches from
    /// its [`Batches`] until [`Batches::next`] says the queue is closed and
    /// empty, and must answer every frame it takes.
    pub fn start(
        config: BatcherConfig,
        worker: impl FnOnce(Batches) + Send + 'static,
    ) -> std::io::Result<Self> {
        let max_batch = config.max_batch.max(1);
        let config = BatcherConfig {
            max_batch,
            max_mixed_batch: config.max_mixed_batch.clamp(1, max_batch),
            queue_capacity: config.queue_capacity.max(1),
            ..config
        };
        let shared = Arc::new(Shared {
            queue: Mutex::new(Queue::default()),
            available: Condvar::new(),
            config,
            active_streams: AtomicUsize::new(0),
        });
        let batches = Batches {
            shared: shared.clone(),
        };
        let thread = std::thread::Builder::new()
            .name("blapose-batcher".into())
            .spawn(move || worker(batches))?;
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
        self.submit_limited(job, usize::MAX, usize::MAX)
    }

    /// [`submit`](Self::submit), refusing the frame when its session has
    /// `per_session` frames waiting or its client `per_client`: one
    /// client's overload is refused to that client while the queue still
    /// has room for the others.
    pub fn submit_limited(
        &self,
        job: FrameJob,
        per_session: usize,
        per_client: usize,
    ) -> Result<(), SubmitError> {
        let mut q = self.shared.lock();
        if q.closed {
            return Err(SubmitError::ShuttingDown);
        }
        let key = job.session.key();
        let client = job.session.client();
        let session_frames = q.per_session.get(&key).map_or(0, VecDeque::len);
        if session_frames >= per_session {
            crate::metrics::limited("frames_per_session");
            return Err(QuotaError::SessionFrames { limit: per_session }.into());
        }
        let capacity = self.shared.config.queue_capacity;
        if q.len >= capacity {
            crate::metrics::limited("queue_capacity");
            return Err(SubmitError::QueueFull { capacity });
        }
        let held = q.per_client.get(&client).copied().unwrap_or(0);
        let holders = q.per_client.len();
        if let Err(limit) = crate::quota::admit(per_client, capacity, q.len, holders, held) {
            crate::metrics::limited("queued_frames_per_client");
            return Err(QuotaError::ClientFrames { limit }.into());
        }
        *q.per_client.entry(client).or_default() += 1;
        let frames = q.per_session.entry(key).or_default();
        let first = frames.is_empty();
        frames.push_back(Queued {
            job,
            enqueued: Instant::now(),
        });
        if first {
            q.ready.push(client, key);
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
    cap: usize,
    ready: usize,
    streams: usize,
    closed: bool,
    oldest: Instant,
    now: Instant,
) -> Gather {
    let target = cap.min(streams.max(1));
    let deadline = oldest + config.max_queue_delay;
    if closed || ready >= target || now >= deadline {
        Gather::Run
    } else {
        Gather::WaitUntil(deadline)
    }
}

/// The most frames the next batch may take, with `clients` clients'
/// frames waiting: `max_batch` for one, `max_mixed_batch` for more.
fn batch_cap(config: &BatcherConfig, clients: usize) -> usize {
    if clients > 1 {
        config.max_mixed_batch
    } else {
        config.max_batch
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
            let cap = batch_cap(&config, q.ready.clients());
            let wait = match gather(&config, cap, q.ready.len, streams, q.closed, oldest, now) {
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
    // A session runs once a batch: those with more frames rejoin their
    // client's sessions after it is taken.
    let mut more = Vec::new();
    let cap = batch_cap(&config, q.ready.clients());
    while batch.len() < cap {
        let Some((client, key)) = q.ready.pop() else {
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
            more.push((client, key));
        }
        if let Some(n) = q.per_client.get_mut(&client) {
            *n = n.saturating_sub(1);
            if *n == 0 {
                q.per_client.remove(&client);
            }
        }
        batch.push(item);
    }
    for (client, key) in more {
        q.ready.push(client, key);
    }
    q.len -= batch.len();
    true
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn clients_take_turns_and_each_keeps_its_sessions_in_order() {
        let (a, b) = (ClientId::of("a"), ClientId::of("b"));
        let mut turns = Turns::default();
        // Client a has five sessions waiting before b's one arrives.
        for key in 1..=5 {
            turns.push(a, key);
        }
        turns.push(b, 100);
        assert_eq!(turns.len, 6);
        let order: Vec<u64> = std::iter::from_fn(|| turns.pop().map(|(_, k)| k)).collect();
        assert_eq!(
            order,
            [1, 100, 2, 3, 4, 5],
            "b waits for one of a's sessions, not five"
        );
        assert_eq!(
            (turns.len, turns.clients.len(), turns.sessions.len()),
            (0, 0, 0)
        );
        assert_eq!(turns.pop(), None);
    }

    #[test]
    fn steps_are_short_while_clients_share_the_queue() {
        let cfg = BatcherConfig {
            max_batch: 64,
            max_mixed_batch: 16,
            max_queue_delay: Duration::from_millis(200),
            queue_capacity: 100,
        };
        assert_eq!(batch_cap(&cfg, 0), 64);
        assert_eq!(batch_cap(&cfg, 1), 64, "one client alone: full batches");
        assert_eq!(batch_cap(&cfg, 2), 16);
        let t0 = Instant::now();
        // 16 sessions ready of 100 streams: two clients' run at once, one
        // client's wait for a fuller batch.
        assert_eq!(gather(&cfg, 16, 16, 100, false, t0, t0), Gather::Run);
        assert!(matches!(
            gather(&cfg, 64, 16, 100, false, t0, t0),
            Gather::WaitUntil(_)
        ));
    }

    #[test]
    fn the_batching_rule() {
        let t0 = Instant::now();
        let ms = Duration::from_millis;
        let cfg = BatcherConfig {
            max_batch: 4,
            max_mixed_batch: 4,
            max_queue_delay: ms(200),
            queue_capacity: 100,
        };
        let at = |elapsed: u64| t0 + ms(elapsed);
        let full = |ready, streams, closed, oldest, now| {
            gather(&cfg, cfg.max_batch, ready, streams, closed, oldest, now)
        };
        // A lone stream never waits, however long the delay.
        assert_eq!(full(1, 1, false, t0, t0), Gather::Run);
        assert_eq!(full(1, 0, false, t0, t0), Gather::Run);
        // Two streams, one frame: wait for the other up to the delay ...
        assert_eq!(full(1, 2, false, t0, t0), Gather::WaitUntil(at(200)));
        assert_eq!(full(1, 2, false, t0, at(199)), Gather::WaitUntil(at(200)));
        // ... and no longer.
        assert_eq!(full(1, 2, false, t0, at(200)), Gather::Run);
        assert_eq!(full(1, 2, false, t0, at(5000)), Gather::Run);
        // Every stream has a frame: go.
        assert_eq!(full(2, 2, false, t0, at(1)), Gather::Run);
        // More streams than a batch holds: a full batch goes.
        assert_eq!(full(4, 100, false, t0, at(1)), Gather::Run);
        assert_eq!(full(3, 100, false, t0, at(1)), Gather::WaitUntil(at(200)));
        // Closing: the queue drains without waiting.
        assert_eq!(full(1, 2, true, t0, t0), Gather::Run);
        // The deadline counts from the oldest frame, not from now.
        assert_eq!(
            full(1, 2, false, at(150), at(300)),
            Gather::WaitUntil(at(350))
        );
    }
}

//! Sending a whole recorded sequence through the server.
//!
//! [`replay`] is what `blapose-client replay` runs: one session, frames sent
//! as fast as allowed (or paced to a frame rate) while answers arrive, at
//! most `window` frames in flight so the server's queue is never flooded by
//! one stream. Every answer is checked against the protocol's promises:
//! exactly one answer per frame, in order, with `frames_seen` counting up by
//! one. With [`ReplayOptions::server_lifter`] the file's poses are not sent:
//! the server lifts each frame from the keypoints, and every answer must
//! name the lifter and carry its pose. [`adjust_offline`] does the same job
//! (with the file's poses) in one unary call.
//!
//! Both send the sequence's camera calibration when it has one
//! ([`Sequence::camera`]), so the server's camera-aware models serve it;
//! clear `camera` first for the default models. [`Adjusted::camera`] says
//! which family it was.

use std::sync::Arc;
use std::time::{Duration, Instant};

use blapose_core::{BoneLengths, Pose};
use tokio::sync::Semaphore;

use blapose_core::ModelKind;
use blapose_data::replay::{write_adjusted_placed, CameraCalibration, Sequence, SequenceError};

use crate::client::{Client, Placement, SessionOptions};
use crate::config::new_affinity_key;
use crate::error::ClientError;
use crate::session::{EventReceiver, Session, SessionEvent};
use crate::types::{PlacedRoot, SessionInfo, SessionSummary, SessionToken};

/// How to stream a sequence.
#[derive(Debug, Clone)]
pub struct ReplayOptions {
    /// Send at most this many frames per second (`None`: as fast as the
    /// window allows).
    pub fps: Option<f64>,
    /// Frames sent but not yet answered, at most (at least 1).
    pub window: usize,
    /// Label for the server's logs.
    pub label: Option<String>,
    /// Send keypoints only and let the server's lifter produce the poses
    /// (the server must run one).
    pub server_lifter: bool,
    /// `Some(frames per second)` (0: 50): open the session with the causal
    /// motion stage ([`SessionOptions::motion`]).
    pub motion: Option<f32>,
}

impl Default for ReplayOptions {
    fn default() -> Self {
        ReplayOptions {
            fps: None,
            window: 64,
            label: None,
            server_lifter: false,
            motion: None,
        }
    }
}

/// The adjusted sequence.
#[derive(Debug, Clone, PartialEq)]
pub struct Adjusted {
    /// The model that produced the lengths.
    pub model: ModelKind,
    /// The sequence's frame that `adjusted[0]` answers: 0, except for a
    /// [`replay_session`] on a resumed session, which continues where the
    /// session's `frames_seen` says.
    pub first_frame: usize,
    /// One adjusted pose per frame.
    pub adjusted: Vec<Pose>,
    /// The bone lengths applied to each frame.
    pub bone_lengths: Vec<BoneLengths>,
    /// The server lifter that produced the input poses; `None` when they
    /// were the sequence's own (`pose_3d`).
    pub lifter: Option<String>,
    /// The server lifter's poses before adjustment, one per frame (empty
    /// unless `lifter` is set).
    pub lifted: Vec<Pose>,
    /// Wall-clock time of the exchange.
    pub elapsed: Duration,
    /// The session (stream only; it is closed at the end).
    pub session: Option<SessionSummary>,
    /// How many times the session was resumed on the way (a stream that
    /// failed, see [`replay_across`]); 0 for an uninterrupted replay.
    pub resumes: u32,
    /// The camera calibration the serving model was given: `Some` when the
    /// camera-aware model adjusted the sequence, `None` for the default
    /// one. For a stream it is the session's, as the server echoed it; the
    /// offline answer does not echo it, so there it is the one sent (a
    /// server refuses a calibration it cannot serve).
    pub camera: Option<CameraCalibration>,
    /// Where the offline motion stage placed the person (offline calls
    /// that asked for it; `None` otherwise).
    pub placement: Option<Placement>,
}

impl Adjusted {
    /// The adjusted poses moved to their placed roots (camera space), when
    /// the motion stage placed them; else the poses as answered.
    pub fn placed_poses(&self) -> Vec<Pose> {
        match &self.placement {
            Some(p) => blapose_core::motion::place(
                &self.adjusted,
                &p.roots.iter().map(|r| r.map(f64::from)).collect::<Vec<_>>(),
            ),
            None => self.adjusted.clone(),
        }
    }

    /// Write the result as `blapose-client --out` does: `adjusted_3d`,
    /// `bone_lengths` and, when the server lifted the poses, its poses as
    /// `lifted_3d` (see [`write_adjusted`]).
    pub fn write_npz(&self, path: impl AsRef<std::path::Path>) -> Result<(), SequenceError> {
        let roots = self.placement.as_ref().map_or(&[][..], |p| &p.roots[..]);
        write_adjusted_placed(
            path,
            &self.adjusted,
            &self.bone_lengths,
            &self.lifted,
            roots,
        )
    }

    /// Frames per second of the exchange.
    pub fn frames_per_second(&self) -> f64 {
        self.adjusted.len() as f64 / self.elapsed.as_secs_f64().max(1e-9)
    }
}

/// Stream `seq` frame by frame on a new session (with `seq.camera` and `seq.subject`, if
/// any), pipelined, then close the session. `progress` is called with the
/// number of frames answered so far.
///
/// If the stream fails on the way (the connection drops, the server shuts
/// down or crashes), the session is resumed and the replay continues: see
/// [`replay_across`], of which this is the one-server case (a server
/// restarted with the same `--session-key` restores the session from its
/// latest token).
pub async fn replay(
    client: &Client,
    seq: &Sequence,
    options: &ReplayOptions,
    progress: impl FnMut(usize),
) -> Result<Adjusted, ClientError> {
    replay_across(std::slice::from_ref(client), seq, options, progress).await
}

/// How many times [`replay_across`] resumes a session before it gives up.
pub const MAX_RESUMES: u32 = 8;

/// [`replay`] with failover across replicas: open the session on
/// `clients[0]`; whenever the stream fails with a connection-level error
/// (UNAVAILABLE, UNKNOWN, CANCELLED, or the stream ending early), resume
/// the session, trying the server it was on first and then the others in
/// order, sending the latest session token along. A server that holds the
/// session resumes it; one that does not (another replica sharing the
/// session key) restores it from the token. Sending then continues at the
/// first frame the resumed session has not processed, so no frame is
/// processed twice or skipped:
///
/// * restored from a token (as of frame k, at most the frames answered so
///   far): frames k.. are sent again, and the answers to frames already
///   answered are dropped (they equal the first ones);
/// * a held session that processed frames whose answers were lost: with a
///   token, the session is closed there and restored from the token, so
///   every frame gets its answer; without one (a server without a session
///   key) the replay fails with the stream's error, as it would without
///   failover.
///
/// Errors that resuming cannot help (a refused frame, a bad request,
/// ABORTED because another stream took the session over) end the replay at
/// once; so does failing to resume anywhere, [`MAX_RESUMES`] times at most,
/// with the stream's original error. `clients` must not be empty.
pub async fn replay_across(
    clients: &[Client],
    seq: &Sequence,
    options: &ReplayOptions,
    mut progress: impl FnMut(usize),
) -> Result<Adjusted, ClientError> {
    let started = Instant::now();
    if clients.is_empty() {
        return Err(ClientError::InvalidInput(
            "replay_across needs a server".into(),
        ));
    }
    // Every stream and call of this session carries one affinity key, so
    // a load balancer in front of replicas keeps it on one of them.
    let affinity = new_affinity_key();
    let clients = clients
        .iter()
        .map(|c| c.with_affinity(&affinity))
        .collect::<Result<Vec<_>, _>>()?;
    let clients = clients.as_slice();
    let first_client = &clients[0];
    let session_options = SessionOptions {
        label: options.label.as_deref(),
        server_lifter: options.server_lifter,
        camera: seq.camera,
        subject: seq.subject,
        motion: options.motion,
    };
    let session = first_client
        .open_session_with(seq.input_format, &session_options)
        .await?;
    let info = session.info().clone();
    let mut answers = Answers::new(&info, seq)?;
    let mut token = info.token.clone();
    let mut target = 0;
    let mut session = session;
    let mut resumes = 0;
    loop {
        let error = match stream_frames(
            session,
            seq,
            options,
            &mut answers,
            &mut token,
            &mut progress,
        )
        .await
        {
            Ok(summary) => {
                let mut done = answers.finish(&info, summary, started);
                done.resumes = resumes;
                return Ok(done);
            }
            Err(e) => e,
        };
        if !resumable(&error) || resumes >= MAX_RESUMES {
            return Err(error);
        }
        resumes += 1;
        session = match resume(
            clients,
            &mut target,
            &info.session_id,
            &answers,
            token.as_ref(),
        )
        .await
        {
            Some(s) => s,
            None => return Err(error),
        };
    }
}

/// Whether a failed stream may be resumed: the connection or the server
/// went away, not a refusal of what was sent.
fn resumable(e: &ClientError) -> bool {
    match e {
        ClientError::Status(s) => matches!(
            s.code(),
            tonic::Code::Unavailable | tonic::Code::Unknown | tonic::Code::Cancelled
        ),
        ClientError::StreamEnded { .. } | ClientError::Timeout { .. } => true,
        _ => false,
    }
}

/// Resume the session on some server (the current target first), so that
/// it continues at a frame already answered or the next one; `None` when
/// no server could (after a few rounds with a short backoff).
async fn resume(
    clients: &[Client],
    target: &mut usize,
    id: &str,
    answers: &Answers,
    token: Option<&SessionToken>,
) -> Option<Session> {
    let answered = answers.end() as u64;
    let mut backoff = Duration::from_millis(100);
    for round in 0..3 {
        if round > 0 {
            tokio::time::sleep(backoff).await;
            backoff *= 2;
        }
        for step in 0..clients.len() {
            let i = (*target + step) % clients.len();
            let client = &clients[i];
            let Ok(session) = client.resume_session_with_token(id, token).await else {
                continue;
            };
            if session.info().frames_seen <= answered {
                *target = i;
                return Some(session);
            }
            // Held there, with answers lost on the way: start again from
            // the token, which is as of a frame already answered.
            let token = token?;
            drop(session);
            if client.close_session(id).await.is_err() {
                continue;
            }
            if let Ok(session) = client.resume_session_with_token(id, Some(token)).await {
                if session.info().frames_seen <= answered {
                    *target = i;
                    return Some(session);
                }
            }
        }
    }
    None
}

/// The answers collected so far, for frames `first..first + len`.
struct Answers {
    first: usize,
    lifter: Option<String>,
    adjusted: Vec<Pose>,
    lengths: Vec<BoneLengths>,
    lifted: Vec<Pose>,
    /// Placed roots (motion sessions), one per answer that carried one.
    roots: Vec<PlacedRoot>,
}

impl Answers {
    fn new(info: &SessionInfo, seq: &Sequence) -> Result<Self, ClientError> {
        let first = start_frame(info, seq)?;
        let total = seq.len() - first;
        Ok(Answers {
            first,
            lifter: info.lifter.clone(),
            adjusted: Vec::with_capacity(total),
            lengths: Vec::with_capacity(total),
            lifted: Vec::new(),
            roots: Vec::new(),
        })
    }

    /// The first frame without an answer.
    fn end(&self) -> usize {
        self.first + self.adjusted.len()
    }

    fn finish(self, info: &SessionInfo, summary: SessionSummary, started: Instant) -> Adjusted {
        // Placed only when every answer was; in the world only when every
        // answer was.
        let placement =
            (!self.roots.is_empty() && self.roots.len() == self.adjusted.len()).then(|| {
                Placement {
                    focal_assumed: self.roots.iter().any(|r| r.focal_assumed),
                    roots: self.roots.iter().map(|r| r.position).collect(),
                    world: self.roots.iter().map(|r| r.world).collect(),
                }
            });
        Adjusted {
            model: info.model,
            first_frame: self.first,
            adjusted: self.adjusted,
            bone_lengths: self.lengths,
            lifter: self.lifter,
            lifted: self.lifted,
            elapsed: started.elapsed(),
            session: Some(summary),
            resumes: 0,
            placement,
            camera: info.camera,
        }
    }
}

fn start_frame(info: &SessionInfo, seq: &Sequence) -> Result<usize, ClientError> {
    usize::try_from(info.frames_seen)
        .ok()
        .filter(|&f| f <= seq.len())
        .ok_or_else(|| {
            ClientError::InvalidInput(format!(
                "the session has processed {} frames, more than the sequence's {}",
                info.frames_seen,
                seq.len()
            ))
        })
}

/// [`replay`] on a session the caller opened, or resumed after a dropped
/// connection: frame `t` of `seq` is the session's frame `t`, and sending
/// starts at the first frame the session has not processed,
/// `session.info().frames_seen` (0 for a new session). Frames before it are
/// in the session's estimate already, including frames in flight when a
/// connection dropped that the server processed although their answers
/// were lost: sending them again would count them twice. The result holds
/// the frames from there on ([`Adjusted::first_frame`]); the lost answers
/// are not sent again. `options.label`, `server_lifter` and `seq.camera` are
/// the session's, fixed when it was opened. One stream, no failover (see
/// [`replay_across`] for that).
///
/// ```no_run
/// # async fn f(client: &blapose_client::Client, seq: &blapose_client::Sequence) -> Result<(), blapose_client::ClientError> {
/// use blapose_client::{replay_session, ReplayOptions, SessionOptions};
/// let options = ReplayOptions::default();
/// let session = client.open_session_with(seq.input_format, &SessionOptions::default()).await?;
/// let id = session.id().to_string();
/// let done = match replay_session(session, seq, &options, |_| {}).await {
///     Ok(done) => done,
///     // The connection dropped: the session waits, detached, for its TTL.
///     Err(_) => replay_session(client.resume_session(&id).await?, seq, &options, |_| {}).await?,
/// };
/// # Ok(()) }
/// ```
pub async fn replay_session(
    session: Session,
    seq: &Sequence,
    options: &ReplayOptions,
    mut progress: impl FnMut(usize),
) -> Result<Adjusted, ClientError> {
    let started = Instant::now();
    let info = session.info().clone();
    let mut answers = Answers::new(&info, seq)?;
    let mut token = None;
    let summary = stream_frames(
        session,
        seq,
        options,
        &mut answers,
        &mut token,
        &mut progress,
    )
    .await?;
    Ok(answers.finish(&info, summary, started))
}

/// One stream of a replay: send the frames from the session's
/// `frames_seen` on, pipelined, then close; add the answers to frames not
/// answered yet to `answers` (an answer to a frame answered before, on a
/// session restored from an older token, is dropped); keep the latest
/// session token as of a frame answered in `token`.
async fn stream_frames(
    session: Session,
    seq: &Sequence,
    options: &ReplayOptions,
    answers: &mut Answers,
    token: &mut Option<SessionToken>,
    progress: &mut impl FnMut(usize),
) -> Result<SessionSummary, ClientError> {
    let (info, sender, mut receiver) = session.split();
    let first = start_frame(&info, seq)?;
    if first > answers.end() {
        return Err(ClientError::Protocol(format!(
            "the session continues at frame {first}, but frame {} was not answered",
            answers.end()
        )));
    }
    if info.lifter != answers.lifter {
        return Err(ClientError::Protocol(format!(
            "the resumed session's poses come from {:?}, the replay's from {:?}",
            info.lifter, answers.lifter
        )));
    }
    let lifter = answers.lifter.clone();
    let total = seq.len() - first;
    let window = Arc::new(Semaphore::new(options.window.max(1)));

    let send = async {
        let mut ticker = pacer(options.fps);
        for t in first..seq.len() {
            let Ok(permit) = window.acquire().await else {
                return;
            };
            permit.forget();
            if let Some(ticker) = ticker.as_mut() {
                ticker.tick().await;
            }
            let frame = if lifter.is_some() {
                seq.keypoints_frame(t)
            } else {
                seq.frame(t)
            };
            // A failed send means the stream has ended; the receiving side
            // sees why (the server's status) and reports it.
            if sender.send(&frame).await.is_err() {
                return;
            }
        }
        let _ = sender.close().await;
    };

    let receive = async {
        // Wakes the sender if this side stops early (it may be waiting for
        // a window slot that would never be released).
        struct CloseOnDrop<'a>(&'a Semaphore);
        impl Drop for CloseOnDrop<'_> {
            fn drop(&mut self) {
                self.0.close();
            }
        }
        let _wake_sender = CloseOnDrop(&window);
        let mut received = 0usize;
        let keep_token =
            |receiver: &mut EventReceiver, token: &mut Option<SessionToken>, answered: usize| {
                if let Some(t) = receiver.take_new_token() {
                    if t.frames_seen <= answered as u64 {
                        *token = Some(t);
                    }
                }
            };
        keep_token(&mut receiver, token, answers.end());
        while received < total {
            let expected = (first + received) as u64;
            let event = receiver.next().await;
            keep_token(&mut receiver, token, answers.end());
            let frame = match event? {
                Some(SessionEvent::Adjusted(f)) => f,
                Some(SessionEvent::Rejected(r)) => return Err(r.into_error()),
                Some(SessionEvent::Closed(_)) | None => {
                    return Err(ClientError::StreamEnded {
                        answered: received as u64,
                        sent: total as u64,
                    })
                }
            };
            if frame.frame_index != expected {
                return Err(ClientError::Protocol(format!(
                    "answer for frame {} arrived when frame {expected} was due",
                    frame.frame_index
                )));
            }
            if frame.frames_seen != expected + 1 {
                return Err(ClientError::Protocol(format!(
                    "frame {expected}: frames_seen is {}, expected {}",
                    frame.frames_seen,
                    expected + 1
                )));
            }
            if frame.lifter() != lifter.as_deref() {
                return Err(ClientError::Protocol(format!(
                    "frame {expected}: lifted by {:?}, but the session's poses come from {:?}",
                    frame.lifter(),
                    lifter
                )));
            }
            received += 1;
            window.add_permits(1);
            // A frame answered before (the session was restored from an
            // older token): keep the first answer.
            if expected as usize == answers.end() {
                answers.lifted.extend(frame.lifted.map(|l| l.pose));
                answers.adjusted.push(frame.pose);
                answers.lengths.push(frame.bone_lengths);
                answers.roots.extend(frame.root.map(|r| *r));
                progress(answers.adjusted.len());
            }
            // A token sent right after this answer is as of it.
            keep_token(&mut receiver, token, answers.end());
        }
        let summary = match receiver.next().await? {
            Some(SessionEvent::Closed(s)) => s,
            other => {
                return Err(ClientError::Protocol(format!(
                    "expected SessionClosed, got {other:?}"
                )))
            }
        };
        if let Some(extra) = receiver.next().await? {
            return Err(ClientError::Protocol(format!(
                "an answer after SessionClosed: {extra:?}"
            )));
        }
        Ok(summary)
    };

    let ((), received) = tokio::join!(send, receive);
    received
}

/// The ticker that paces sending to `fps` frames per second (`None`: no
/// pacing, for no, a non-finite or a non-positive rate).
fn pacer(fps: Option<f64>) -> Option<tokio::time::Interval> {
    fps.filter(|f| f.is_finite() && *f > 0.0)
        .and_then(|f| Duration::try_from_secs_f64(1.0 / f).ok())
        .filter(|period| !period.is_zero())
        .map(tokio::time::interval)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn fps_sets_the_pacing_period() {
        let period = |fps| pacer(fps).map(|p| p.period());
        assert_eq!(period(Some(100.0)), Some(Duration::from_millis(10)));
        assert_eq!(period(Some(25.0)), Some(Duration::from_millis(40)));
        for unpaced in [
            None,
            Some(0.0),
            Some(-5.0),
            Some(f64::NAN),
            Some(f64::INFINITY),
        ] {
            assert_eq!(period(unpaced), None, "{unpaced:?}");
        }
    }
}

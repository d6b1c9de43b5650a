//! One online stream: attach it to its session ([`crate::attach`]: open,
//! resume or restore), then answer every frame exactly once and in order.
//!
//! Each stream runs as its own task that reads requests, validates frames
//! ([`crate::validate`]), submits them to the batcher ([`crate::batch`])
//! and keeps a FIFO of pending answers ([`crate::answer`]). Answers
//! are written strictly from the front of that FIFO, so a frame refused at
//! validation (answered at once) never overtakes an earlier frame still in
//! the model. The FIFO is bounded (`max_inflight_per_stream`): when it is
//! full the task stops reading, and HTTP/2 flow control (on a WebSocket,
//! TCP's) pushes back on the client instead of the server buffering
//! without limit.
//!
//! Transports: the task reads any [`Inbound`] and writes [`Outbound`]s to
//! a channel, so the gRPC `Stream` RPC ([`crate::service`]) and the
//! browser's WebSocket ([`crate::web`]) run this one handler.
//!
//! In a session opened with `server_lifter`, frames carry keypoints only;
//! the batcher lifts each one from the session's window of earlier frames
//! (see [`crate::prepare`]) and the answer is built from that pose and
//! names the lifter.
//!
//! Ending: a `close` request, the client ending its side, a protocol error,
//! a takeover by another stream, or server shutdown all stop the reading
//! side first; the task then still answers every pending frame before it
//! sends the final message or status. A stream that ends without `close`
//! leaves its session detached (resumable for the TTL).

use std::collections::VecDeque;
use std::sync::Arc;
use std::time::Instant;

use blapose_core::Pose;
use blapose_proto::v1 as pb;
use pb::stream_request::Kind as Req;
use pb::stream_response::Kind as Resp;
use tokio::sync::{mpsc, oneshot, watch};
use tokio_stream::{Stream, StreamExt};
use tonic::Status;
use tracing::Instrument;

use crate::answer::{self, frame_error};
use crate::attach::{
    lengths_vec, open_or_resume, opened_response, seal, session_lifter, session_status,
    token_response,
};
use crate::frame::{FrameJob, StepResult};
use crate::metrics;
use crate::quota::ClientId;
use crate::session::{Attachment, Ownership};
use crate::state::AppState;
use crate::validate;

/// What the response channel carries. Boxed: the channel allocates its
/// slots in blocks of 32 per stream, and an unboxed response (192 bytes)
/// made every idle stream's block 6 KiB (the boxes live only while a
/// response is in the channel).
pub type Outbound = Result<Box<pb::StreamResponse>, Status>;

/// An answer waiting for its turn.
enum Pending {
    /// Already known (a refused frame).
    Ready(pb::StreamResponse),
    /// A token request: answered with the session's state once every
    /// earlier frame is answered (no later frame is read before that).
    Token,
    /// In the batcher. `pose` is the client's, `None` when the server
    /// lifts it.
    Step {
        frame_index: u64,
        pose: Option<Pose>,
        received: Instant,
        rx: oneshot::Receiver<StepResult>,
    },
}

/// How the frame phase ended.
enum End {
    /// The client ended its side: detach.
    Detach,
    /// `close` request: delete the session and say so.
    Close,
    /// End with this status, detaching the session.
    Fail(Status),
    /// The session is no longer ours (takeover or close elsewhere).
    Lost(Status),
    /// The response channel is gone (client disconnected).
    Gone,
}

/// The requests of one stream, whatever carries them: tonic's
/// `Streaming` for gRPC, the WebSocket's decoded messages for the browser
/// transport ([`crate::web`]). An `Err` ends the stream with that status.
/// Reading must be cancel-safe (a message is never lost when the read is
/// dropped half-way), as `StreamExt::next` on both is.
pub trait Inbound: Stream<Item = Result<pb::StreamRequest, Status>> + Unpin + Send {}

impl<S: Stream<Item = Result<pb::StreamRequest, Status>> + Unpin + Send> Inbound for S {}

/// The next request, `Ok(None)` once the client ended its side.
async fn message(inbound: &mut impl Inbound) -> Result<Option<pb::StreamRequest>, Status> {
    inbound.next().await.transpose()
}

/// Drive one stream to completion: every transport's stream handler. Runs
/// as its own task; `tx` carries the answers, and the final status, back
/// to the transport.
pub async fn run(
    state: Arc<AppState>,
    client: ClientId,
    mut inbound: impl Inbound,
    tx: mpsc::Sender<Outbound>,
) {
    // A stream that never sends its first message would hold its task and
    // connection slot forever: the open or resume has a deadline.
    let open_timeout = state.open_timeout;
    let first = async {
        match tokio::time::timeout(open_timeout, message(&mut inbound)).await {
            Ok(Ok(None)) if client_cancelled(&tx).await => Err(Status::cancelled(
                "the client cancelled the stream before its open or resume",
            )),
            Ok(first) => first,
            Err(_) => Err(no_open_in_time(open_timeout)),
        }
    };
    let (attachment, periodic_tokens) = tokio::select! {
        first = first => match open_or_resume(&state, client, first) {
            Ok(a) => a,
            Err(status) => {
                metrics::error(status.code(), "Stream");
                let _ = tx.send(Err(status)).await;
                return;
            }
        },
        _ = state.draining.cancelled() => {
            let _ = tx.send(Err(shutting_down(state.tokens.is_some()))).await;
            return;
        }
    };
    let session = attachment.session.clone();
    let span = tracing::info_span!(
        "stream",
        session = %session.id(),
        label = %session.config().label,
    );
    async move {
        let opened = opened_response(&state, &attachment);
        if tx.send(Ok(Box::new(opened))).await.is_err() {
            state.store.detach(&session, attachment.epoch);
            return;
        }
        tracing::info!(resumed = attachment.epoch > 1, "stream attached");
        metrics::stream_attached(1);
        let end = {
            let _guard = state.batcher.stream_guard();
            // Periodic tokens only for clients that read them.
            let token_every = match &state.tokens {
                Some(t) if periodic_tokens => t.every,
                _ => 0,
            };
            let asked = periodic_tokens && state.tokens.is_some();
            frames(&state, &attachment, token_every, asked, &mut inbound, &tx).await
        };
        metrics::stream_attached(-1);
        finish(&state, &attachment, end, &tx).await;
    }
    .instrument(span)
    .await;
}

/// The status a stream ends with at shutdown. Sessions live in this
/// server's memory: without a session key they end with it (resuming
/// elsewhere, or here after a restart, finds no session); with one, the
/// stream's last message before this status is a session token as of every
/// frame answered, from which another replica restores the session.
fn shutting_down(tokens: bool) -> Status {
    if tokens {
        Status::unavailable(
            "the server is shutting down: every frame it received was answered and the session's \
             latest token sent; resume the session with that token on another replica",
        )
    } else {
        Status::unavailable(
            "the server is shutting down: every frame it received was answered, and its sessions \
             end with it; reconnect later (or to another server) and open a new session",
        )
    }
}

/// Whether the client reset its stream (a cancel) rather than half-closed
/// it: hyper ends a request body reset with CANCEL as if it had ended
/// cleanly, but then the response side closes too, soon after (a client
/// that half-closed is still reading and keeps it open).
async fn client_cancelled(tx: &mpsc::Sender<Outbound>) -> bool {
    tokio::time::timeout(std::time::Duration::from_millis(50), tx.closed())
        .await
        .is_ok()
}

/// The status a stream ends with when its first message did not arrive
/// within `waited` (`--open-timeout`).
fn no_open_in_time(waited: std::time::Duration) -> Status {
    Status::deadline_exceeded(format!(
        "no open or resume request within {waited:?} of the stream starting \
         (--open-timeout): send it as the first message"
    ))
}

/// Validate and submit one frame; the returned entry answers it.
fn submit(state: &AppState, a: &Attachment, token_every: u64, frame: pb::Frame) -> Pending {
    let received = Instant::now();
    let index = frame.frame_index;
    let config = a.session.config();
    // A lifting session's frame carries keypoints only; its pose comes
    // from the batcher.
    let valid = if config.lifting() {
        validate::keypoints_frame(&config.input, &frame)
            .map(|(input, present)| (input, present, None))
    } else {
        validate::frame(&config.input, &frame).map(|v| (v.input, v.present, Some(v.pose)))
    };
    let (input, present, pose) = match valid {
        Ok(v) => v,
        Err(e) => {
            return Pending::Ready(frame_error(
                index,
                tonic::Code::InvalidArgument,
                e.to_string(),
            ))
        }
    };
    if let Err(e) = state.budget.admit(crate::budget::FRAME_BYTES) {
        return Pending::Ready(frame_error(index, e.to_status().code(), e.to_string()));
    }
    let (reply, rx) = oneshot::channel();
    let job = FrameJob {
        session: a.session.clone(),
        epoch: a.epoch,
        input,
        present,
        lift: pose.is_none(),
        // Only the motion stage reads the pose on the batcher thread.
        pose: pose.filter(|_| a.session.config().motion.is_some()),
        state_every: token_every,
        reply,
    };
    match state.batcher.submit_limited(
        job,
        state.limits.frames_per_session,
        state.limits.queued_per_client,
    ) {
        Ok(()) => Pending::Step {
            frame_index: index,
            pose,
            received,
            rx,
        },
        Err(e) => Pending::Ready(frame_error(index, e.code(), e.to_string())),
    }
}

/// Wait for the front answer and turn it into responses: the answer, and
/// a session token after it when one is due (`lifter`: the name lifted
/// frames are answered with).
async fn next_answer(
    state: &AppState,
    a: &Attachment,
    pending: &mut VecDeque<Pending>,
    lifter: &str,
) -> (Option<pb::StreamResponse>, Option<pb::StreamResponse>) {
    let result = match pending.front_mut() {
        None => return (None, None),
        Some(Pending::Ready(_) | Pending::Token) => None,
        Some(Pending::Step { rx, .. }) => Some(rx.await),
    };
    let Some(front) = pending.pop_front() else {
        return (None, None);
    };
    match (front, result) {
        (Pending::Ready(response), _) => (Some(response), None),
        (Pending::Token, _) => {
            // Every earlier frame is answered and no later one was read:
            // the state is exactly the one after the frames before the
            // request. A session no longer ours gets no token (the stream
            // ends with ABORTED).
            let copy = {
                let st = a.session.lock();
                st.accepts(a.epoch).then(|| st.copy_state())
            };
            let token = copy.and_then(|c| seal(state, &a.session, c));
            (None, token.map(token_response))
        }
        (
            Pending::Step {
                frame_index,
                pose,
                received,
                ..
            },
            Some(mut result),
        ) => {
            let copy = match &mut result {
                Ok(Ok(output)) => output.state.take(),
                _ => None,
            };
            let token = copy
                .and_then(|c| seal(state, &a.session, *c))
                .map(token_response);
            (
                Some(answer::frame_response(
                    frame_index,
                    pose,
                    lifter,
                    received,
                    result,
                )),
                token,
            )
        }
        (Pending::Step { frame_index, .. }, None) => (
            Some(frame_error(
                frame_index,
                tonic::Code::Internal,
                "frame was not answered".into(),
            )),
            None,
        ),
    }
}

fn lost_status(owner: Ownership) -> Status {
    if owner.closed {
        Status::aborted("the session was closed (CloseSession) or expired")
    } else {
        Status::aborted("the session was resumed by another stream")
    }
}

/// The frame phase: read, submit, answer in order.
async fn frames(
    state: &AppState,
    a: &Attachment,
    token_every: u64,
    asked: bool,
    inbound: &mut impl Inbound,
    tx: &mpsc::Sender<Outbound>,
) -> End {
    let cap = state.max_inflight_per_stream.max(1);
    // Grows to the stream's actual pipelining depth (then stays there, so
    // no allocation per frame); not preallocated to `cap`, which would cost
    // every idle stream `cap` x ~250 bytes.
    let mut pending: VecDeque<Pending> = VecDeque::new();
    let mut owner: watch::Receiver<Ownership> = a.session.watch();
    let mut reading = true;
    let mut end = End::Detach;
    let lifter = session_lifter(state, a);
    // A takeover between attaching and subscribing would not show up as a
    // change: check the current owner once up front.
    let now = *owner.borrow_and_update();
    if now.closed || now.epoch != a.epoch {
        return End::Lost(lost_status(now));
    }
    loop {
        if !reading && pending.is_empty() {
            return end;
        }
        tokio::select! {
            biased;
            changed = owner.changed() => {
                let now = *owner.borrow_and_update();
                if changed.is_err() || now.closed || now.epoch != a.epoch {
                    // Pending frames will be refused by the batcher; the
                    // client learns why from the status.
                    return End::Lost(lost_status(now));
                }
            }
            (response, token) = next_answer(state, a, &mut pending, lifter), if !pending.is_empty() => {
                for response in [response, token].into_iter().flatten() {
                    if tx.send(Ok(Box::new(response))).await.is_err() {
                        return End::Gone;
                    }
                }
            }
            _ = state.draining.cancelled(), if reading => {
                reading = false;
                end = End::Fail(shutting_down(asked));
                // A final token, as of every frame answered: the client
                // resumes on another replica without re-sending any frame.
                // Only for a stream that asked for tokens: one that did
                // not would never use it.
                if asked {
                    pending.push_back(Pending::Token);
                }
            }
            message = message(inbound),
                if reading && pending.len() < cap && !pending.iter().any(|p| matches!(p, Pending::Token)) =>
            match message {
                Ok(Some(request)) => match request.kind {
                    Some(Req::Frame(frame)) => pending.push_back(submit(state, a, token_every, frame)),
                    Some(Req::TokenRequest(_)) => pending.push_back(if state.tokens.is_some() {
                        Pending::Token
                    } else {
                        Pending::Ready(frame_error(
                            0,
                            tonic::Code::FailedPrecondition,
                            "this server has no session key (--session-key): it issues no session tokens".into(),
                        ))
                    }),
                    Some(Req::Close(_)) => {
                        reading = false;
                        end = End::Close;
                    }
                    Some(Req::Open(_) | Req::Resume(_)) => {
                        reading = false;
                        end = End::Fail(Status::failed_precondition(
                            "this stream already has a session; open or resume only as the first message",
                        ));
                    }
                    None => {
                        reading = false;
                        end = End::Fail(Status::invalid_argument(
                            "empty StreamRequest: set open, resume, frame or close",
                        ));
                    }
                },
                Ok(None) => reading = false,
                Err(status) => {
                    reading = false;
                    end = End::Fail(status);
                }
            },
        }
    }
}

async fn finish(state: &AppState, a: &Attachment, end: End, tx: &mpsc::Sender<Outbound>) {
    let id = a.session.id().to_string();
    match end {
        End::Close => match state.store.close(&id) {
            Ok(snapshot) => {
                tracing::info!(
                    frames_seen = snapshot.frames_seen,
                    "session closed by client"
                );
                let closed = pb::StreamResponse {
                    kind: Some(Resp::Closed(pb::SessionClosed {
                        session_id: id,
                        frames_seen: snapshot.frames_seen,
                        bone_lengths: lengths_vec(&snapshot),
                    })),
                };
                let _ = tx.send(Ok(Box::new(closed))).await;
            }
            Err(e) => {
                let status = session_status(e);
                metrics::error(status.code(), "Stream");
                let _ = tx.send(Err(status)).await;
            }
        },
        end @ (End::Detach | End::Gone) => {
            state.store.detach(&a.session, a.epoch);
            tracing::info!("stream ended; session detached");
            // Gone, or the response side closed: the client cancelled (or
            // lost its connection) rather than half-closing.
            if matches!(end, End::Gone) || tx.is_closed() {
                metrics::error(tonic::Code::Cancelled, "Stream");
            }
        }
        End::Fail(status) => {
            state.store.detach(&a.session, a.epoch);
            tracing::info!(code = ?status.code(), message = status.message(), "stream ended with an error; session detached");
            metrics::error(status.code(), "Stream");
            let _ = tx.send(Err(status)).await;
        }
        End::Lost(status) => {
            tracing::info!(message = status.message(), "stream lost its session");
            metrics::error(status.code(), "Stream");
            let _ = tx.send(Err(status)).await;
        }
    }
}

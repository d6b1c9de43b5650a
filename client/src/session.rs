//! One online session: a bidirectional gRPC stream.
//!
//! The server answers every frame exactly once and in order, so a client can
//! pipeline: keep sending while answers arrive. To make that natural the
//! session splits into a [`FrameSender`] (cloneable, usable from another
//! task) and an [`EventReceiver`]; [`Session`] bundles both for the simple
//! send-then-wait case. Outgoing frames go through a bounded channel, so a
//! sender that outruns the network waits instead of buffering without
//! limit.
//!
//! Ending the client's half of the stream (dropping every sender) leaves the
//! session *detached* on the server for its TTL, resumable by id; only an
//! explicit close deletes it.

use blapose_proto::v1 as pb;
use blapose_proto::v1::stream_request::Kind as RequestKind;
use blapose_proto::v1::stream_response::Kind as ResponseKind;
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;

use crate::config::{ClientConfig, Stub};
use crate::error::ClientError;
use crate::types::wire::ToProto;
use crate::types::{AdjustedFrame, FrameInput, SessionInfo, SessionSummary, SessionToken};

/// A frame the server refused; the session is unchanged and later frames
/// are processed normally.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameRejection {
    /// The refused frame's index.
    pub frame_index: u64,
    /// gRPC status code (INVALID_ARGUMENT for bad values, RESOURCE_EXHAUSTED
    /// when the server's queue is full, INTERNAL for a model failure).
    pub code: tonic::Code,
    /// The server's explanation.
    pub message: String,
}

impl FrameRejection {
    /// As an error.
    pub fn into_error(self) -> ClientError {
        ClientError::FrameRejected {
            frame_index: self.frame_index,
            code: self.code,
            message: self.message,
        }
    }
}

/// One answer on a session's stream (after it was opened).
#[derive(Debug, Clone, PartialEq)]
pub enum SessionEvent {
    /// A frame was adjusted.
    Adjusted(AdjustedFrame),
    /// A frame was refused.
    Rejected(FrameRejection),
    /// The session was closed (always the last event).
    Closed(SessionSummary),
}

/// The sending half of a session. Clones send on the same stream.
#[derive(Debug, Clone)]
pub struct FrameSender {
    tx: mpsc::Sender<pb::StreamRequest>,
}

impl FrameSender {
    /// Queue one frame; waits while the local buffer is full. Fails only if
    /// the stream has already ended.
    pub async fn send(&self, frame: &FrameInput) -> Result<(), ClientError> {
        self.send_raw(pb::StreamRequest {
            kind: Some(RequestKind::Frame(frame.to_proto())),
        })
        .await
    }

    /// Queue a request exactly as given (e.g. a deliberately malformed frame).
    pub async fn send_raw(&self, req: pb::StreamRequest) -> Result<(), ClientError> {
        self.tx
            .send(req)
            .await
            .map_err(|_| ClientError::Protocol("the session's stream has ended".into()))
    }

    /// Ask the server for a session token (servers with a session key): it
    /// arrives after the answers to every frame sent before, and
    /// [`EventReceiver::latest_token`] holds it from then on. A server
    /// without a key answers with a rejection (FAILED_PRECONDITION,
    /// frame index 0).
    pub async fn request_token(&self) -> Result<(), ClientError> {
        self.send_raw(pb::StreamRequest {
            kind: Some(RequestKind::TokenRequest(pb::TokenRequest {})),
        })
        .await
    }

    /// Ask the server to close the session: it answers every earlier frame,
    /// then sends [`SessionEvent::Closed`] and ends the stream.
    pub async fn close(&self) -> Result<(), ClientError> {
        self.send_raw(pb::StreamRequest {
            kind: Some(RequestKind::Close(pb::CloseSession {})),
        })
        .await
    }
}

/// The receiving half of a session. Session tokens the server sends
/// (servers with a session key) are not events: the receiver keeps the
/// latest one ([`EventReceiver::latest_token`]).
#[derive(Debug)]
pub struct EventReceiver {
    inner: tonic::Streaming<pb::StreamResponse>,
    token: Option<SessionToken>,
    fresh_token: bool,
}

impl EventReceiver {
    /// The latest session token: the one in `SessionOpened`, then each one
    /// the server sent since (every N frames, or on request), each as of
    /// the frames answered before it; `None` from a server without a key.
    pub fn latest_token(&self) -> Option<&SessionToken> {
        self.token.as_ref()
    }

    /// The latest token if one arrived since the last call (or since the
    /// session opened, for the first call).
    pub fn take_new_token(&mut self) -> Option<SessionToken> {
        if std::mem::take(&mut self.fresh_token) {
            self.token.clone()
        } else {
            None
        }
    }

    /// The next answer; `Ok(None)` when the server ended the stream with OK,
    /// `Err(ClientError::Status)` when it ended it with an error status.
    pub async fn next(&mut self) -> Result<Option<SessionEvent>, ClientError> {
        let msg = loop {
            let Some(msg) = self.inner.message().await? else {
                return Ok(None);
            };
            match msg.kind {
                Some(ResponseKind::Token(t)) => {
                    self.token = Some(SessionToken {
                        token: t.token,
                        frames_seen: t.frames_seen,
                    });
                    self.fresh_token = true;
                }
                _ => break msg,
            }
        };
        let event = match msg.kind {
            Some(ResponseKind::Frame(f)) => SessionEvent::Adjusted(AdjustedFrame::from_proto(f)?),
            Some(ResponseKind::Error(e)) => SessionEvent::Rejected(FrameRejection {
                frame_index: e.frame_index,
                code: tonic::Code::from_i32(e.code),
                message: e.message,
            }),
            Some(ResponseKind::Closed(c)) => SessionEvent::Closed(SessionSummary::from_closed(c)?),
            Some(ResponseKind::Opened(_)) => {
                return Err(ClientError::Protocol(
                    "a second SessionOpened on one stream".into(),
                ))
            }
            Some(ResponseKind::Token(_)) | None => {
                return Err(ClientError::Protocol("an empty StreamResponse".into()))
            }
        };
        Ok(Some(event))
    }

    /// The next adjusted frame; a rejection, a close or the end of the
    /// stream is an error here.
    pub async fn next_adjusted(&mut self) -> Result<AdjustedFrame, ClientError> {
        match self.next().await? {
            Some(SessionEvent::Adjusted(f)) => Ok(f),
            Some(SessionEvent::Rejected(r)) => Err(r.into_error()),
            Some(SessionEvent::Closed(_)) => Err(ClientError::Protocol(
                "session closed while a frame was pending".into(),
            )),
            None => Err(ClientError::Protocol(
                "stream ended while a frame was pending".into(),
            )),
        }
    }
}

/// An open session: its id and state at open time, and both stream halves.
#[derive(Debug)]
pub struct Session {
    info: SessionInfo,
    sender: FrameSender,
    receiver: EventReceiver,
}

impl Session {
    /// Open a stream on `stub` whose first request is `first` (an open or
    /// a resume) and wait, at most `config.request_timeout`, for the
    /// server's `SessionOpened`.
    pub(crate) async fn start(
        stub: Stub,
        config: &ClientConfig,
        first: RequestKind,
    ) -> Result<Session, ClientError> {
        Session::start_raw(stub, config, pb::StreamRequest { kind: Some(first) }).await
    }

    /// [`start`](Self::start) with the first message exactly as given.
    pub(crate) async fn start_raw(
        mut stub: Stub,
        config: &ClientConfig,
        first: pb::StreamRequest,
    ) -> Result<Session, ClientError> {
        let (tx, rx) = mpsc::channel(config.session_buffer.max(1));
        tx.send(first)
            .await
            .map_err(|_| ClientError::Protocol("request channel closed".into()))?;
        let after = config.request_timeout;
        let open = async move {
            let mut inner = stub.stream(ReceiverStream::new(rx)).await?.into_inner();
            let first = inner.message().await?;
            Ok::<_, ClientError>((inner, first))
        };
        let (inner, first) =
            tokio::time::timeout(after, open)
                .await
                .map_err(|_| ClientError::Timeout {
                    what: "opening a session",
                    after,
                })??;
        let info = match first.and_then(|m| m.kind) {
            Some(ResponseKind::Opened(o)) => SessionInfo::from_proto(o)?,
            Some(other) => {
                return Err(ClientError::Protocol(format!(
                    "expected SessionOpened as the first answer, got {other:?}"
                )))
            }
            None => {
                return Err(ClientError::Protocol(
                    "the stream ended before the session opened".into(),
                ))
            }
        };
        let token = info.token.clone();
        Ok(Session {
            info,
            sender: FrameSender { tx },
            receiver: EventReceiver {
                inner,
                fresh_token: token.is_some(),
                token,
            },
        })
    }

    /// What the server said when the session opened (or resumed).
    pub fn info(&self) -> &SessionInfo {
        &self.info
    }

    /// The session id.
    pub fn id(&self) -> &str {
        &self.info.session_id
    }

    /// The latest session token (see [`EventReceiver::latest_token`]).
    pub fn latest_token(&self) -> Option<&SessionToken> {
        self.receiver.latest_token()
    }

    /// Queue one frame (see [`FrameSender::send`]).
    pub async fn send(&self, frame: &FrameInput) -> Result<(), ClientError> {
        self.sender.send(frame).await
    }

    /// The next answer (see [`EventReceiver::next`]).
    pub async fn next_event(&mut self) -> Result<Option<SessionEvent>, ClientError> {
        self.receiver.next().await
    }

    /// Send one frame and wait for its answer (no pipelining).
    pub async fn adjust(&mut self, frame: &FrameInput) -> Result<AdjustedFrame, ClientError> {
        self.sender.send(frame).await?;
        let answer = self.receiver.next_adjusted().await?;
        if answer.frame_index != frame.frame_index {
            return Err(ClientError::Protocol(format!(
                "sent frame {} but the answer is for frame {}",
                frame.frame_index, answer.frame_index
            )));
        }
        Ok(answer)
    }

    /// Split into the two halves, for pipelining from two tasks.
    pub fn split(self) -> (SessionInfo, FrameSender, EventReceiver) {
        (self.info, self.sender, self.receiver)
    }

    /// Close the session for good and return its final state. Answers to
    /// frames still in flight are discarded; to keep them, [`split`] and
    /// read them before the [`SessionEvent::Closed`] event.
    ///
    /// [`split`]: Session::split
    pub async fn close(self) -> Result<SessionSummary, ClientError> {
        let Session {
            sender,
            mut receiver,
            ..
        } = self;
        sender.close().await?;
        drop(sender);
        while let Some(event) = receiver.next().await? {
            if let SessionEvent::Closed(summary) = event {
                return Ok(summary);
            }
        }
        Err(ClientError::Protocol(
            "the stream ended without a SessionClosed".into(),
        ))
    }

    /// End this stream without closing the session: the server keeps it,
    /// detached, for its TTL. Ends the client's half of the stream, then
    /// reads (and discards) the server's remaining answers until it ends its
    /// half too, so the server has seen the detach when this returns; gives
    /// up waiting after `wait`. Returns the id to resume with.
    pub async fn detach(self, wait: std::time::Duration) -> String {
        let Session {
            info,
            sender,
            mut receiver,
        } = self;
        drop(sender);
        let drain = async { while let Ok(Some(_)) = receiver.next().await {} };
        let _ = tokio::time::timeout(wait, drain).await;
        info.session_id
    }
}

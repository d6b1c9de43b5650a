//! One WebSocket, one stream: the adapter between a browser's socket and
//! the stream handler every transport shares ([`crate::stream::run`]).
//!
//! Wire format: each binary message is one protobuf `StreamRequest` (to
//! the server) or `StreamResponse` (to the client), exactly the gRPC
//! `Stream` RPC's messages. Where gRPC ends a call with a status, the
//! server sends one text message, `{"code":14,"status":"UNAVAILABLE",
//! "message":"..."}` (the gRPC code, its name and the full message), then
//! closes with code 4000 + the gRPC code (4014 here) and the name as the
//! reason; a stream that ends well closes with 1000.
//!
//! Auth (`--auth-token`): browsers cannot set headers on a WebSocket, so
//! the token is accepted, checked before the upgrade, from an
//! `authorization: Bearer` header, a `bearer.<token>` subprotocol offered
//! beside `blapose.v1`, or a `token` query parameter (in that order).
//!
//! Bounds, so that a slow or dead browser never holds the server: a
//! message over `--max-message-bytes` ends the stream with OUT_OF_RANGE;
//! answers wait in a channel of the gRPC stream's size, and when it is full
//! the handler stops reading the socket (TCP then pushes back); the
//! server pings every third of the idle timeout and closes a socket that
//! sent nothing for the idle timeout (DEADLINE_EXCEEDED) or on which one
//! write blocked that long; the first message must arrive within
//! `--open-timeout` as on gRPC.

use std::collections::HashMap;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use axum::body::Bytes;
use axum::extract::ws::{CloseFrame, Message, WebSocket, WebSocketUpgrade};
use axum::extract::{ConnectInfo, Query, State};
use axum::http::{HeaderMap, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::Extension;
use blapose_proto::v1 as pb;
use futures_util::stream::{SplitSink, SplitStream};
use futures_util::{SinkExt, StreamExt};
use prost::Message as _;
use tokio::sync::mpsc;
use tokio_util::task::TaskTracker;
use tonic::Status;

use crate::auth::BearerAuth;
use crate::state::AppState;
use crate::stream::{self, Outbound};
use crate::transport::Permit;

use super::config::WebConfig;
use super::token::presented_token;
use super::PROTOCOL;

/// What the upgrade handler shares.
#[derive(Debug)]
pub struct Endpoint {
    state: Arc<AppState>,
    auth: BearerAuth,
    idle_timeout: Duration,
    ping_interval: Duration,
    /// Sockets in progress, so that shutdown waits for them.
    sockets: TaskTracker,
}

impl Endpoint {
    /// The endpoint of a server.
    pub fn new(
        state: Arc<AppState>,
        auth: BearerAuth,
        config: &WebConfig,
        sockets: TaskTracker,
    ) -> Self {
        Self {
            state,
            auth,
            idle_timeout: config.idle_timeout,
            ping_interval: config.ping_interval(),
            sockets,
        }
    }
}

/// `GET /v1/stream`: check the token, then upgrade to a WebSocket served
/// by the stream handler.
pub async fn upgrade(
    State(endpoint): State<Arc<Endpoint>>,
    ConnectInfo(peer): ConnectInfo<SocketAddr>,
    Extension(permit): Extension<Arc<Permit>>,
    Query(query): Query<HashMap<String, String>>,
    headers: HeaderMap,
    ws: WebSocketUpgrade,
) -> Response {
    if let Err(status) = endpoint.auth.check(
        presented_token(&headers, &query).as_deref(),
        "missing bearer token (send it as the `bearer.<token>` subprotocol beside blapose.v1, \
         a `token` query parameter, or an authorization header)",
    ) {
        return (StatusCode::UNAUTHORIZED, status.message().to_string()).into_response();
    }
    let client = endpoint.state.limits.client_of(Some(peer.ip()), |name| {
        headers
            .get(name)
            .and_then(|v| v.to_str().ok())
            .map(str::to_string)
    });
    let max = endpoint.state.max_message_bytes;
    let token = endpoint.sockets.token();
    ws.protocols([PROTOCOL])
        .max_message_size(max)
        .max_frame_size(max)
        .on_failed_upgrade(move |e| tracing::debug!(%peer, error = %e, "web: upgrade failed"))
        .on_upgrade(move |socket| async move {
            let _held = (token, permit);
            session(&endpoint, client, socket).await;
        })
}

/// How long a closing socket waits for the client's close frame (the
/// closing handshake) before its connection is dropped.
const CLOSE_WAIT: Duration = Duration::from_secs(1);

/// Run the stream handler on `socket` until both it and the writer end,
/// then finish the closing handshake.
async fn session(endpoint: &Endpoint, client: crate::quota::ClientId, socket: WebSocket) {
    let (mut sink, mut source) = socket.split();
    let state = &endpoint.state;
    let (tx, rx) = mpsc::channel(state.max_inflight_per_stream.max(1) + 2);
    let inbound = Box::pin(requests(
        &mut source,
        endpoint.idle_timeout,
        state.max_message_bytes,
    ));
    let ((), closed) = tokio::join!(
        stream::run(state.clone(), client, inbound, tx),
        answers(&mut sink, rx, endpoint.ping_interval, endpoint.idle_timeout),
    );
    if closed {
        // Read (and drop) what the client still sends until its close
        // frame: a connection dropped with unread bytes is reset, and the
        // client might then lose the final status.
        let _ = tokio::time::timeout(CLOSE_WAIT, async {
            while let Some(Ok(message)) = source.next().await {
                if matches!(message, Message::Close(_)) {
                    break;
                }
            }
        })
        .await;
    }
}

/// The socket's requests, decoded; pings and pongs only keep it alive.
fn requests(
    source: &mut SplitStream<WebSocket>,
    idle: Duration,
    max_bytes: usize,
) -> impl futures_util::Stream<Item = Result<pb::StreamRequest, Status>> + Send + '_ {
    futures_util::stream::unfold(Some(source), move |source| async move {
        let source = source?;
        loop {
            let Ok(next) = tokio::time::timeout(idle, source.next()).await else {
                return Some((Err(idle_status(idle)), None));
            };
            let request = match next {
                None | Some(Ok(Message::Close(_))) => return None,
                Some(Ok(Message::Ping(_) | Message::Pong(_))) => continue,
                Some(Ok(Message::Binary(bytes))) => decode(&bytes),
                Some(Ok(Message::Text(_))) => Err(Status::invalid_argument(
                    "a text message: send each StreamRequest as one binary message (its protobuf encoding)",
                )),
                Some(Err(e)) => Err(read_error(e, max_bytes)),
            };
            // After an error the stream ends (the handler reads no more).
            let rest = request.is_ok().then_some(source);
            return Some((request, rest));
        }
    })
}

fn decode(bytes: &[u8]) -> Result<pb::StreamRequest, Status> {
    pb::StreamRequest::decode(bytes).map_err(|e| {
        Status::invalid_argument(format!(
            "a binary message that is not a StreamRequest protobuf: {e}"
        ))
    })
}

fn idle_status(idle: Duration) -> Status {
    Status::deadline_exceeded(format!(
        "the socket sent nothing for {idle:?}, not even a pong to the server's pings: closed as dead"
    ))
}

/// The status a failed read ends the stream with.
fn read_error(e: axum::Error, max_bytes: usize) -> Status {
    let e = e.into_inner();
    match e.downcast_ref::<tungstenite::Error>() {
        Some(tungstenite::Error::Capacity(c)) => Status::out_of_range(format!(
            "message too large: {c} (the server accepts at most {max_bytes} bytes, --max-message-bytes)"
        )),
        _ => Status::cancelled(format!("the socket failed: {e}")),
    }
}

/// Write the handler's answers, ping while waiting, and end with the
/// status (or a normal close); whether the close frame was sent. Returns
/// early when a write fails or blocks for `write_timeout`: the handler
/// then sees its channel closed and ends as for a client that vanished.
async fn answers(
    sink: &mut SplitSink<WebSocket, Message>,
    mut rx: mpsc::Receiver<Outbound>,
    ping_every: Duration,
    write_timeout: Duration,
) -> bool {
    let mut ping = tokio::time::interval_at(tokio::time::Instant::now() + ping_every, ping_every);
    ping.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let last = loop {
        let message = tokio::select! {
            out = rx.recv() => match out {
                Some(Ok(response)) => Message::Binary(response.encode_to_vec().into()),
                Some(Err(status)) => break Some(status),
                None => break None,
            },
            _ = ping.tick() => Message::Ping(Bytes::new()),
        };
        if send(sink, message, write_timeout).await.is_err() {
            return false;
        }
    };
    let close = match last {
        None => CloseFrame {
            code: 1000,
            reason: "".into(),
        },
        Some(status) => {
            let text = status_text(&status);
            if send(sink, Message::Text(text.into()), write_timeout)
                .await
                .is_err()
            {
                return false;
            }
            close_frame(status.code())
        }
    };
    send(sink, Message::Close(Some(close)), write_timeout)
        .await
        .is_ok()
}

async fn send(
    sink: &mut SplitSink<WebSocket, Message>,
    message: Message,
    timeout: Duration,
) -> Result<(), ()> {
    match tokio::time::timeout(timeout, sink.send(message)).await {
        Ok(Ok(())) => Ok(()),
        Ok(Err(e)) => {
            tracing::debug!(error = %e, "web: write failed");
            Err(())
        }
        Err(_) => {
            tracing::info!(
                ?timeout,
                "web: a write blocked too long; closing the socket"
            );
            Err(())
        }
    }
}

/// The text message that carries a final status.
pub fn status_text(status: &Status) -> String {
    serde_json::json!({
        "code": status.code() as i32,
        "status": crate::metrics::code_name(status.code()),
        "message": status.message(),
    })
    .to_string()
}

/// The close frame of a final status: 4000 + the gRPC code, its name.
pub fn close_frame(code: tonic::Code) -> CloseFrame {
    CloseFrame {
        code: 4000 + code as u16,
        reason: crate::metrics::code_name(code).into(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_status_closes_with_4000_plus_its_code() {
        let frame = close_frame(tonic::Code::Unavailable);
        assert_eq!(frame.code, 4014);
        assert_eq!(frame.reason.as_str(), "UNAVAILABLE");
        let text = status_text(&Status::out_of_range("too big"));
        let json: serde_json::Value = serde_json::from_str(&text).unwrap();
        assert_eq!(json["code"], 11);
        assert_eq!(json["status"], "OUT_OF_RANGE");
        assert_eq!(json["message"], "too big");
    }
}

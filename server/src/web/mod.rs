//! The browser transport (`--web-addr`): an HTTP/1 listener with a
//! WebSocket at [`STREAM_PATH`] and the live page at `/`.
//!
//! Why a second transport: browsers cannot open a client-streaming gRPC
//! call (gRPC-Web has no client streaming), but every browser speaks
//! WebSocket. The socket carries exactly the `Stream` RPC's messages, one
//! binary WebSocket message per `StreamRequest` or `StreamResponse`, and
//! is served by the same handler ([`crate::stream::run`]), so validation,
//! the pipeline, the per-client limits, auth, metrics and session tokens
//! are the gRPC ones by construction, not by copy. [`socket`] adapts a
//! WebSocket to that handler; [`page`] serves the built page; [`export`]
//! turns the page's take into a BVH, C3D, TRC or replay file.
//!
//! A browser is an untrusted peer that may stall or vanish, so this
//! listener keeps the gRPC listener's bounds: connections are admitted
//! through the same [`ConnectionTable`] (`--max-connections`,
//! `--max-connections-per-peer` count both listeners together) and memory
//! budget (a socket counts as a connection and its one stream), a
//! connection must send its request head within `--handshake-timeout`,
//! and the socket itself is bounded by [`socket`] (message size, queues,
//! pings and an idle timeout). The WebSocket framing is tungstenite's
//! (through axum); nothing here parses HTTP or WebSocket bytes.

pub mod config;
pub mod export;
mod page;
mod socket;
pub mod token;

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use axum::extract::ConnectInfo;
use axum::routing::{get, post};
use axum::Router;
use hyper::body::Incoming;
use hyper_util::rt::{TokioIo, TokioTimer};
use tokio::net::{TcpListener, TcpStream};
use tokio::task::JoinHandle;
use tokio_util::sync::CancellationToken;
use tokio_util::task::TaskTracker;
use tower::Service;

use crate::auth::BearerAuth;
use crate::budget::{Budget, WEBSOCKET_CONNECTION_BYTES};
use crate::metrics;
use crate::state::AppState;
use crate::transport::{canonical_peer, ConnectionTable, Permit};

pub use config::{WebArgs, WebConfig};

/// Where the WebSocket is served.
pub const STREAM_PATH: &str = "/v1/stream";

/// Where the page posts a take to get it back as a file ([`export`]).
pub const EXPORT_PATH: &str = "/v1/export/{format}";

/// The WebSocket subprotocol clients offer (and the server selects).
pub const PROTOCOL: &str = "blapose.v1";

/// The running transport: its address, and a task that ends once it
/// stopped accepting (at shutdown) and every socket has ended.
#[derive(Debug)]
pub struct WebServer {
    /// The bound address.
    pub local_addr: SocketAddr,
    /// Ends when the transport is done.
    pub task: JoinHandle<()>,
}

/// Bind `config.addr` and serve until `shutdown` is cancelled; sockets
/// open then end through the stream handler's draining (answers first,
/// then UNAVAILABLE).
pub async fn start(
    config: &WebConfig,
    state: Arc<AppState>,
    auth: BearerAuth,
    connections: ConnectionTable,
    handshake_timeout: Duration,
    shutdown: CancellationToken,
) -> std::io::Result<WebServer> {
    let addr = config.addr;
    let listener = TcpListener::bind(addr).await.map_err(|e| {
        std::io::Error::new(
            e.kind(),
            format!("cannot listen on {addr} (--web-addr): {e}"),
        )
    })?;
    let local_addr = listener.local_addr()?;
    let tracker = TaskTracker::new();
    let budget = state.budget.clone();
    let exports = Router::new()
        .route(EXPORT_PATH, post(export::export))
        .with_state(Arc::new(export::Exports::new(auth.clone())));
    let app = Router::new()
        .route(STREAM_PATH, get(socket::upgrade))
        .with_state(Arc::new(socket::Endpoint::new(
            state,
            auth,
            config,
            tracker.clone(),
        )))
        .merge(exports)
        .fallback_service(page::service(&config.dir));
    tracing::info!(
        addr = %local_addr,
        "browser transport at http://{local_addr}/ (WebSocket {STREAM_PATH})"
    );
    let task = tokio::spawn(accept(
        listener,
        app,
        connections,
        budget,
        handshake_timeout,
        shutdown,
        tracker,
    ));
    Ok(WebServer { local_addr, task })
}

/// Admit connections until shutdown, then wait for every one to end.
async fn accept(
    listener: TcpListener,
    app: Router,
    connections: ConnectionTable,
    budget: Arc<Budget>,
    handshake_timeout: Duration,
    shutdown: CancellationToken,
    tracker: TaskTracker,
) {
    loop {
        let (tcp, peer) = tokio::select! {
            _ = shutdown.cancelled() => break,
            accepted = listener.accept() => match accepted {
                Ok(accepted) => accepted,
                Err(e) => {
                    // Out of file descriptors and the like: wait a little
                    // rather than spin.
                    tracing::warn!(error = %e, "web: accept failed");
                    tokio::time::sleep(Duration::from_millis(50)).await;
                    continue;
                }
            },
        };
        // As on the gRPC listener: `::ffff:a.b.c.d` is a.b.c.d for every
        // per-address rule, and answers are small and latency matters more
        // than packets.
        let peer = canonical_peer(peer);
        let _ = tcp.set_nodelay(true);
        let permit = match connections.admit_within(peer.ip(), &budget, WEBSOCKET_CONNECTION_BYTES)
        {
            Ok(permit) => Arc::new(permit),
            Err(refusal) => {
                metrics::connection_refused(refusal.flag());
                tracing::warn!(%peer, limit = refusal.flag(), "web: connection refused at accept");
                continue;
            }
        };
        tracker.spawn(connection(
            tcp,
            peer,
            permit,
            app.clone(),
            handshake_timeout,
            shutdown.clone(),
        ));
    }
    drop(listener);
    tracker.close();
    tracker.wait().await;
}

/// Serve one HTTP/1 connection. The permit travels with the request, so
/// an upgraded WebSocket keeps its connection's place in the table after
/// this HTTP connection is done.
async fn connection(
    tcp: TcpStream,
    peer: SocketAddr,
    permit: Arc<Permit>,
    app: Router,
    handshake_timeout: Duration,
    shutdown: CancellationToken,
) {
    let service = hyper::service::service_fn(move |mut request: hyper::Request<Incoming>| {
        request.extensions_mut().insert(ConnectInfo(peer));
        request.extensions_mut().insert(permit.clone());
        app.clone().call(request)
    });
    let mut http = hyper::server::conn::http1::Builder::new();
    http.timer(TokioTimer::new())
        .header_read_timeout(handshake_timeout);
    let conn = http
        .serve_connection(TokioIo::new(tcp), service)
        .with_upgrades();
    tokio::pin!(conn);
    let served = tokio::select! {
        served = conn.as_mut() => served,
        _ = shutdown.cancelled() => {
            conn.as_mut().graceful_shutdown();
            conn.await
        }
    };
    if let Err(e) = served {
        tracing::debug!(%peer, error = %e, "web: connection ended with an error");
    }
}

//! Serving handshaken connections with hyper's HTTP/2, each watched for
//! idleness, age and control-frame floods.
//!
//! tonic's own serve loop can end a connection only when the whole server
//! shuts down (or at a fixed age), so a connection that sent its preface
//! and then only answers keepalive PINGs was held for ever. Here each
//! connection is hyper's HTTP/2 connection serving tonic's routes (the
//! same settings tonic gives it), beside a watchdog that starts hyper's
//! graceful shutdown (GOAWAY: no new streams, open ones finish) when the
//! connection has had no open stream for `--max-connection-idle`, when it
//! reaches `--max-connection-age`, or at once when it floods control
//! frames ([`crate::frames`]); it is cut if still open after
//! `--max-connection-age-grace` (a flooding one after 250 ms). Server
//! shutdown sends every connection GOAWAY and waits for them, as tonic
//! does. Each close is a log line and a count in
//! `blapose_connections_closed_total{reason}` (`idle`, `max_age`,
//! `control_frame_flood`).

use std::convert::Infallible;
use std::future::Future;
use std::pin::{pin, Pin};
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::Duration;

use hyper::body::Incoming;
use hyper::server::conn::http2;
use hyper_util::rt::{TokioExecutor, TokioIo, TokioTimer};
use hyper_util::service::TowerToHyperService;
use tokio::time::Instant;
use tokio_stream::StreamExt;
use tokio_util::sync::CancellationToken;
use tonic::body::Body;
use tonic::codegen::http::{Request, Response};
use tonic::codegen::Service;
use tonic::service::Routes;
use tonic::transport::server::{Connected, TcpConnectInfo};

use crate::activity::{Activity, StreamGuard};
use crate::budget::{Budget, BudgetStream};
use crate::metrics;
use crate::protect::Protection;
use crate::transport::Conn;

/// How long a flooding connection has between its GOAWAY and being cut.
const FLOOD_GRACE: Duration = Duration::from_millis(250);

/// The HTTP/2 settings every connection is served with.
#[derive(Debug, Clone, Copy)]
pub struct Http2Settings {
    /// SETTINGS_MAX_CONCURRENT_STREAMS.
    pub max_concurrent_streams: u32,
    /// SETTINGS_MAX_HEADER_LIST_SIZE.
    pub max_header_list_bytes: u32,
    /// Keepalive PING interval and the wait for its answer.
    pub keepalive: (Duration, Duration),
}

fn builder(s: Http2Settings) -> http2::Builder<TokioExecutor> {
    let mut b = http2::Builder::new(TokioExecutor::new());
    b.timer(TokioTimer::new())
        .max_concurrent_streams(s.max_concurrent_streams)
        .max_header_list_size(s.max_header_list_bytes)
        .keep_alive_interval(Some(s.keepalive.0))
        .keep_alive_timeout(s.keepalive.1);
    b
}

/// Serve every connection `incoming` yields with `routes` until `shutdown`
/// is cancelled; then send each GOAWAY and return once all are closed.
pub async fn serve<I>(
    incoming: I,
    routes: Routes,
    settings: Http2Settings,
    protection: Protection,
    budget: Arc<Budget>,
    shutdown: CancellationToken,
) where
    I: tokio_stream::Stream<Item = std::io::Result<Conn>>,
{
    let builder = builder(settings);
    let (closing_tx, closing_rx) = tokio::sync::watch::channel(());
    {
        // Dropped when accepting stops, which closes the listener.
        let mut incoming = pin!(incoming);
        loop {
            let conn = tokio::select! {
                conn = incoming.next() => conn,
                _ = shutdown.cancelled() => break,
            };
            let conn = match conn {
                Some(Ok(conn)) => conn,
                Some(Err(_)) => continue,
                None => break,
            };
            let service = Tracked {
                routes: routes.clone(),
                info: conn.connect_info(),
                activity: conn.activity(),
                budget: budget.clone(),
            };
            tokio::spawn(serve_one(
                conn,
                service,
                builder.clone(),
                protection,
                closing_rx.clone(),
            ));
        }
    }
    let _ = closing_tx.send(());
    drop(closing_rx);
    closing_tx.closed().await;
}

/// Why the watchdog closes a connection (the metric's `reason`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Close {
    Idle,
    MaxAge,
    Flood,
}

impl Close {
    fn reason(self) -> &'static str {
        match self {
            Close::Idle => "idle",
            Close::MaxAge => "max_age",
            Close::Flood => "control_frame_flood",
        }
    }
}

/// Resolves with the first reason to close the connection.
async fn watchdog(activity: &Activity, p: Protection) -> Close {
    let flood = activity.flood_raised();
    let timers = async {
        loop {
            let now = Instant::now();
            let age_at = p.max_connection_age.map(|a| activity.born() + a);
            if age_at.is_some_and(|at| at <= now) {
                return Close::MaxAge;
            }
            let idle_at = p
                .max_connection_idle
                .and_then(|idle| activity.idle_since().map(|since| since + idle));
            if idle_at.is_some_and(|at| at <= now) {
                return Close::Idle;
            }
            // Streams come and go meanwhile: look again at the earliest
            // deadline, and at least once a second.
            let next = [age_at, idle_at, Some(now + Duration::from_secs(1))]
                .into_iter()
                .flatten()
                .min()
                .unwrap_or(now);
            tokio::time::sleep_until(next).await;
        }
    };
    tokio::select! {
        _ = flood => Close::Flood,
        close = timers => close,
    }
}

async fn serve_one(
    conn: Conn,
    service: Tracked,
    builder: http2::Builder<TokioExecutor>,
    protection: Protection,
    mut closing: tokio::sync::watch::Receiver<()>,
) {
    let activity = conn.activity();
    let peer = service.info.remote_addr;
    let mut connection =
        pin!(builder.serve_connection(TokioIo::new(conn), TowerToHyperService::new(service)));
    let mut watch = pin!(watchdog(&activity, protection));
    let mut watching = true;
    let mut draining = false;
    let mut cut_at: Option<Instant> = None;
    loop {
        let cut = async {
            match cut_at {
                Some(at) => tokio::time::sleep_until(at).await,
                None => std::future::pending().await,
            }
        };
        tokio::select! {
            done = &mut connection => {
                if let Err(e) = done {
                    tracing::debug!(?peer, error = %e, "connection ended");
                }
                break;
            }
            close = &mut watch, if watching => {
                watching = false;
                metrics::connection_closed(close.reason());
                let grace = match close {
                    Close::Flood => FLOOD_GRACE,
                    _ => protection.max_connection_age_grace,
                };
                tracing::info!(?peer, reason = close.reason(), "closing connection (GOAWAY)");
                connection.as_mut().graceful_shutdown();
                cut_at = Some(Instant::now() + grace);
            }
            _ = closing.changed(), if !draining => {
                draining = true;
                connection.as_mut().graceful_shutdown();
            }
            _ = cut => {
                tracing::info!(?peer, "connection cut after its grace period");
                break;
            }
        }
    }
    drop(closing);
}

/// tonic's routes with each request's connection info (what
/// `Request::remote_addr` reads) and its stream counted in the
/// connection's [`Activity`] until its response body ends.
#[derive(Clone)]
struct Tracked {
    routes: Routes,
    info: TcpConnectInfo,
    activity: Arc<Activity>,
    budget: Arc<Budget>,
}

type BoxFuture<T> = Pin<Box<dyn Future<Output = T> + Send>>;

impl Service<Request<Incoming>> for Tracked {
    type Response = Response<Body>;
    type Error = Infallible;
    type Future = BoxFuture<Result<Response<Body>, Infallible>>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), Infallible>> {
        Service::<Request<Body>>::poll_ready(&mut self.routes, cx)
    }

    fn call(&mut self, request: Request<Incoming>) -> Self::Future {
        // Past the memory budget or the address's streams, the stream is
        // answered at once and holds nothing.
        let admitted = match self.budget.stream(self.info.remote_addr.map(|a| a.ip())) {
            Ok(admitted) => admitted,
            Err(e) => {
                let refused = e.to_status().into_http::<Body>();
                return Box::pin(async move { Ok(refused) });
            }
        };
        let guard = (self.activity.stream(), admitted);
        let mut request = request.map(Body::new);
        request.extensions_mut().insert(self.info.clone());
        let call = self.routes.call(request);
        Box::pin(async move {
            let response = call.await?;
            Ok(response.map(|body| {
                Body::new(Guarded {
                    body,
                    _guard: guard,
                })
            }))
        })
    }
}

/// A response body that keeps its stream counted until it ends.
struct Guarded {
    body: Body,
    _guard: (StreamGuard, BudgetStream),
}

impl http_body::Body for Guarded {
    type Data = tonic::codegen::Bytes;
    type Error = tonic::Status;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<http_body::Frame<Self::Data>, Self::Error>>> {
        Pin::new(&mut self.body).poll_frame(cx)
    }

    fn is_end_stream(&self) -> bool {
        self.body.is_end_stream()
    }

    fn size_hint(&self) -> http_body::SizeHint {
        self.body.size_hint()
    }
}

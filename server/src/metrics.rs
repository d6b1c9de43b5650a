//! Prometheus metrics: every name the server exports, the helpers that
//! record them, and the `/metrics` HTTP exporter.
//!
//! Recording goes through the `metrics` facade, so the hot path costs a few
//! atomic operations and nothing at all when no recorder is installed (tests,
//! embedders that disable metrics). The recorder is process-global: the
//! first server in a process that asks for an exporter installs it; a later
//! one gets [`MetricsError::AlreadyInstalled`].

use std::net::SocketAddr;
use std::sync::OnceLock;
use std::time::Duration;

use metrics::{
    counter, describe_counter, describe_gauge, describe_histogram, gauge, histogram, Unit,
};
use metrics_exporter_prometheus::{BuildError, Matcher, PrometheusBuilder};

/// Frames answered, by outcome (`ok` or `error`).
pub const FRAMES: &str = "blapose_frames_total";
/// Sessions currently held (attached or detached).
pub const SESSIONS: &str = "blapose_sessions";
/// Streams currently attached to a session.
pub const STREAMS: &str = "blapose_streams_attached";
/// Session lifecycle events, by `event` (opened, resumed, closed, evicted).
pub const SESSION_EVENTS: &str = "blapose_session_events_total";
/// Frames per batched GRU step.
pub const BATCH_SIZE: &str = "blapose_batch_size";
/// Time a frame waited in the batcher queue.
pub const QUEUE_LATENCY: &str = "blapose_queue_latency_seconds";
/// Time one batched GRU step took.
pub const COMPUTE_LATENCY: &str = "blapose_compute_latency_seconds";
/// Time from receiving a frame to its answer being ready.
pub const FRAME_LATENCY: &str = "blapose_frame_latency_seconds";
/// Frames waiting in the batcher queue.
pub const QUEUE_DEPTH: &str = "blapose_queue_depth";
/// Errors returned, by gRPC `code` and `rpc`.
pub const ERRORS: &str = "blapose_errors_total";
/// Offline sequences adjusted, by `model`.
pub const OFFLINE_SEQUENCES: &str = "blapose_offline_sequences_total";
/// Time one offline request's model run took.
pub const OFFLINE_LATENCY: &str = "blapose_offline_latency_seconds";
/// Frames lifted by the server lifter.
pub const LIFTED_FRAMES: &str = "blapose_lifted_frames_total";
/// Time one batched server-lifter call took.
pub const LIFT_LATENCY: &str = "blapose_lift_latency_seconds";
/// TCP connections held (admitted, handshaking or served).
pub const CONNECTIONS: &str = "blapose_connections";
/// Connections refused at accept, by `limit` (the flag's name).
pub const CONNECTIONS_REFUSED: &str = "blapose_connections_refused_total";
/// Connections closed before they reached HTTP/2, by `reason`.
pub const CONNECTIONS_CLOSED: &str = "blapose_connections_closed_total";
/// Gauge: a configured limit in force, by `limit` (its flag's name).
pub const LIMIT: &str = "blapose_limit";
/// Gauge: memory the server accounts for its clients (the budget's sum).
pub const MEMORY_ACCOUNTED: &str = "blapose_memory_accounted_bytes";
/// Gauge: ended sessions remembered (so their tokens cannot revive them).
pub const ENDED_SESSIONS: &str = "blapose_ended_sessions";
/// Counter: requests or frames refused by a per-client limit or a token
/// rule, by `limit`.
pub const LIMITED: &str = "blapose_limited_total";

const LATENCY_BUCKETS: [f64; 14] = [
    50e-6, 100e-6, 250e-6, 500e-6, 1e-3, 2e-3, 5e-3, 10e-3, 20e-3, 50e-3, 100e-3, 250e-3, 1.0, 5.0,
];
const BATCH_BUCKETS: [f64; 12] = [
    1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0, 128.0, 256.0, 512.0, 1024.0, 4096.0,
];

/// Why the exporter could not start.
#[derive(Debug, thiserror::Error)]
pub enum MetricsError {
    /// Another server in this process already installed the recorder.
    #[error("a metrics recorder is already installed in this process")]
    AlreadyInstalled,
    /// The exporter could not be built (e.g. the address is in use).
    #[error("cannot start the metrics exporter on {addr}: {source}")]
    Build {
        /// The requested address.
        addr: SocketAddr,
        /// The cause.
        #[source]
        source: BuildError,
    },
}

static INSTALLED: OnceLock<SocketAddr> = OnceLock::new();

/// Install the global recorder and serve `/metrics` on `addr` (on the
/// current tokio runtime).
pub fn install_exporter(addr: SocketAddr) -> Result<(), MetricsError> {
    if INSTALLED.get().is_some() {
        return Err(MetricsError::AlreadyInstalled);
    }
    let build = |source| MetricsError::Build { addr, source };
    let (recorder, exporter) = PrometheusBuilder::new()
        .with_http_listener(addr)
        .set_buckets_for_metric(Matcher::Suffix("_seconds".into()), &LATENCY_BUCKETS)
        .map_err(build)?
        .set_buckets_for_metric(Matcher::Full(BATCH_SIZE.into()), &BATCH_BUCKETS)
        .map_err(build)?
        .build()
        .map_err(build)?;
    if INSTALLED.set(addr).is_err() || metrics::set_global_recorder(recorder).is_err() {
        return Err(MetricsError::AlreadyInstalled);
    }
    tokio::spawn(async move {
        if let Err(e) = exporter.await {
            tracing::error!(error = ?e, "metrics exporter stopped");
        }
    });
    describe();
    // Gauges appear in the exposition only once set: start them at zero.
    gauge!(SESSIONS).set(0.0);
    gauge!(STREAMS).set(0.0);
    gauge!(QUEUE_DEPTH).set(0.0);
    gauge!(CONNECTIONS).set(0.0);
    Ok(())
}

fn describe() {
    describe_counter!(FRAMES, "Frames answered, by outcome (ok, error).");
    describe_gauge!(SESSIONS, "Sessions currently held (attached or detached).");
    describe_gauge!(STREAMS, "Streams currently attached to a session.");
    describe_counter!(
        SESSION_EVENTS,
        "Session lifecycle events (opened, resumed, closed, evicted)."
    );
    describe_histogram!(BATCH_SIZE, "Frames per batched GRU step.");
    describe_histogram!(
        QUEUE_LATENCY,
        Unit::Seconds,
        "Time a frame waited in the batcher queue."
    );
    describe_histogram!(
        COMPUTE_LATENCY,
        Unit::Seconds,
        "Time one batched GRU step took."
    );
    describe_histogram!(
        FRAME_LATENCY,
        Unit::Seconds,
        "Time from receiving a frame to its answer."
    );
    describe_gauge!(QUEUE_DEPTH, "Frames waiting in the batcher queue.");
    describe_gauge!(LIMIT, "Configured limits in force, by flag name.");
    describe_counter!(
        LIMITED,
        "Refusals by a per-client limit or session token rule, by limit."
    );
    describe_counter!(ERRORS, "Errors returned, by gRPC code and rpc.");
    describe_counter!(OFFLINE_SEQUENCES, "Offline sequences adjusted, by model.");
    describe_histogram!(
        OFFLINE_LATENCY,
        Unit::Seconds,
        "Model time of one offline request."
    );
    describe_counter!(
        LIFTED_FRAMES,
        "Frames the server lifter lifted (sessions opened with server_lifter)."
    );
    describe_histogram!(
        LIFT_LATENCY,
        Unit::Seconds,
        "Time one batched server-lifter call took."
    );
    describe_gauge!(CONNECTIONS, "TCP connections held (handshaking or served).");
    describe_counter!(
        CONNECTIONS_REFUSED,
        "Connections refused at accept, by the limit (flag) that refused them."
    );
    describe_counter!(
        CONNECTIONS_CLOSED,
        "Connections closed before HTTP/2 (handshake timeout, wrong protocol), by reason."
    );
}

/// `held` TCP connections now.
pub fn connections(held: usize) {
    gauge!(CONNECTIONS).set(held as f64);
}

/// A connection was refused by the limit whose flag is `limit`.
pub fn connection_refused(limit: &'static str) {
    counter!(CONNECTIONS_REFUSED, "limit" => limit).increment(1);
}

/// A connection was closed before HTTP/2 for `reason`.
pub fn connection_closed(reason: &'static str) {
    counter!(CONNECTIONS_CLOSED, "reason" => reason).increment(1);
}

/// A session was opened; `held` sessions now.
pub fn session_opened(held: usize) {
    counter!(SESSION_EVENTS, "event" => "opened").increment(1);
    gauge!(SESSIONS).set(held as f64);
}

/// A session was resumed.
pub fn session_resumed() {
    counter!(SESSION_EVENTS, "event" => "resumed").increment(1);
}

/// A session was closed explicitly; `held` sessions remain.
pub fn session_closed(held: usize) {
    counter!(SESSION_EVENTS, "event" => "closed").increment(1);
    gauge!(SESSIONS).set(held as f64);
}

/// A detached session expired; `held` sessions remain.
pub fn session_evicted(held: usize) {
    counter!(SESSION_EVENTS, "event" => "evicted").increment(1);
    gauge!(SESSIONS).set(held as f64);
}

/// Export the configured value of the limit `name` (its flag's name).
pub fn limit(name: &'static str, value: usize) {
    gauge!(LIMIT, "limit" => name).set(value as f64);
}

/// `bytes` accounted against the memory budget.
pub fn memory_accounted(bytes: usize) {
    gauge!(MEMORY_ACCOUNTED).set(bytes as f64);
}

/// `count` ended sessions remembered.
pub fn ended_sessions(count: usize) {
    gauge!(ENDED_SESSIONS).set(count as f64);
}

/// Something was refused by the limit or token rule `name`.
pub fn limited(name: &'static str) {
    counter!(LIMITED, "limit" => name).increment(1);
}

/// A stream attached (`+1`) or detached (`-1`).
pub fn stream_attached(delta: i8) {
    if delta >= 0 {
        gauge!(STREAMS).increment(1.0);
    } else {
        gauge!(STREAMS).decrement(1.0);
    }
}

/// One batched step ran.
pub fn batch(size: usize, compute: Duration, queue_depth: usize) {
    histogram!(BATCH_SIZE).record(size as f64);
    histogram!(COMPUTE_LATENCY).record(compute.as_secs_f64());
    gauge!(QUEUE_DEPTH).set(queue_depth as f64);
}

/// A frame waited `wait` in the queue.
pub fn queue_wait(wait: Duration) {
    histogram!(QUEUE_LATENCY).record(wait.as_secs_f64());
}

/// A frame was answered successfully after `latency`.
pub fn frame_ok(latency: Duration) {
    counter!(FRAMES, "outcome" => "ok").increment(1);
    histogram!(FRAME_LATENCY).record(latency.as_secs_f64());
}

/// A frame was answered with an error.
pub fn frame_error(code: tonic::Code) {
    counter!(FRAMES, "outcome" => "error").increment(1);
    error(code, "Stream");
}

/// An error status (stream-ending or per-frame) was returned.
pub fn error(code: tonic::Code, rpc: &'static str) {
    counter!(ERRORS, "code" => code_name(code), "rpc" => rpc).increment(1);
}

/// The server lifter lifted `frames` frames in one call.
pub fn lift(frames: usize, elapsed: Duration) {
    counter!(LIFTED_FRAMES).increment(frames as u64);
    histogram!(LIFT_LATENCY).record(elapsed.as_secs_f64());
}

/// An offline request finished.
pub fn offline(model: &'static str, elapsed: Duration) {
    counter!(OFFLINE_SEQUENCES, "model" => model).increment(1);
    histogram!(OFFLINE_LATENCY, "model" => model).record(elapsed.as_secs_f64());
}

/// Counts the unary methods' error statuses in [`ERRORS`], including those
/// tonic answers before the handler runs (an undecodable or oversized
/// `AdjustSequence` request): a unary error is a trailers-only response,
/// its status in the headers, so it is read there once for all. Streams
/// count their own statuses (`stream.rs`), which travel in trailers.
#[derive(Debug, Clone)]
pub struct ErrorCounting<S> {
    inner: S,
}

impl<S> ErrorCounting<S> {
    /// Count `inner`'s unary errors.
    pub fn new(inner: S) -> Self {
        Self { inner }
    }
}

impl<S: tonic::server::NamedService> tonic::server::NamedService for ErrorCounting<S> {
    const NAME: &'static str = S::NAME;
}

impl<S, B, R> tonic::codegen::Service<tonic::codegen::http::Request<B>> for ErrorCounting<S>
where
    S: tonic::codegen::Service<
        tonic::codegen::http::Request<B>,
        Response = tonic::codegen::http::Response<R>,
    >,
    S::Future: Send + 'static,
{
    type Response = S::Response;
    type Error = S::Error;
    type Future = tonic::codegen::BoxFuture<S::Response, S::Error>;

    fn poll_ready(
        &mut self,
        cx: &mut std::task::Context<'_>,
    ) -> std::task::Poll<Result<(), Self::Error>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, request: tonic::codegen::http::Request<B>) -> Self::Future {
        let rpc = unary_rpc(request.uri().path());
        let future = self.inner.call(request);
        Box::pin(async move {
            let response = future.await?;
            let status = response
                .headers()
                .get("grpc-status")
                .map(|v| tonic::Code::from_bytes(v.as_bytes()));
            if let (Some(rpc), Some(code)) = (rpc, status) {
                if code != tonic::Code::Ok {
                    error(code, rpc);
                }
            }
            Ok(response)
        })
    }
}

/// The `rpc` label of a unary method's path; `None` for the stream (and
/// anything else).
fn unary_rpc(path: &str) -> Option<&'static str> {
    match path.rsplit('/').next()? {
        "AdjustSequence" => Some("AdjustSequence"),
        "CloseSession" => Some("CloseSession"),
        "ModelInfo" => Some("ModelInfo"),
        _ => None,
    }
}

/// The canonical upper-case name of a gRPC code (as in the gRPC spec).
pub fn code_name(code: tonic::Code) -> &'static str {
    use tonic::Code as C;
    match code {
        C::Ok => "OK",
        C::Cancelled => "CANCELLED",
        C::Unknown => "UNKNOWN",
        C::InvalidArgument => "INVALID_ARGUMENT",
        C::DeadlineExceeded => "DEADLINE_EXCEEDED",
        C::NotFound => "NOT_FOUND",
        C::AlreadyExists => "ALREADY_EXISTS",
        C::PermissionDenied => "PERMISSION_DENIED",
        C::ResourceExhausted => "RESOURCE_EXHAUSTED",
        C::FailedPrecondition => "FAILED_PRECONDITION",
        C::Aborted => "ABORTED",
        C::OutOfRange => "OUT_OF_RANGE",
        C::Unimplemented => "UNIMPLEMENTED",
        C::Internal => "INTERNAL",
        C::Unavailable => "UNAVAILABLE",
        C::DataLoss => "DATA_LOSS",
        C::Unauthenticated => "UNAUTHENTICATED",
    }
}

/// A recorder of a test's own, to install on the test's thread
/// (`metrics::with_local_recorder`, `metrics::set_default_local_recorder`):
/// the process-wide one is the exporter's, once per process.
#[cfg(test)]
pub(crate) fn test_recorder() -> metrics_exporter_prometheus::PrometheusRecorder {
    PrometheusBuilder::new().build_recorder()
}

/// What `recorder` counted in `blapose_limited_total{limit}`.
#[cfg(test)]
pub(crate) fn limited_count(
    recorder: &metrics_exporter_prometheus::PrometheusRecorder,
    limit: &str,
) -> u64 {
    let needle = format!("{LIMITED}{{limit=\"{limit}\"}} ");
    recorder
        .handle()
        .render()
        .lines()
        .find_map(|l| l.strip_prefix(&needle)?.trim().parse().ok())
        .unwrap_or(0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_test_recorder_counts_refusals_by_limit() {
        let recorder = test_recorder();
        metrics::with_local_recorder(&recorder, || {
            limited("max_sessions");
            limited("max_sessions");
        });
        assert_eq!(limited_count(&recorder, "max_sessions"), 2);
        assert_eq!(limited_count(&recorder, "queue_capacity"), 0);
    }

    #[test]
    fn code_names_follow_the_grpc_spec() {
        assert_eq!(code_name(tonic::Code::InvalidArgument), "INVALID_ARGUMENT");
        assert_eq!(
            code_name(tonic::Code::ResourceExhausted),
            "RESOURCE_EXHAUSTED"
        );
        assert_eq!(code_name(tonic::Code::Unauthenticated), "UNAUTHENTICATED");
    }

    #[test]
    fn buckets_are_sorted() {
        assert!(LATENCY_BUCKETS.windows(2).all(|w| w[0] < w[1]));
        assert!(BATCH_BUCKETS.windows(2).all(|w| w[0] < w[1]));
    }
}

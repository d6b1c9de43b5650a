//! `--spawn`: a blapose server in this process, on loopback, with the
//! embedded default weights, so the load test needs no set-up at all.
//!
//! The server is the library's own [`blapose_server::spawn`] (the same code
//! the binary runs), bound to an ephemeral `127.0.0.1` port. Its Prometheus
//! exporter is process-global and wants an address rather than a bound
//! listener, so for an ephemeral metrics port we ask the OS for a free one
//! and hand that over (retrying if another process grabs it meanwhile).

use std::net::{Ipv4Addr, SocketAddr, TcpListener as StdListener};
use std::time::Duration;

use blapose_server::metrics::MetricsError;
use blapose_server::{ServerConfig, ServerError, ServerHandle, WeightsSource};

/// Server settings the load test exposes.
#[derive(Debug, Clone)]
pub struct SpawnOptions {
    /// Metrics listen address; port 0 picks a free port; `None`: no metrics.
    pub metrics_addr: Option<SocketAddr>,
    /// Maximum sessions held.
    pub max_sessions: usize,
    /// Maximum frames per batched step.
    pub max_batch: usize,
    /// Longest wait for a fuller batch.
    pub max_queue_delay: Duration,
    /// Threads of one batched step.
    pub compute_threads: usize,
    /// Per-stream in-flight bound on the server side.
    pub max_inflight_per_stream: usize,
    /// Storage precision of the GRU weights.
    pub weight_precision: blapose_model::Precision,
}

impl Default for SpawnOptions {
    /// The server's own defaults, metrics on a free loopback port.
    fn default() -> Self {
        let d = ServerConfig::default();
        SpawnOptions {
            metrics_addr: Some((Ipv4Addr::LOCALHOST, 0).into()),
            max_sessions: d.max_sessions,
            max_batch: d.max_batch,
            max_queue_delay: d.max_queue_delay,
            compute_threads: d.compute_threads,
            max_inflight_per_stream: d.max_inflight_per_stream,
            weight_precision: d.weight_precision,
        }
    }
}

/// A server running in this process.
#[derive(Debug)]
pub struct Spawned {
    /// The running server.
    pub handle: ServerHandle,
    /// gRPC URL (`http://127.0.0.1:PORT`).
    pub url: String,
    /// Metrics URL, if the exporter runs.
    pub metrics_url: Option<String>,
}

impl Spawned {
    /// Shut the server down (bounded by its 2 s grace period).
    pub async fn shutdown(self) -> Result<(), ServerError> {
        self.handle.shutdown().await
    }
}

/// Start the server; returns once it serves (weights loaded, warmed up).
pub async fn spawn(options: &SpawnOptions) -> Result<Spawned, ServerError> {
    const ATTEMPTS: usize = 3;
    let mut attempt = 0;
    loop {
        attempt += 1;
        let metrics_addr = match options.metrics_addr {
            Some(a) if a.port() == 0 => Some(free_port(a)?),
            other => other,
        };
        let config = ServerConfig {
            metrics_addr,
            weights: WeightsSource::Embedded,
            bigru_weights: WeightsSource::Embedded,
            max_sessions: options.max_sessions,
            max_batch: options.max_batch,
            max_queue_delay: options.max_queue_delay,
            compute_threads: options.compute_threads,
            max_inflight_per_stream: options.max_inflight_per_stream,
            weight_precision: options.weight_precision,
            shutdown_grace: Duration::from_secs(2),
            ..ServerConfig::default()
        };
        let listener = tokio::net::TcpListener::bind((Ipv4Addr::LOCALHOST, 0)).await?;
        match blapose_server::spawn(config, listener).await {
            Ok(handle) => {
                return Ok(Spawned {
                    url: format!("http://{}", handle.local_addr()),
                    metrics_url: metrics_addr.map(|a| format!("http://{a}/metrics")),
                    handle,
                })
            }
            // The free port was taken between asking and binding: try another.
            Err(ServerError::Metrics(MetricsError::Build { .. }))
                if attempt < ATTEMPTS && options.metrics_addr.is_some_and(|a| a.port() == 0) => {}
            Err(e) => return Err(e),
        }
    }
}

/// A port on `addr`'s interface that is free right now.
fn free_port(addr: SocketAddr) -> std::io::Result<SocketAddr> {
    StdListener::bind(addr)?.local_addr()
}

//! blapose-server: BLAPose bone-length adjustment as a streaming gRPC
//! service.
//!
//! Clients open a session per person/camera stream and send, frame by
//! frame, 2D keypoints and the 3D pose their lifting model produced. The
//! server keeps each session's GRU state, batches the frames of all sessions
//! into one GRU step at a time (Triton-style "oldest" sequence batching), and
//! answers each frame with the pose rebuilt from the lifter's bone directions
//! and the session's running bone-length estimate. The contract is
//! `proto/blapose/v1/blapose.proto` (crate `blapose-proto`).
//!
//! Optionally (`--lifter-weights`) the server also runs a trained causal
//! lifter, so a client with only a 2D detector can open a session with
//! `server_lifter` and send keypoints alone: each frame's pose is then lifted
//! from the session's window of recent keypoints (batched across sessions
//! like the GRU step) and adjusted as a client's pose would be. Without the
//! flag nothing about serving changes.
//!
//! Sessions and offline requests that send their camera's calibration
//! (`CameraCalibration`) are served by a second, camera-aware model pair
//! ([`models::Family::CameraAware`]), fed their keypoints as those weights'
//! input contract says (`blapose_model::input`: undistorted, rectified to a
//! level camera at the same place, scaled to the floor), in the same
//! batcher as every other session.
//!
//! A frame's way through the server, one module per stage:
//! [`validate`] (checks and typed errors) -> [`prepare`] (missing joints,
//! the server lifter, the camera the model reads through) -> [`batch`] (the
//! queue; only batching) -> [`step`] (the batched GRU step) -> [`answer`]
//! (lengths, adjustment, token snapshots). [`stream`] drives a streamed
//! frame through them, [`offline`] a whole sequence (`AdjustSequence`,
//! which shares prepare and answer).
//!
//! Around them: [`config`] (flags and [`ServerConfig`]), [`session`] (store,
//! TTL, resume), [`backend`] (the model-execution trait), [`engine`]
//! (blapose-model's fast engines behind it), [`models`] (weights, their
//! input contract, providers), [`service`] (the tonic service), [`auth`],
//! [`metrics`], [`shutdown`], [`telemetry`], [`token`] (portable session
//! state: session tokens), [`testing`] (test support).
//!
//! Embedding (tests, load generators): [`spawn`] starts a server on a bound
//! listener and returns a [`ServerHandle`]; [`serve`] runs until a future
//! completes.

pub mod answer;
pub mod auth;
pub mod backend;
pub mod batch;
pub mod config;
pub mod engine;
pub mod error;
#[cfg(test)]
mod fakes;
pub mod metrics;
pub mod models;
pub mod motion;
pub mod offline;
pub mod prepare;
pub mod quota;
pub mod restore_check;
mod retired;
pub mod service;
pub mod session;
pub mod session_id;
pub mod shutdown;
pub mod step;
pub mod stream;
pub mod telemetry;
pub mod testing;
pub mod token;
pub mod transport;
pub mod validate;

use std::future::Future;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use blapose_proto::v1::pose_adjustment_server::PoseAdjustmentServer;
use tokio::net::TcpListener;
use tokio::task::JoinHandle;
use tokio_util::sync::CancellationToken;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::Server;
use tonic_health::ServingStatus;

pub use blapose_model::input::ModelInput;
pub use config::CameraAwareWeights;
pub use config::{Cli, HealthCheckTls, LogFormat, ServerConfig, TlsFiles, WeightsSource};
pub use error::ServerError;
pub use models::{
    embedded_bigru, embedded_bigru_rectified, embedded_gru, embedded_gru_rectified, Family,
    LoadedLifter, ModelProvider, WeightsProvider,
};

use auth::BearerAuth;
use batch::{Batcher, BatcherConfig};
use offline::OfflineRunner;
use service::{AppState, PoseService};
use session::SessionStore;

/// A running server.
#[derive(Debug)]
pub struct ServerHandle {
    local_addr: SocketAddr,
    shutdown: CancellationToken,
    /// `None` once the task's result was collected by [`ServerHandle::wait`].
    task: Option<JoinHandle<Result<(), ServerError>>>,
}

impl ServerHandle {
    /// The address the gRPC server listens on.
    pub fn local_addr(&self) -> SocketAddr {
        self.local_addr
    }

    /// Graceful shutdown: stop accepting, answer every frame already
    /// received, end streams with UNAVAILABLE, stop the batcher; returns when
    /// done (or after the configured grace period).
    pub async fn shutdown(mut self) -> Result<(), ServerError> {
        self.shutdown.cancel();
        match self.task.take() {
            Some(task) => join(task).await,
            None => Ok(()),
        }
    }

    /// Wait until the server stops on its own (an error) or through its
    /// shutdown token. Cancel-safe; later calls return `Ok(())`.
    pub async fn wait(&mut self) -> Result<(), ServerError> {
        let Some(task) = self.task.as_mut() else {
            return Ok(());
        };
        let result = join(task).await;
        self.task = None;
        result
    }

    /// A token that starts shutdown when cancelled.
    pub fn shutdown_token(&self) -> CancellationToken {
        self.shutdown.clone()
    }
}

async fn join<J>(task: J) -> Result<(), ServerError>
where
    J: Future<Output = Result<Result<(), ServerError>, tokio::task::JoinError>>,
{
    match task.await {
        Ok(result) => result,
        Err(e) => Err(ServerError::Task(e.to_string())),
    }
}

/// Load the configured weights and start serving on `listener`; returns
/// once the model is warmed up and the server accepts calls (health
/// SERVING).
pub async fn spawn(
    config: ServerConfig,
    listener: TcpListener,
) -> Result<ServerHandle, ServerError> {
    let (gru, bigru, camera_aware, threads, precision) = (
        config.weights.clone(),
        config.bigru_weights.clone(),
        config.camera_aware.clone(),
        config.compute_threads,
        config.weight_precision,
    );
    let provider = tokio::task::spawn_blocking(move || -> Result<_, ServerError> {
        let provider = WeightsProvider::load(Family::Default, &gru, &bigru, threads, precision)?;
        Ok(match camera_aware {
            Some(w) => provider.with_camera_aware(WeightsProvider::load(
                Family::CameraAware,
                &w.gru,
                &w.bigru,
                threads,
                precision,
            )?),
            None => provider,
        })
    })
    .await
    .map_err(|e| ServerError::Task(e.to_string()))??;
    let families = [
        (false, Some(&provider)),
        (true, provider.camera_aware_models()),
    ];
    for (camera_aware, p) in families {
        let Some(p) = p else { continue };
        tracing::info!(
            camera_aware,
            gru = %p.gru().origin,
            gru_sha256 = %p.gru().sha256,
            bigru = %p.bigru().origin,
            bigru_sha256 = %p.bigru().sha256,
            "weights loaded"
        );
    }
    spawn_with_provider(config, listener, Arc::new(provider)).await
}

/// [`spawn`] with any [`ModelProvider`] (e.g. a fake model in tests).
pub async fn spawn_with_provider(
    config: ServerConfig,
    listener: TcpListener,
    provider: Arc<dyn ModelProvider>,
) -> Result<ServerHandle, ServerError> {
    let local_addr = listener.local_addr()?;
    // A bad lifter file is a start-up error, before anything is served.
    let lifter = match config.lifter_weights.clone() {
        Some(path) => {
            let lifter = tokio::task::spawn_blocking(move || LoadedLifter::load(&path))
                .await
                .map_err(|e| ServerError::Task(e.to_string()))??;
            tracing::info!(
                lifter = lifter.name(),
                receptive_field = lifter.lifter.receptive_field(),
                params = lifter.lifter.params(),
                weights = %lifter.origin,
                sha256 = %lifter.sha256,
                "server lifter loaded"
            );
            Some(Arc::new(lifter))
        }
        None => None,
    };
    if let Some(addr) = config.metrics_addr {
        metrics::install_exporter(addr)?;
        tracing::info!(%addr, "metrics at http://{addr}/metrics");
    }

    // Build and warm up the online backend (and the lifter) off the async
    // workers.
    let batcher_config = BatcherConfig {
        max_batch: config.max_batch.max(1),
        max_queue_delay: config.max_queue_delay,
        queue_capacity: config.queue_capacity.max(1),
    };
    let online_provider = provider.clone();
    let batcher_lifter = lifter.clone();
    let batcher = tokio::task::spawn_blocking(move || -> Result<Batcher, ServerError> {
        let backends = step::OnlineBackends {
            default: online_provider.online()?,
            camera_aware: online_provider
                .camera_aware()
                .map(|p| p.online())
                .transpose()?,
        };
        Ok(step::start(backends, batcher_config, batcher_lifter)?)
    })
    .await
    .map_err(|e| ServerError::Task(e.to_string()))??;
    let batcher = Arc::new(batcher);

    let tokens = config.session_key.clone().map(|key| {
        service::Tokens::new(
            key,
            config.token_every,
            provider.as_ref(),
            lifter.as_deref(),
        )
    });
    let (store, purge_guard) = SessionStore::with_memory(
        config.max_sessions.max(1),
        config.session_ttl,
        // Ended sessions are remembered only where tokens could revive them.
        config
            .session_key
            .as_ref()
            .map_or(std::time::Duration::ZERO, |_| config.token_ttl),
    );
    let shutdown = CancellationToken::new();
    let state = Arc::new(AppState {
        store,
        batcher: batcher.clone(),
        offline: OfflineRunner::new(provider.clone(), config.compute_threads),
        provider,
        lifter,
        draining: shutdown.child_token(),
        open_timeout: config.open_timeout,
        max_inflight_per_stream: config.max_inflight_per_stream.max(1),
        max_message_bytes: config.max_message_bytes,
        tokens,
        stature: Arc::new(models::embedded_stature_model()?),
        limits: service::limits(&config),
    });

    let (health, health_service) = tonic_health::server::health_reporter();
    // Warm-up ran inside step::start, so the model is ready now.
    health.set_service_status("", ServingStatus::Serving).await;
    health
        .set_service_status(blapose_proto::SERVICE_NAME, ServingStatus::Serving)
        .await;

    let reflection_v1 = tonic_reflection::server::Builder::configure()
        .register_encoded_file_descriptor_set(blapose_proto::FILE_DESCRIPTOR_SET)
        .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
        .build_v1()
        .map_err(|e| ServerError::Reflection(e.to_string()))?;
    let reflection_v1alpha = tonic_reflection::server::Builder::configure()
        .register_encoded_file_descriptor_set(blapose_proto::FILE_DESCRIPTOR_SET)
        .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
        .build_v1alpha()
        .map_err(|e| ServerError::Reflection(e.to_string()))?;

    let pose = PoseAdjustmentServer::new(PoseService::new(state.clone()))
        .max_decoding_message_size(config.max_message_bytes);
    let pose = metrics::ErrorCounting::new(pose);
    let pose = InterceptedService::new(pose, BearerAuth::new(config.auth_token.as_deref()));

    // TLS is terminated in `transport` (under the handshake deadline).
    let tls = config
        .tls
        .as_ref()
        .map(transport::tls_acceptor)
        .transpose()
        .map_err(ServerError::Tls)?;
    export_limits(&config);
    let mut builder = Server::builder()
        .http2_keepalive_interval(Some(Duration::from_secs(30)))
        .http2_keepalive_timeout(Some(Duration::from_secs(20)))
        .max_concurrent_streams(config.max_concurrent_streams)
        .http2_max_header_list_size(config.max_header_list_bytes);
    let router = builder
        .add_service(health_service)
        .add_service(reflection_v1)
        .add_service(reflection_v1alpha)
        .add_service(pose);

    let incoming = transport::incoming(
        listener,
        transport::ConnectionTable::new(config.connection_limits),
        tls,
        shutdown.clone(),
    );
    let token = shutdown.clone();
    let grace = config.shutdown_grace;
    let task = tokio::spawn(async move {
        let signal_health = health.clone();
        let signal_token = token.clone();
        let server = router.serve_with_incoming_shutdown(incoming, async move {
            signal_token.cancelled().await;
            tracing::info!("shutting down: draining in-flight frames");
            signal_health
                .set_service_status("", ServingStatus::NotServing)
                .await;
            signal_health
                .set_service_status(blapose_proto::SERVICE_NAME, ServingStatus::NotServing)
                .await;
        });
        tokio::pin!(server);
        let served = tokio::select! {
            r = &mut server => r.map_err(ServerError::from),
            _ = async { token.cancelled().await; tokio::time::sleep(grace).await } => {
                tracing::warn!(?grace, "shutdown grace period expired; dropping remaining connections");
                Ok(())
            }
        };
        // Streams are done (or abandoned): answer anything still queued and
        // stop the batcher thread.
        token.cancel();
        let b = batcher.clone();
        let joined = tokio::task::spawn_blocking(move || b.join()).await;
        drop(purge_guard);
        drop(state);
        tracing::info!("server stopped");
        served?;
        joined.map_err(|e| ServerError::Task(e.to_string()))
    });
    tracing::info!(addr = %local_addr, "serving blapose.v1");
    Ok(ServerHandle {
        local_addr,
        shutdown,
        task: Some(task),
    })
}

/// Export the configured transport limits (`blapose_limit{limit}`, the
/// gauge the per-client limits share; the handshake timeout in ms).
fn export_limits(config: &ServerConfig) {
    let c = &config.connection_limits;
    metrics::limit(
        "max_concurrent_streams",
        config.max_concurrent_streams as usize,
    );
    metrics::limit(
        "max_header_list_bytes",
        config.max_header_list_bytes as usize,
    );
    metrics::limit("max_connections", c.max_connections);
    metrics::limit("max_connections_per_peer", c.max_connections_per_peer);
    metrics::limit(
        "handshake_timeout_ms",
        usize::try_from(c.handshake_timeout.as_millis()).unwrap_or(usize::MAX),
    );
}

/// Run a server on `listener` until `shutdown` completes, then shut down
/// gracefully. Returns early with the error if the server fails.
pub async fn serve(
    config: ServerConfig,
    listener: TcpListener,
    shutdown: impl Future<Output = ()>,
) -> Result<(), ServerError> {
    let mut handle = spawn(config, listener).await?;
    tokio::select! {
        r = handle.wait() => r,
        _ = shutdown => handle.shutdown().await,
    }
}

/// Query `grpc.health.v1` at `addr` (overall status). `Ok(true)` when
/// SERVING. With `tls`, connect over TLS and verify the server's certificate
/// against `tls.ca` for the name `tls.domain` (see [`Cli::health_check_tls`]).
pub async fn probe_health(
    addr: SocketAddr,
    tls: Option<&HealthCheckTls>,
) -> Result<bool, ServerError> {
    use tonic_health::pb::{
        health_check_response::ServingStatus as S, health_client::HealthClient, HealthCheckRequest,
    };
    let host = if addr.ip().is_unspecified() {
        SocketAddr::new(
            if addr.is_ipv4() {
                std::net::Ipv4Addr::LOCALHOST.into()
            } else {
                std::net::Ipv6Addr::LOCALHOST.into()
            },
            addr.port(),
        )
    } else {
        addr
    };
    // TLS goes through blapose-tls's connector (a pinned self-signed
    // certificate is accepted even when marked CA:TRUE), on an http://
    // endpoint so that tonic adds no TLS of its own.
    let endpoint = tonic::transport::Endpoint::from_shared(format!("http://{host}"))
        .map_err(ServerError::from)?
        .connect_timeout(Duration::from_secs(3))
        .timeout(Duration::from_secs(3));
    let checked = async {
        let channel = match tls {
            Some(tls) => {
                let pem = std::fs::read(&tls.ca).map_err(|e| {
                    ServerError::Tls(format!("cannot read {}: {e}", tls.ca.display()))
                })?;
                let connector = blapose_tls::TlsConnector::new(&pem, Some(tls.domain.clone()))
                    .map_err(|e| ServerError::Tls(format!("{}: {e}", tls.ca.display())))?;
                endpoint.connect_with_connector(connector).await?
            }
            None => endpoint.connect().await?,
        };
        HealthClient::new(channel)
            .check(HealthCheckRequest {
                service: String::new(),
            })
            .await
            .map_err(|s| ServerError::Task(format!("health check failed: {s}")))
    }
    .await;
    match checked {
        Ok(response) => Ok(response.into_inner().status == S::Serving as i32),
        Err(e)
            if tls.is_none()
                && blapose_tls::probe(&host.ip().to_string(), host.port()).await
                    == blapose_tls::Speaks::Tls =>
        {
            Err(ServerError::Tls(format!(
                "the server speaks TLS: run --health-check with the server's TLS settings \
                 (--tls-cert / BLAPOSE_TLS_CERT, and --tls-ca, --tls-domain if its certificate \
                 needs them) ({e})"
            )))
        }
        Err(e) => Err(e),
    }
}

//! The wiring: load the models, start the batcher thread, build the
//! services and their layers, accept connections, and shut it all down in
//! order.
//!
//! Everything a frame goes through lives in the stage modules; this module
//! only connects them, once, at start-up (as text-embeddings-inference's
//! `router/src/server.rs` does): [`spawn`] loads the configured weights,
//! [`spawn_with_provider`] starts a server with any [`ModelProvider`] (a
//! fake one in tests), and the returned [`ServerHandle`] stops it.
//! Shutdown drains: stop accepting, answer every frame already received,
//! end streams with UNAVAILABLE, then stop the batcher thread.

use std::future::Future;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use blapose_proto::v1::pose_adjustment_server::PoseAdjustmentServer;
use tokio::net::TcpListener;
use tokio::task::JoinHandle;
use tokio_util::sync::CancellationToken;
use tonic::service::interceptor::InterceptedService;
use tonic::service::Routes;
use tonic_health::server::HealthReporter;
use tonic_health::ServingStatus;

use crate::auth::BearerAuth;
use crate::batch::{Batcher, BatcherConfig};
use crate::config::{ServerConfig, WeightsSource};
use crate::connection::{self, Http2Settings};
use crate::error::ServerError;
use crate::metrics;
use crate::models::{self, Family, LoadedLifter, ModelProvider, WeightsProvider};
use crate::offline::OfflineRunner;
use crate::pipeline;
use crate::service::PoseService;
use crate::session::SessionStore;
use crate::state::{self, AppState};
use crate::step::OnlineBackends;
use crate::transport;
use crate::web;

/// A running server.
#[derive(Debug)]
pub struct ServerHandle {
    local_addr: SocketAddr,
    web_addr: Option<SocketAddr>,
    shutdown: CancellationToken,
    /// `None` once the task's result was collected by [`ServerHandle::wait`].
    task: Option<JoinHandle<Result<(), ServerError>>>,
}

impl ServerHandle {
    /// The address the gRPC server listens on.
    pub fn local_addr(&self) -> SocketAddr {
        self.local_addr
    }

    /// The address of the browser transport (`--web-addr`), if on.
    pub fn web_addr(&self) -> Option<SocketAddr> {
        self.web_addr
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
            weight_precision = %p.precision().precision,
            why = p.precision().reason,
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
    let lifter = match config.lifter.clone() {
        Some(source) => load_lifter(source).await?.map(Arc::new),
        None => None,
    };
    if let Some(addr) = config.metrics_addr {
        metrics::install_exporter(addr)?;
        tracing::info!(%addr, "metrics at http://{addr}/metrics");
    }
    let batcher = Arc::new(start_batcher(&config, provider.clone(), lifter.clone()).await?);
    let (store, purge_guard) = SessionStore::with_limits(
        config.max_sessions.max(1),
        config.session_ttl,
        // Ended sessions are remembered only where tokens could revive them.
        config
            .session_key
            .as_ref()
            .map_or(Duration::ZERO, |_| config.token_ttl),
        crate::session::EndedLimits::with_max(config.protection.max_ended_sessions),
    );
    let shutdown = CancellationToken::new();
    let budget = crate::budget::Budget::new(
        config
            .protection
            .memory_budget
            .unwrap_or_else(crate::budget::default_budget),
        config.protection.max_streams_per_peer,
        config.trusted_proxies.clone(),
    );
    metrics::limit("memory_budget_bytes", budget.budget());
    // In the log too: the default depends on the machine (or cgroup).
    tracing::info!(
        memory_budget_mb = budget.budget() >> 20,
        max_streams_per_peer = config.protection.max_streams_per_peer,
        "memory budget"
    );
    let state = Arc::new(AppState {
        store,
        batcher: batcher.clone(),
        offline: OfflineRunner::new(provider.clone(), config.compute_threads),
        tokens: config.session_key.clone().map(|key| {
            state::Tokens::new(
                key,
                config.token_every,
                provider.as_ref(),
                lifter.as_deref(),
            )
        }),
        provider,
        lifter,
        draining: shutdown.child_token(),
        open_timeout: config.open_timeout,
        max_inflight_per_stream: config.max_inflight_per_stream.max(1),
        max_message_bytes: config.max_message_bytes,
        stature: Arc::new(models::embedded_stature_model()?),
        limits: state::limits(&config),
        budget: budget.clone(),
    });
    tokio::spawn(sample_budget(state.clone(), shutdown.clone()));
    let (health, routes) = routes(&config, state.clone()).await?;

    // TLS is terminated in `transport` (under the handshake deadline).
    let tls = config
        .tls
        .as_ref()
        .map(transport::tls_acceptor)
        .transpose()
        .map_err(ServerError::Tls)?;
    // What one HTTP/2 connection may hold, as the budget counts it.
    let connection_bytes = crate::budget::http2_connection_bytes(config.max_concurrent_streams);
    let connection_limits = connection_limits_within(&config, &budget, connection_bytes);
    export_limits(&config, &connection_limits);
    let protection = config.protection;
    protection.export();
    // One table for both listeners: a peer's connections count together.
    let connections = transport::ConnectionTable::new(connection_limits);
    let web = match &config.web {
        Some(web_config) => {
            if config.tls.is_some() {
                tracing::warn!("the browser transport (--web-addr) speaks plain HTTP, not TLS");
            }
            Some(
                web::start(
                    web_config,
                    state.clone(),
                    BearerAuth::new(config.auth_token.as_deref()),
                    connections.clone(),
                    config.connection_limits.handshake_timeout,
                    shutdown.clone(),
                )
                .await?,
            )
        }
        None => None,
    };
    let web_addr = web.as_ref().map(|w| w.local_addr);
    let incoming = transport::incoming(
        listener,
        connections,
        tls,
        shutdown.clone(),
        protection.max_control_frames_per_second,
        transport::ConnectionCost {
            budget: budget.clone(),
            bytes: connection_bytes,
        },
    );
    let settings = Http2Settings {
        max_concurrent_streams: config.max_concurrent_streams,
        max_header_list_bytes: config.max_header_list_bytes,
        keepalive: (Duration::from_secs(30), Duration::from_secs(20)),
    };
    let token = shutdown.clone();
    let grace = config.shutdown_grace;
    let task = tokio::spawn(async move {
        let signal_health = health.clone();
        let signal_token = token.clone();
        tokio::spawn(async move {
            signal_token.cancelled().await;
            tracing::info!("shutting down: draining in-flight frames");
            set_health(&signal_health, ServingStatus::NotServing).await;
        });
        // Both transports drain (the browser's sockets as streams do).
        let serve_token = token.clone();
        let server = async move {
            connection::serve(incoming, routes, settings, protection, budget, serve_token).await;
            if let Some(web) = web {
                let _ = web.task.await;
            }
        };
        tokio::pin!(server);
        let served: Result<(), ServerError> = tokio::select! {
            () = &mut server => Ok(()),
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
        web_addr,
        shutdown,
        task: Some(task),
    })
}

/// Sample what the memory budget accounts from the store and the batcher
/// (`crate::budget`) every 100 ms until shutdown. Holds the state weakly,
/// so it never keeps a stopped server alive.
async fn sample_budget(state: Arc<AppState>, shutdown: CancellationToken) {
    let state = Arc::downgrade(&state);
    loop {
        {
            let Some(s) = state.upgrade() else { return };
            s.budget
                .sample(s.store.len(), s.batcher.queue_len(), s.store.ended_bytes());
        }
        tokio::select! {
            _ = shutdown.cancelled() => return,
            _ = tokio::time::sleep(Duration::from_millis(100)) => {}
        }
    }
}

/// Load and log the server lifter (embedded or `--lifter-weights`), off
/// the async workers; `None` when the build embedded none.
async fn load_lifter(source: WeightsSource) -> Result<Option<LoadedLifter>, ServerError> {
    let loaded = tokio::task::spawn_blocking(move || LoadedLifter::load(&source))
        .await
        .map_err(|e| ServerError::Task(e.to_string()))??;
    let Some(lifter) = loaded else {
        tracing::warn!("no server lifter: this build embedded none and --lifter-weights names none; server_lifter sessions are refused");
        return Ok(None);
    };
    tracing::info!(
        lifter = lifter.name(),
        receptive_field = lifter.lifter.receptive_field(),
        params = lifter.lifter.params(),
        weights = %lifter.origin,
        sha256 = %lifter.sha256,
        "server lifter loaded"
    );
    Ok(Some(lifter))
}

/// Build and warm up the online backends (and the lifter) off the async
/// workers, and start the batcher thread.
async fn start_batcher(
    config: &ServerConfig,
    provider: Arc<dyn ModelProvider>,
    lifter: Option<Arc<LoadedLifter>>,
) -> Result<Batcher, ServerError> {
    let batcher_config = BatcherConfig {
        max_batch: config.max_batch.max(1),
        max_mixed_batch: config.max_mixed_batch,
        max_queue_delay: config.max_queue_delay,
        queue_capacity: config.queue_capacity.max(1),
    };
    tokio::task::spawn_blocking(move || -> Result<Batcher, ServerError> {
        let backends = OnlineBackends {
            default: provider.online()?,
            camera_aware: provider.camera_aware().map(|p| p.online()).transpose()?,
        };
        Ok(pipeline::start(backends, batcher_config, lifter)?)
    })
    .await
    .map_err(|e| ServerError::Task(e.to_string()))?
}

/// Set the overall and the service's health status.
async fn set_health(health: &HealthReporter, status: ServingStatus) {
    health.set_service_status("", status).await;
    health
        .set_service_status(blapose_proto::SERVICE_NAME, status)
        .await;
}

/// The gRPC services (health, reflection, the pose service behind its
/// metrics and auth layers) on one set of routes, health already SERVING:
/// the warm-up ran in [`pipeline::start`], so the models are ready.
async fn routes(
    config: &ServerConfig,
    state: Arc<AppState>,
) -> Result<(HealthReporter, Routes), ServerError> {
    let (health, health_service) = tonic_health::server::health_reporter();
    set_health(&health, ServingStatus::Serving).await;

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

    let pose = PoseAdjustmentServer::new(PoseService::new(state))
        .max_decoding_message_size(config.max_message_bytes);
    let pose = metrics::ErrorCounting::new(pose);
    let pose = InterceptedService::new(pose, BearerAuth::new(config.auth_token.as_deref()));

    // The HTTP/2 settings (streams, header list, keepalive) are
    // `connection`'s, which serves these routes on each connection.
    let routes = Routes::new(health_service)
        .add_service(reflection_v1)
        .add_service(reflection_v1alpha)
        .add_service(pose)
        .prepare();
    Ok((health, routes))
}

/// The connection limits, `--max-connections` lowered where connections
/// of `each` bytes would pass half the memory budget
/// ([`crate::budget::connections_within`]; logged when it is).
fn connection_limits_within(
    config: &ServerConfig,
    budget: &crate::budget::Budget,
    each: usize,
) -> transport::ConnectionLimits {
    let mut limits = config.connection_limits;
    let within = crate::budget::connections_within(budget.budget(), limits.max_connections, each);
    if within < limits.max_connections {
        tracing::warn!(
            max_connections = within,
            configured = limits.max_connections,
            connection_kb = each >> 10,
            "--max-connections lowered: connections may hold at most half of --memory-budget"
        );
        limits.max_connections = within;
        limits.max_connections_per_peer = limits.max_connections_per_peer.min(within);
    }
    limits
}

/// Export the transport limits in force (`blapose_limit{limit}`, the
/// gauge the per-client limits share; the handshake timeout in ms).
fn export_limits(config: &ServerConfig, c: &transport::ConnectionLimits) {
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

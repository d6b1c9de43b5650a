//! What every request handler shares: the session store, the batcher,
//! the offline runner, the models, the limits and the token settings.
//!
//! Apart from [`crate::service`] (the tonic glue) and [`crate::stream`]
//! (one stream's protocol), which both read it, so neither imports the
//! other for it. Built once by [`crate::server`].

use std::sync::Arc;

use blapose_model::input::ModelInput;
use blapose_model::stature::StatureModel;
use blapose_proto::v1 as pb;
use tokio_util::sync::CancellationToken;

use crate::batch::Batcher;
use crate::models::{LoadedLifter, ModelProvider};
use crate::offline::OfflineRunner;
use crate::quota::{self, Limits};
use crate::session::SessionStore;
use crate::token::{self, SessionKey};

/// Shared server state.
pub struct AppState {
    /// Sessions.
    pub store: SessionStore,
    /// The online batcher.
    pub batcher: Arc<Batcher>,
    /// Offline requests.
    pub offline: OfflineRunner,
    /// Models, for ModelInfo.
    pub provider: Arc<dyn ModelProvider>,
    /// The server lifter (`--lifter-weights`), if any.
    pub lifter: Option<Arc<LoadedLifter>>,
    /// Cancelled when shutdown begins: streams stop reading and drain.
    pub draining: CancellationToken,
    /// How long a new stream may take to send its open or resume.
    pub open_timeout: std::time::Duration,
    /// Per-stream pipelining bound.
    pub max_inflight_per_stream: usize,
    /// Request size limit (reported by ModelInfo).
    pub max_message_bytes: usize,
    /// Session tokens (`--session-key`); `None`: none issued or accepted.
    pub tokens: Option<Tokens>,
    /// The stature model subjects are answered with (embedded).
    pub stature: Arc<StatureModel>,
    pub limits: Limits,
    /// The memory budget (`crate::budget`).
    pub budget: Arc<crate::budget::Budget>,
}

/// What issuing and restoring session tokens needs: the key, how often to
/// send one, and the ids of the weights a session's state belongs to.
#[derive(Debug, Clone)]
pub struct Tokens {
    /// The shared key.
    pub key: SessionKey,
    /// Send a token every this many frames (0: open/resume and on request).
    pub every: u64,
    /// The default family's online GRU weights.
    pub default_weights: [u8; 32],
    /// The camera-aware family's online GRU weights, if served.
    pub camera_weights: Option<[u8; 32]>,
    /// The server lifter's weights and receptive field, if any.
    pub lifter: Option<([u8; 32], usize)>,
}

impl Tokens {
    /// Tokens for a server with these models.
    pub fn new(
        key: SessionKey,
        every: u64,
        provider: &dyn ModelProvider,
        lifter: Option<&LoadedLifter>,
    ) -> Self {
        let online = |descriptions: Vec<pb::ModelDescription>, camera_aware: bool| {
            descriptions
                .iter()
                .find(|d| d.model == pb::Model::OnlineGru as i32 && d.camera_aware == camera_aware)
                .map(|d| token::weights_id(&d.weights_sha256))
        };
        let all = provider.describe();
        let default_weights = online(all.clone(), false).unwrap_or_else(|| token::weights_id(""));
        let camera_weights = online(all, true).or_else(|| {
            provider
                .camera_aware()
                .and_then(|p| online(p.describe(), true).or_else(|| online(p.describe(), false)))
        });
        Self {
            key,
            every,
            default_weights,
            camera_weights,
            lifter: lifter.map(|l| (token::weights_id(&l.sha256), l.lifter.receptive_field())),
        }
    }

    /// The weights id of a session's family.
    pub fn weights_for(&self, camera: bool) -> Option<[u8; 32]> {
        if camera {
            self.camera_weights
        } else {
            Some(self.default_weights)
        }
    }
}

/// The per-client limits a configuration asks for (defaults filled in:
/// each client may hold a share of the session table and of the frame
/// queue), exported as `blapose_limit` gauges.
pub fn limits(config: &crate::config::ServerConfig) -> Limits {
    let sessions_per_client = config
        .max_sessions_per_client
        .unwrap_or_else(|| quota::default_share(config.max_sessions))
        .min(config.max_sessions.max(1));
    let queued_per_client = config
        .max_queued_frames_per_client
        .unwrap_or_else(|| quota::default_share(config.queue_capacity))
        .min(config.queue_capacity.max(1));
    let limits = Limits::new(
        sessions_per_client,
        config.max_frames_per_session,
        queued_per_client,
        config.token_ttl,
        config.client_header.as_deref(),
        config.trusted_proxies.clone(),
    );
    crate::metrics::limit("max_sessions_per_client", limits.sessions_per_client);
    crate::metrics::limit("max_frames_per_session", limits.frames_per_session);
    crate::metrics::limit("max_queued_frames_per_client", limits.queued_per_client);
    crate::metrics::limit(
        "token_ttl_seconds",
        usize::try_from(limits.token_ttl.as_secs()).unwrap_or(usize::MAX),
    );
    limits
}

impl AppState {
    /// The input contract of the server's camera-aware models, what a
    /// calibration is checked against and read through (`None` without
    /// any).
    pub fn camera_models(&self) -> Option<ModelInput> {
        self.provider
            .camera_aware()
            .map(|models| models.model_input())
    }
}

impl std::fmt::Debug for AppState {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("AppState")
            .field("sessions", &self.store.len())
            .field("batcher", &self.batcher.config())
            .finish()
    }
}

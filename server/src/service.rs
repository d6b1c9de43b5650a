//! The `blapose.v1.PoseAdjustment` gRPC service: the glue between tonic and
//! the session store, the batcher and the offline runner.
//!
//! Handlers stay thin: the stream protocol lives in [`crate::stream`], whole
//! sequences in [`crate::offline`], and what both do with a frame in the
//! stages [`crate::validate`], [`crate::prepare`], [`crate::batch`],
//! [`crate::step`] and [`crate::answer`].

use std::sync::Arc;

use blapose_core::layouts::KeypointLayout;
use blapose_core::skeleton::{BONE_NAMES, JOINT_NAMES};
use blapose_model::input::ModelInput;
use blapose_model::stature::StatureModel;
use blapose_proto::v1 as pb;
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tokio_stream::{Stream, StreamExt};
use tokio_util::sync::CancellationToken;
use tonic::{Request, Response, Status, Streaming};

use crate::batch::Batcher;
use crate::models::{LoadedLifter, ModelProvider};
use crate::offline::OfflineRunner;
use crate::quota::{self, Limits};
use crate::session::SessionStore;
use crate::stream::{self, session_status};
use crate::token::{self, SessionKey};
use crate::validate;

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

/// The tonic service.
#[derive(Debug, Clone)]
pub struct PoseService {
    state: Arc<AppState>,
}

impl PoseService {
    /// A service over `state`.
    pub fn new(state: Arc<AppState>) -> Self {
        Self { state }
    }
}

/// An error answer of a unary call. It is counted in `blapose_errors_total`
/// by [`crate::metrics::ErrorCounting`], with the errors tonic answers before the
/// handler runs (an undecodable request).
fn fail<T>(status: Status, _rpc: &'static str) -> Result<T, Status> {
    Err(status)
}

impl PoseService {
    /// `ModelInfo.accepts`: what this server does with the optional inputs.
    fn accepts(&self) -> Vec<String> {
        let mut out = vec![
            format!(
                "confidence: a joint below {} is missing (not read; held at its last detection)",
                validate::MISSING_CONFIDENCE
            ),
            format!(
                "subject: stature {}-{} m (and sex), answered with the stature regression's \
                 lengths ({} ANSUR II people)",
                blapose_model::stature::MIN_STATURE_M,
                blapose_model::stature::MAX_STATURE_M,
                self.state.stature.pooled.people
            ),
        ];
        if self.state.camera_models().is_some() {
            out.push(
                "camera: a calibration with the camera's height, served by the camera-aware \
                 models within their trained range"
                    .into(),
            );
        }
        if self.state.lifter.is_some() {
            out.push("server_lifter: 2D keypoints only; the server lifts the poses".into());
        }
        out
    }
}

/// A stream's responses, unboxed from the channel ([`stream::Outbound`]).
pub type ResponseStream =
    std::pin::Pin<Box<dyn Stream<Item = Result<pb::StreamResponse, Status>> + Send>>;

#[tonic::async_trait]
impl pb::pose_adjustment_server::PoseAdjustment for PoseService {
    type StreamStream = ResponseStream;

    async fn stream(
        &self,
        request: Request<Streaming<pb::StreamRequest>>,
    ) -> Result<Response<Self::StreamStream>, Status> {
        let client = self.state.limits.client(&request);
        let inbound = request.into_inner();
        // A little slack beyond the in-flight bound so answers never wait on
        // the channel while the stream task is still reading.
        let (tx, rx) = mpsc::channel(self.state.max_inflight_per_stream.max(1) + 2);
        tokio::spawn(stream::run(self.state.clone(), client, inbound, tx));
        Ok(Response::new(Box::pin(
            ReceiverStream::new(rx).map(|r| r.map(|response| *response)),
        )))
    }

    async fn close_session(
        &self,
        request: Request<pb::CloseSessionRequest>,
    ) -> Result<Response<pb::CloseSessionResponse>, Status> {
        match self.state.store.close(&request.get_ref().session_id) {
            Ok(snapshot) => {
                tracing::info!(session = %request.get_ref().session_id, frames_seen = snapshot.frames_seen, "session closed by CloseSession");
                Ok(Response::new(pb::CloseSessionResponse {
                    frames_seen: snapshot.frames_seen,
                    bone_lengths: snapshot
                        .bone_lengths
                        .map(|l| l.to_vec())
                        .unwrap_or_default(),
                }))
            }
            Err(e) => fail(session_status(e), "CloseSession"),
        }
    }

    async fn adjust_sequence(
        &self,
        request: Request<pb::AdjustSequenceRequest>,
    ) -> Result<Response<pb::AdjustSequenceResponse>, Status> {
        if self.state.draining.is_cancelled() {
            return fail(
                Status::unavailable("the server is shutting down"),
                "AdjustSequence",
            );
        }
        match self
            .state
            .offline
            .respond(request.get_ref(), &self.state.stature)
            .await
        {
            Ok(response) => Ok(Response::new(response)),
            Err(status) => fail(status, "AdjustSequence"),
        }
    }

    async fn model_info(
        &self,
        _request: Request<pb::ModelInfoRequest>,
    ) -> Result<Response<pb::ModelInfoResponse>, Status> {
        let config = self.state.batcher.config();
        Ok(Response::new(pb::ModelInfoResponse {
            models: self.state.provider.describe(),
            layouts: KeypointLayout::ALL
                .iter()
                .map(|l| validate::layout_to_proto(*l) as i32)
                .collect(),
            server_version: env!("CARGO_PKG_VERSION").to_string(),
            protocol: "blapose.v1".to_string(),
            joint_names: JOINT_NAMES.iter().map(|s| s.to_string()).collect(),
            bone_names: BONE_NAMES.iter().map(|s| s.to_string()).collect(),
            max_sessions: u32::try_from(self.state.store.max_sessions()).unwrap_or(u32::MAX),
            session_ttl_ms: u64::try_from(self.state.store.ttl().as_millis()).unwrap_or(u64::MAX),
            max_batch: u32::try_from(config.max_batch).unwrap_or(u32::MAX),
            max_message_bytes: self.state.max_message_bytes as u64,
            lifter: self.state.lifter.as_ref().map(|l| l.describe()),
            accepts: self.accepts(),
        }))
    }
}

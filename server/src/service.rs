//! The `blapose.v1.PoseAdjustment` gRPC service: the glue between tonic and
//! the session store, the batcher and the offline runner.
//!
//! Handlers stay thin: the stream protocol lives in [`crate::stream`], whole
//! sequences in [`crate::offline`], and what both do with a frame in the
//! stages, in the order a frame flows: [`crate::validate`],
//! [`crate::batch`], then on the batcher thread ([`crate::pipeline`])
//! [`crate::prepare`], [`crate::step`] and [`crate::answer`].

use std::sync::Arc;

use blapose_core::layouts::KeypointLayout;
use blapose_core::skeleton::{BONE_NAMES, JOINT_NAMES};
use blapose_proto::v1 as pb;
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tokio_stream::{Stream, StreamExt};
use tonic::{Request, Response, Status, Streaming};

use crate::attach::session_status;
use crate::state::AppState;
use crate::stream;
use crate::validate;

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

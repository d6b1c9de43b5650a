//! Connecting to a blapose server and the unary calls.
//!
//! A [`Client`] is a cheap-to-clone handle on one HTTP/2 connection (tonic
//! multiplexes every session's stream over it). Connecting retries with
//! exponential backoff because the usual failure is a server that is still
//! loading its weights; every unary call has a deadline so a wedged server
//! cannot hang a CLI forever. Authentication and TLS are connection
//! settings ([`crate::config`]), applied to every call.

use blapose_core::{BoneLengths, ModelKind, Pose};
use blapose_data::replay::{CameraCalibration, Sequence, Subject};
use blapose_proto::v1 as pb;
use tonic::transport::Channel;

use crate::config::{build_endpoint, new_stub, next_backoff, CallMetadata, ClientConfig, Stub};
use crate::error::ClientError;
use crate::session::Session;
use crate::types::wire::{lengths_from_flat, model_from_answer, pose_from_flat, ToProto};
use crate::types::{InputFormat, ModelInfo, SessionSummary, SessionToken};

/// How to open a session (see [`Client::open_session_with`]). Build it
/// from `SessionOptions::default()` (`..Default::default()` in a literal)
/// so code keeps compiling when options are added.
#[derive(Debug, Clone, Copy, Default)]
pub struct SessionOptions<'a> {
    /// Label for the server's logs.
    pub label: Option<&'a str>,
    /// Let the server lift the poses from the keypoints (it must have been
    /// started with a lifter; see `ModelInfo::lifter`).
    pub server_lifter: bool,
    /// The camera's calibration: `Some` asks for the camera-aware online
    /// model (the server must have one, see
    /// [`ModelDescription::camera_aware`](crate::ModelDescription::camera_aware));
    /// `None` (the default) gets the default model.
    pub camera: Option<CameraCalibration>,
    /// The person's stature (and sex): `Some` answers with the stature
    /// regression's lengths for it ([`Subject`]).
    pub subject: Option<Subject>,
    /// `Some(frames per second)` (0: 50) runs the causal motion stage on
    /// every answer: directions smoothed, the pelvis placed
    /// ([`AdjustedFrame::root`](crate::AdjustedFrame::root)).
    pub motion: Option<f32>,
}

impl<'a> SessionOptions<'a> {
    /// These options with `camera` as the session's calibration.
    pub fn with_camera(self, camera: Option<CameraCalibration>) -> Self {
        SessionOptions { camera, ..self }
    }

    /// The `OpenSession` message [`Client::open_session_with`] sends.
    pub fn to_proto(&self, input_format: InputFormat) -> pb::OpenSession {
        pb::OpenSession {
            input_format: Some(input_format.into()),
            model: pb::Model::OnlineGru as i32,
            client_label: self.label.unwrap_or_default().to_string(),
            server_lifter: self.server_lifter,
            camera: self.camera.as_ref().map(ToProto::to_proto),
            // The library keeps them (EventReceiver::latest_token).
            session_tokens: true,
            subject: self.subject.as_ref().map(ToProto::to_proto),
            motion: self.motion.map(|frame_rate_hz| pb::MotionOptions {
                enabled: true,
                frame_rate_hz,
            }),
        }
    }
}

/// A connected blapose client. Clone it freely: clones share the connection.
#[derive(Debug, Clone)]
pub struct Client {
    stub: Stub,
    /// What the stub adds to every call.
    metadata: CallMetadata,
    channel: Channel,
    config: ClientConfig,
}

/// The result of an offline adjustment.
#[derive(Debug, Clone, PartialEq)]
pub struct OfflineAdjustment {
    /// The model that ran.
    pub model: ModelKind,
    /// Adjusted poses, one per frame.
    pub adjusted: Vec<Pose>,
    /// Bone lengths applied to each frame.
    pub bone_lengths: Vec<BoneLengths>,
    /// With the motion stage: what it placed.
    pub placement: Option<Placement>,
}

/// Where the offline motion stage put the person.
#[derive(Debug, Clone, PartialEq)]
pub struct Placement {
    /// Each frame's pelvis in camera space (metres; x right, y down, z
    /// forward).
    pub roots: Vec<[f32; 3]>,
    /// The root was placed through an assumed focal length (no
    /// calibration was sent): positions scale with the true one.
    pub focal_assumed: bool,
    /// Each frame's pose in world coordinates (z up, the floor at 0), when
    /// the calibration had a camera height.
    pub world: Option<Vec<Pose>>,
}

/// A whole sequence for the offline RPC, already flattened.
#[derive(Debug, Clone, Copy)]
pub struct SequenceInput<'a> {
    /// Layout and coordinates of the keypoints.
    pub input_format: InputFormat,
    /// `T * J * 2` keypoint values, frame-major.
    pub keypoints_2d: &'a [f32],
    /// Empty or `T * J` confidences.
    pub confidence: &'a [f32],
    /// `T` lifted poses.
    pub poses_3d: &'a [Pose],
    /// Optional camera calibration: `Some` runs the camera-aware model of
    /// the chosen kind (the server must have one), `None` the default one.
    pub camera: Option<CameraCalibration>,
    /// Optional stature (and sex): `Some` answers every frame with the
    /// stature regression's lengths.
    pub subject: Option<Subject>,
    /// Optional motion stage at this many frames per second (0: 50):
    /// directions smoothed, the root placed, feet held.
    pub motion: Option<f32>,
}

impl<'a> SequenceInput<'a> {
    /// A sequence's arrays, camera and subject (each sent when present).
    pub fn from_sequence(seq: &'a Sequence) -> Self {
        SequenceInput {
            input_format: seq.input_format,
            keypoints_2d: &seq.keypoints_2d,
            confidence: &seq.confidence,
            poses_3d: &seq.pose_3d,
            camera: seq.camera,
            subject: seq.subject,
            motion: None,
        }
    }

    /// The `AdjustSequence` request [`Client::adjust_sequence`] sends;
    /// `InvalidInput` when there are no frames or the keypoint count does
    /// not match them.
    pub fn to_proto(&self, model: ModelKind) -> Result<pb::AdjustSequenceRequest, ClientError> {
        let t = self.poses_3d.len();
        let j = self.input_format.layout.num_joints();
        if t == 0 {
            return Err(ClientError::InvalidInput(
                "the sequence has no frames".into(),
            ));
        }
        if self.keypoints_2d.len() != t * j * 2 {
            return Err(ClientError::InvalidInput(format!(
                "{} keypoint values for {t} frames of {j} joints (expected {})",
                self.keypoints_2d.len(),
                t * j * 2
            )));
        }
        let num_frames = u32::try_from(t).map_err(|_| {
            ClientError::InvalidInput(format!("{t} frames is too many for one call"))
        })?;
        Ok(pb::AdjustSequenceRequest {
            input_format: Some(self.input_format.into()),
            model: pb::Model::from(model) as i32,
            num_frames,
            keypoints_2d: self.keypoints_2d.to_vec(),
            confidence: self.confidence.to_vec(),
            poses_3d: self.poses_3d.as_flattened().as_flattened().to_vec(),
            camera: self.camera.as_ref().map(ToProto::to_proto),
            subject: self.subject.as_ref().map(ToProto::to_proto),
            motion: self.motion.map(|frame_rate_hz| pb::MotionOptions {
                enabled: true,
                frame_rate_hz,
            }),
        })
    }
}

impl Client {
    /// Connect, retrying with exponential backoff (see [`ClientConfig`]).
    pub async fn connect(config: ClientConfig) -> Result<Client, ClientError> {
        let endpoint = build_endpoint(&config)?;
        let auth = CallMetadata::new(config.token.as_deref())?;
        let attempts = config.connect_attempts.max(1);
        let mut backoff = config.retry_backoff;
        let mut last_error = String::new();
        for attempt in 1..=attempts {
            match endpoint.connect().await {
                Ok(channel) => return Ok(Client::from_channel(channel, auth, config)),
                Err(e) => {
                    last_error = error_chain(&e);
                    // A certificate the client does not trust will not be
                    // trusted on the next attempt either: say why and stop.
                    if let Some(problem) = blapose_tls::untrusted(&e) {
                        let ca_given = config.tls.ca_cert_pem.is_some();
                        return Err(ClientError::Connect {
                            endpoint: config.endpoint,
                            attempts: attempt,
                            last_error: format!("{} ({last_error})", problem.advice(ca_given)),
                        });
                    }
                    if attempt < attempts {
                        tokio::time::sleep(backoff).await;
                        backoff = next_backoff(backoff);
                    }
                }
            }
        }
        Err(ClientError::Connect {
            endpoint: config.endpoint,
            attempts,
            last_error,
        })
    }

    /// A client that connects at its first call instead of now (and
    /// reconnects as needed): for a fallback replica that may be down when
    /// the program starts. Fails only on a bad URL, TLS setting or token.
    pub fn connect_lazy(config: ClientConfig) -> Result<Client, ClientError> {
        let endpoint = build_endpoint(&config)?;
        let auth = CallMetadata::new(config.token.as_deref())?;
        Ok(Client::from_channel(endpoint.connect_lazy(), auth, config))
    }

    fn from_channel(channel: Channel, auth: CallMetadata, config: ClientConfig) -> Client {
        let stub = new_stub(channel.clone(), auth.clone(), &config);
        Client {
            stub,
            metadata: auth,
            channel,
            config,
        }
    }

    /// The configuration this client was connected with.
    pub fn config(&self) -> &ClientConfig {
        &self.config
    }

    /// The underlying channel (e.g. for a `grpc.health.v1` client).
    pub fn channel(&self) -> Channel {
        self.channel.clone()
    }

    /// The same connection, sending `key` as the
    /// [`AFFINITY_HEADER`](crate::AFFINITY_HEADER) on every call: use it for
    /// every stream and call of one session (see
    /// [`new_affinity_key`](crate::new_affinity_key)) so that a load
    /// balancer hashing on it keeps the session on one replica.
    /// [`replay_across`](crate::replay_across) does this itself.
    pub fn with_affinity(&self, key: &str) -> Result<Client, ClientError> {
        let auth = self.metadata.clone().with_affinity(key)?;
        Ok(Client::from_channel(
            self.channel.clone(),
            auth,
            self.config.clone(),
        ))
    }

    /// The same connection with a different bearer token (tests of the
    /// server's authentication use it).
    pub fn with_token(&self, token: Option<&str>) -> Result<Client, ClientError> {
        let mut config = self.config.clone();
        config.token = token.map(str::to_string);
        let auth = CallMetadata::new(token)?;
        Ok(Client::from_channel(self.channel.clone(), auth, config))
    }

    fn stub(&self) -> Stub {
        self.stub.clone()
    }

    fn request<T>(&self, msg: T) -> tonic::Request<T> {
        let mut req = tonic::Request::new(msg);
        req.set_timeout(self.config.request_timeout);
        req
    }

    async fn deadline<T, F>(&self, what: &'static str, fut: F) -> Result<T, ClientError>
    where
        F: std::future::Future<Output = Result<tonic::Response<T>, tonic::Status>>,
    {
        let after = self.config.request_timeout;
        match tokio::time::timeout(after, fut).await {
            Ok(Ok(r)) => Ok(r.into_inner()),
            Ok(Err(status)) => Err(self.explain_transport_error(status).await),
            Err(_) => Err(ClientError::Timeout { what, after }),
        }
    }

    /// A call whose connection failed: a certificate the client does not
    /// trust is named with the flag that fixes it; for a plaintext call,
    /// when the port speaks TLS, say so. The server's GOAWAY says it too, but the connection's close
    /// can reach the client first, so the port is asked directly
    /// ([`blapose_tls::probe`], a connection of its own).
    async fn explain_transport_error(&self, status: tonic::Status) -> ClientError {
        if let Some(problem) = blapose_tls::untrusted(&status) {
            let advice = problem.advice(self.config.tls.ca_cert_pem.is_some());
            return ClientError::Status(tonic::Status::unavailable(format!(
                "{advice} ({})",
                status.message()
            )));
        }
        let plaintext =
            self.config.endpoint.starts_with("http://") && self.config.tls.ca_cert_pem.is_none();
        let transport = matches!(
            status.code(),
            tonic::Code::Unavailable | tonic::Code::Cancelled | tonic::Code::Unknown
        ) && !status.message().contains("speaks TLS");
        if plaintext && transport {
            if let Ok(uri) = self.config.endpoint.parse::<tonic::codegen::http::Uri>() {
                if let (Some(host), Some(port)) = (uri.host(), uri.port_u16()) {
                    if blapose_tls::probe(host, port).await == blapose_tls::Speaks::Tls {
                        return ClientError::Status(tonic::Status::unavailable(format!(
                            "the server at {host}:{port} speaks TLS: connect with https:// and \
                             --tls-ca ({})",
                            status.message()
                        )));
                    }
                }
            }
        }
        ClientError::Status(status)
    }

    /// What the server runs (models, layouts, limits).
    pub async fn model_info(&self) -> Result<ModelInfo, ClientError> {
        let mut stub = self.stub();
        let req = self.request(pb::ModelInfoRequest {});
        let resp = self.deadline("ModelInfo", stub.model_info(req)).await?;
        Ok(ModelInfo::from_proto(resp))
    }

    /// Open a new streaming session (every frame carries the client's 3D
    /// pose).
    pub async fn open_session(
        &self,
        input_format: InputFormat,
        label: Option<&str>,
    ) -> Result<Session, ClientError> {
        self.open_session_with(
            input_format,
            &SessionOptions {
                label,
                ..SessionOptions::default()
            },
        )
        .await
    }

    /// Open a new streaming session with `options`. With
    /// `server_lifter`, the server lifts every pose itself: frames carry
    /// keypoints only (`FrameInput::pose_3d` = `None`) and
    /// [`SessionInfo::lifter`](crate::SessionInfo::lifter) names the lifter;
    /// a server without a lifter answers INVALID_ARGUMENT. With a `camera`,
    /// the camera-aware model serves the session and
    /// [`SessionInfo::camera`](crate::SessionInfo::camera) echoes the
    /// calibration; a bad calibration, or a server without camera-aware
    /// models, answers INVALID_ARGUMENT (the calibration is not checked
    /// locally: the server is the authority on what it accepts).
    pub async fn open_session_with(
        &self,
        input_format: InputFormat,
        options: &SessionOptions<'_>,
    ) -> Result<Session, ClientError> {
        let open = options.to_proto(input_format);
        let session = Session::start(
            self.stub(),
            &self.config,
            pb::stream_request::Kind::Open(open),
        )
        .await?;
        // A server that predates server lifters ignores the request; the
        // session would then expect poses the client does not send.
        if options.server_lifter && session.info().lifter.is_none() {
            return Err(ClientError::Protocol(
                "server_lifter was requested but the server opened a session that expects client poses (a server without lifter support?)".into(),
            ));
        }
        // Likewise a server that predates camera calibrations would serve
        // the session with the default model without saying so.
        if options.camera.is_some() && session.info().camera.is_none() {
            return Err(ClientError::Protocol(
                "a camera calibration was sent but the server opened a session without one (a server without camera support?); open it without the camera for the default model".into(),
            ));
        }
        Ok(session)
    }

    /// Re-attach to a session by id (its state is intact if its TTL has not
    /// expired; otherwise the server answers NOT_FOUND).
    pub async fn resume_session(&self, session_id: &str) -> Result<Session, ClientError> {
        self.resume_session_with_token(session_id, None).await
    }

    /// Re-attach to a session by id, sending `token` (the latest
    /// [`SessionToken`] received for it) along: a
    /// server that holds the session resumes it as
    /// [`resume_session`](Client::resume_session) does and ignores the
    /// token; one that does not (another replica sharing the session key,
    /// or this one after a restart) restores the session from the token,
    /// as of the token's `frames_seen`. Continue from the answer's
    /// `frames_seen` either way. A token the server cannot use is refused
    /// (UNAUTHENTICATED: altered or another key; FAILED_PRECONDITION: other
    /// weights, another token version, or no key on that server).
    pub async fn resume_session_with_token(
        &self,
        session_id: &str,
        token: Option<&SessionToken>,
    ) -> Result<Session, ClientError> {
        let resume = pb::ResumeSession {
            session_id: session_id.to_string(),
            session_token: token.map(|t| t.token.clone()).unwrap_or_default(),
            session_tokens: true,
        };
        Session::start(
            self.stub(),
            &self.config,
            pb::stream_request::Kind::Resume(resume),
        )
        .await
    }

    /// Open a stream whose first message is `first`, exactly as given
    /// (tests of the server's input validation use it to send what the
    /// typed API would refuse to build).
    pub async fn open_raw(&self, first: pb::StreamRequest) -> Result<Session, ClientError> {
        Session::start_raw(self.stub(), &self.config, first).await
    }

    /// Close a (detached) session by id.
    pub async fn close_session(&self, session_id: &str) -> Result<SessionSummary, ClientError> {
        let mut stub = self.stub();
        let req = self.request(pb::CloseSessionRequest {
            session_id: session_id.to_string(),
        });
        let resp = self
            .deadline("CloseSession", stub.close_session(req))
            .await?;
        SessionSummary::from_close_response(session_id, resp)
    }

    /// Adjust a whole sequence in one call (with `input.camera`, by the
    /// camera-aware model of `model`'s kind).
    pub async fn adjust_sequence(
        &self,
        input: SequenceInput<'_>,
        model: ModelKind,
    ) -> Result<OfflineAdjustment, ClientError> {
        let msg = input.to_proto(model)?;
        let t = input.poses_3d.len();
        self.adjust_sequence_raw(msg)
            .await
            .and_then(|resp| offline_from_proto(resp, t))
    }

    /// Send an `AdjustSequence` request exactly as given.
    pub async fn adjust_sequence_raw(
        &self,
        msg: pb::AdjustSequenceRequest,
    ) -> Result<pb::AdjustSequenceResponse, ClientError> {
        let mut stub = self.stub();
        let frames = msg.num_frames;
        let req = self.request(msg);
        match self
            .deadline("AdjustSequence", stub.adjust_sequence(req))
            .await
        {
            Err(ClientError::Status(s))
                if s.code() == tonic::Code::OutOfRange
                    && s.message().contains("message length too large") =>
            {
                Err(ClientError::MessageTooLarge {
                    frames,
                    detail: s.message().to_string(),
                })
            }
            other => other,
        }
    }
}

fn offline_from_proto(
    resp: pb::AdjustSequenceResponse,
    t: usize,
) -> Result<OfflineAdjustment, ClientError> {
    let model = model_from_answer(resp.model)?;
    if resp.adjusted_poses_3d.len() != t * 51 || resp.bone_lengths.len() != t * 16 {
        return Err(ClientError::Protocol(format!(
            "AdjustSequence answered {} pose values and {} length values for {t} frames",
            resp.adjusted_poses_3d.len(),
            resp.bone_lengths.len()
        )));
    }
    let adjusted = resp
        .adjusted_poses_3d
        .chunks_exact(51)
        .map(|c| pose_from_flat(c, "adjusted_poses_3d"))
        .collect::<Result<Vec<_>, _>>()?;
    let bone_lengths = resp
        .bone_lengths
        .chunks_exact(16)
        .map(|c| lengths_from_flat(c, "bone_lengths"))
        .collect::<Result<Vec<_>, _>>()?;
    let placement = if resp.root_positions.is_empty() {
        None
    } else {
        if resp.root_positions.len() != t * 3
            || !(resp.world_poses_3d.is_empty() || resp.world_poses_3d.len() == t * 51)
        {
            return Err(ClientError::Protocol(format!(
                "AdjustSequence answered {} root values and {} world pose values for {t} frames",
                resp.root_positions.len(),
                resp.world_poses_3d.len()
            )));
        }
        let world = if resp.world_poses_3d.is_empty() {
            None
        } else {
            Some(
                resp.world_poses_3d
                    .chunks_exact(51)
                    .map(|c| pose_from_flat(c, "world_poses_3d"))
                    .collect::<Result<Vec<_>, _>>()?,
            )
        };
        Some(Placement {
            roots: resp
                .root_positions
                .chunks_exact(3)
                .map(|c| [c[0], c[1], c[2]])
                .collect(),
            focal_assumed: resp.focal_assumed,
            world,
        })
    };
    Ok(OfflineAdjustment {
        model,
        adjusted,
        bone_lengths,
        placement,
    })
}

/// An error and its sources on one line (tonic's transport errors hide the
/// useful part, e.g. "connection refused", in the source chain).
fn error_chain(e: &dyn std::error::Error) -> String {
    let mut s = e.to_string();
    let mut src = e.source();
    while let Some(inner) = src {
        let text = inner.to_string();
        if !s.contains(&text) {
            s.push_str(": ");
            s.push_str(&text);
        }
        src = inner.source();
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::AFFINITY_HEADER;
    use std::time::Duration;

    #[tokio::test]
    async fn an_affinity_handle_sends_the_key_on_every_call() {
        use tonic::service::Interceptor;
        let client = Client::connect_lazy(ClientConfig::new("http://127.0.0.1:1")).unwrap();
        let mut plain = CallMetadata::new(None).unwrap();
        let sent = plain.call(tonic::Request::new(())).unwrap();
        assert!(sent.metadata().get(AFFINITY_HEADER).is_none());
        let keyed = client.with_affinity("0123abcd").unwrap();
        let mut metadata = keyed.metadata.clone();
        let sent = metadata.call(tonic::Request::new(())).unwrap();
        assert_eq!(sent.metadata().get(AFFINITY_HEADER).unwrap(), "0123abcd");
        assert!(client.with_affinity("not\nascii").is_err());
    }

    fn calibration() -> CameraCalibration {
        CameraCalibration {
            up: [0.0, -0.99, 0.1],
            focal: [1150.0, 1150.0],
            principal: [500.0, 500.0],
            image_size: None,
            height: Some(1.6),
            distortion: None,
        }
    }

    #[test]
    fn open_session_sends_the_camera_only_when_given() {
        use blapose_core::layouts::KeypointLayout;
        let format = InputFormat::pixels(KeypointLayout::Coco17, 640, 480);
        let plain = SessionOptions {
            label: Some("cam0"),
            ..SessionOptions::default()
        };
        let open = plain.to_proto(format);
        assert_eq!(open.camera, None);
        assert_eq!(open.client_label, "cam0");
        assert_eq!(open.input_format, Some(format.into()));
        let with = plain.with_camera(Some(calibration()));
        assert_eq!(with.label, Some("cam0"));
        assert_eq!(with.to_proto(format).camera, Some(calibration().to_proto()));
        assert_eq!(with.with_camera(None).to_proto(format).camera, None);
    }

    #[test]
    fn adjust_sequence_sends_the_sequences_camera() {
        use blapose_core::layouts::KeypointLayout;
        let mut seq = Sequence {
            input_format: InputFormat::pixels(KeypointLayout::H36m17, 1000, 1000),
            keypoints_2d: vec![500.0; 2 * 17 * 2],
            confidence: Vec::new(),
            pose_3d: vec![[[0.0; 3]; 17]; 2],
            gt_3d: None,
            fps: None,
            camera: None,
            subject: None,
        };
        let req = SequenceInput::from_sequence(&seq)
            .to_proto(ModelKind::BiGru)
            .unwrap();
        assert_eq!((req.camera, req.num_frames), (None, 2));
        seq.camera = Some(calibration());
        let input = SequenceInput::from_sequence(&seq);
        assert_eq!(input.camera, Some(calibration()));
        let req = input.to_proto(ModelKind::Gru).unwrap();
        assert_eq!(req.camera, Some(calibration().to_proto()));
        assert_eq!(req.model, pb::Model::OnlineGru as i32);
        let short = SequenceInput {
            keypoints_2d: &seq.keypoints_2d[1..],
            ..input
        };
        assert!(matches!(
            short.to_proto(ModelKind::Gru),
            Err(ClientError::InvalidInput(_))
        ));
    }

    #[tokio::test]
    async fn connect_gives_up_after_the_configured_attempts() {
        // Bind then drop a listener so the port is (almost certainly) closed.
        let port = {
            let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
            l.local_addr().unwrap().port()
        };
        let mut config = ClientConfig::new(format!("http://127.0.0.1:{port}"));
        config.connect_attempts = 3;
        config.retry_backoff = Duration::from_millis(10);
        config.connect_timeout = Duration::from_millis(500);
        match Client::connect(config).await {
            Err(ClientError::Connect { attempts, .. }) => assert_eq!(attempts, 3),
            other => panic!("expected a connect error, got {other:?}"),
        }
    }
}

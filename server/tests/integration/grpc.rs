//! The server over real gRPC on a loopback port, driven with the generated
//! client stub. A fake model (deterministic, state-dependent) isolates the
//! protocol: ordering, exactly-once answers, per-frame errors, resume and
//! takeover, close, limits, auth, size limits, health and shutdown draining.
//! One test runs the real fast engines on random weights.

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use blapose_proto::v1 as pb;
use blapose_server::backend::{
    Backend, BackendError, SequenceBackend, INPUT_DIM, OUTPUT_DIM, STATE_DIM,
};
use blapose_server::{ModelInput, ModelProvider, ServerConfig, ServerHandle};
use blapose_test_support::StepGate;
use pb::pose_adjustment_client::PoseAdjustmentClient;
use pb::stream_request::Kind as Req;
use pb::stream_response::Kind as Resp;
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tonic::transport::Channel;
use tonic::Code;

/// Fake online model: every state slot counts the frames seen; the per-frame
/// prediction for bone `b` is `0.2 + 0.01 * b + 0.001 * count`. So the
/// running mean after `n` frames is `0.2 + 0.01 b + 0.001 (n + 1) / 2`,
/// which exposes lost, repeated or reordered frames and lost state.
struct FakeStep {
    delay: Duration,
    /// Added to every prediction (the camera-aware fake's is 0.1).
    offset: f32,
    /// Every step waits here first, if set.
    gate: Option<Arc<StepGate>>,
}

/// Wait (off the async workers) until `n` steps have reached the gate.
async fn wait_entered(gate: &Arc<StepGate>, n: usize) {
    let gate = gate.clone();
    tokio::task::spawn_blocking(move || gate.wait_entered(n))
        .await
        .unwrap();
}

impl Backend for FakeStep {
    fn step(
        &mut self,
        inputs: &[f32],
        hidden: &mut [f32],
        out: &mut [f32],
        batch: usize,
    ) -> Result<(), BackendError> {
        blapose_server::backend::check_step_shapes(inputs, hidden, out, batch)?;
        if let Some(gate) = &self.gate {
            gate.pass();
        }
        std::thread::sleep(self.delay);
        for b in 0..batch {
            let h = &mut hidden[b * STATE_DIM..(b + 1) * STATE_DIM];
            h.iter_mut().for_each(|v| *v += 1.0);
            for (bone, y) in out[b * OUTPUT_DIM..(b + 1) * OUTPUT_DIM]
                .iter_mut()
                .enumerate()
            {
                *y = 0.2 + self.offset + 0.01 * bone as f32 + 0.001 * h[0];
            }
        }
        Ok(())
    }
}

struct FakeSeq {
    offset: f32,
}

impl SequenceBackend for FakeSeq {
    fn predict(&mut self, inputs: &[f32], frames: usize) -> Result<[f32; 16], BackendError> {
        assert_eq!(inputs.len(), frames * INPUT_DIM);
        Ok(std::array::from_fn(|b| {
            0.3 + self.offset + 0.001 * b as f32
        }))
    }
}

/// The fake models; `camera_aware` adds a second family whose predictions
/// are 0.1 larger (what sessions with a camera calibration get).
struct Fake {
    delay: Duration,
    offset: f32,
    camera_aware: Option<Arc<Fake>>,
    /// The input contract the fake reports.
    input: ModelInput,
    gate: Option<Arc<StepGate>>,
}

impl Fake {
    fn new(delay: Duration) -> Self {
        Self {
            delay,
            offset: 0.0,
            camera_aware: None,
            input: ModelInput::level(),
            gate: None,
        }
    }

    fn with_camera_aware(delay: Duration) -> Self {
        Self {
            camera_aware: Some(Arc::new(Self {
                offset: 0.1,
                ..Self::new(delay)
            })),
            ..Self::new(delay)
        }
    }
}

impl ModelProvider for Fake {
    fn online(&self) -> Result<Box<dyn Backend>, BackendError> {
        Ok(Box::new(FakeStep {
            delay: self.delay,
            offset: self.offset,
            gate: self.gate.clone(),
        }))
    }
    fn offline(&self) -> Result<Box<dyn SequenceBackend>, BackendError> {
        Ok(Box::new(FakeSeq {
            offset: self.offset,
        }))
    }
    fn describe(&self) -> Vec<pb::ModelDescription> {
        vec![pb::ModelDescription {
            name: "fake".into(),
            ..Default::default()
        }]
    }
    fn camera_aware(&self) -> Option<Arc<dyn ModelProvider>> {
        self.camera_aware
            .clone()
            .map(|p| p as Arc<dyn ModelProvider>)
    }
    fn model_input(&self) -> ModelInput {
        self.input
    }
}

fn expected_mean(bone: usize, n: u64) -> f32 {
    0.2 + 0.01 * bone as f32 + 0.001 * (n as f32 + 1.0) / 2.0
}

fn config() -> ServerConfig {
    ServerConfig {
        metrics_addr: None,
        ..ServerConfig::default()
    }
}

async fn start(config: ServerConfig, delay: Duration) -> ServerHandle {
    start_with(config, Fake::new(delay)).await
}

async fn start_with(config: ServerConfig, fake: Fake) -> ServerHandle {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    blapose_server::spawn_with_provider(config, listener, Arc::new(fake))
        .await
        .unwrap()
}

async fn client(addr: SocketAddr) -> PoseAdjustmentClient<Channel> {
    PoseAdjustmentClient::connect(format!("http://{addr}"))
        .await
        .unwrap()
}

/// A plausible standing pose in metres, 4 m in front of the camera.
fn pose() -> Vec<f32> {
    let joints: [[f32; 3]; 17] = [
        [0.0, 0.0, 4.0],
        [-0.13, 0.0, 4.0],
        [-0.13, 0.45, 4.0],
        [-0.13, 0.9, 4.0],
        [0.13, 0.0, 4.0],
        [0.13, 0.45, 4.0],
        [0.13, 0.9, 4.0],
        [0.0, -0.23, 4.0],
        [0.0, -0.48, 4.0],
        [0.0, -0.58, 4.0],
        [0.0, -0.7, 4.0],
        [0.15, -0.45, 4.0],
        [0.43, -0.45, 4.0],
        [0.68, -0.45, 4.0],
        [-0.15, -0.45, 4.0],
        [-0.43, -0.45, 4.0],
        [-0.68, -0.45, 4.0],
    ];
    joints.iter().flatten().copied().collect()
}

/// H36M-17 keypoints in pixels of a 1000 x 1000 image.
fn pixel_format() -> pb::InputFormat {
    pb::InputFormat {
        layout: pb::KeypointLayout::H36m17 as i32,
        coordinates: Some(pb::input_format::Coordinates::ImageSize(pb::ImageSize {
            width: 1000,
            height: 1000,
        })),
    }
}

fn open_request() -> pb::StreamRequest {
    open_with_camera(None)
}

/// A camera looking 12 degrees down with a centred principal point.
fn calibration() -> pb::CameraCalibration {
    let tilt = 12f32.to_radians();
    pb::CameraCalibration {
        up: vec![0.0, -tilt.cos(), -tilt.sin()],
        focal_x: 1150.0,
        focal_y: 1150.0,
        principal_x: 500.0,
        principal_y: 500.0,
        image_size: None,
        height: 0.0,
        distortion: vec![],
    }
}

fn open_with_camera(camera: Option<pb::CameraCalibration>) -> pb::StreamRequest {
    pb::StreamRequest {
        kind: Some(Req::Open(pb::OpenSession {
            input_format: Some(pixel_format()),
            model: 0,
            client_label: "test".into(),
            server_lifter: false,
            camera,
            session_tokens: false,
            subject: None,
            motion: None,
        })),
    }
}

/// An AdjustSequence request (Bi-GRU) of the frames `frame(0..n)` sends.
fn sequence_request(n: u64, camera: Option<pb::CameraCalibration>) -> pb::AdjustSequenceRequest {
    let frames: Vec<pb::Frame> = (0..n)
        .map(|i| match frame(i).kind {
            Some(Req::Frame(f)) => f,
            _ => unreachable!(),
        })
        .collect();
    pb::AdjustSequenceRequest {
        input_format: Some(pixel_format()),
        model: 0,
        num_frames: n as u32,
        keypoints_2d: frames.iter().flat_map(|f| f.keypoints_2d.clone()).collect(),
        confidence: vec![],
        poses_3d: frames.iter().flat_map(|f| f.pose_3d.clone()).collect(),
        camera,
        subject: None,
        motion: None,
    }
}

fn frame(index: u64) -> pb::StreamRequest {
    pb::StreamRequest {
        kind: Some(Req::Frame(pb::Frame {
            frame_index: index,
            keypoints_2d: (0..34).map(|i| 400.0 + i as f32).collect(),
            confidence: vec![],
            pose_3d: pose(),
        })),
    }
}

fn request(kind: Req) -> pb::StreamRequest {
    pb::StreamRequest { kind: Some(kind) }
}

/// An open stream: a sender for requests and the response stream.
struct Conn {
    tx: mpsc::Sender<pb::StreamRequest>,
    rx: tonic::Streaming<pb::StreamResponse>,
}

impl Conn {
    async fn new(client: &mut PoseAdjustmentClient<Channel>) -> Self {
        let (tx, rx) = mpsc::channel(1024);
        let rx = client
            .stream(ReceiverStream::new(rx))
            .await
            .unwrap()
            .into_inner();
        Self { tx, rx }
    }

    async fn send(&self, r: pb::StreamRequest) {
        self.tx.send(r).await.unwrap();
    }

    async fn next(&mut self) -> Result<Option<Resp>, tonic::Status> {
        tokio::time::timeout(Duration::from_secs(10), self.rx.message())
            .await
            .expect("response within 10 s")
            .map(|m| m.and_then(|r| r.kind))
    }

    async fn open(client: &mut PoseAdjustmentClient<Channel>) -> (Self, pb::SessionOpened) {
        Self::open_with(client, open_request()).await
    }

    async fn open_with(
        client: &mut PoseAdjustmentClient<Channel>,
        open: pb::StreamRequest,
    ) -> (Self, pb::SessionOpened) {
        let mut c = Self::new(client).await;
        c.send(open).await;
        match c.next().await.unwrap() {
            Some(Resp::Opened(o)) => (c, o),
            other => panic!("expected opened, got {other:?}"),
        }
    }

    async fn frame(&mut self) -> pb::AdjustedFrame {
        match self.next().await.unwrap() {
            Some(Resp::Frame(f)) => f,
            other => panic!("expected a frame, got {other:?}"),
        }
    }

    async fn status(&mut self) -> tonic::Status {
        loop {
            match self.next().await {
                Err(s) => return s,
                Ok(None) => panic!("stream ended with OK, expected an error status"),
                Ok(Some(_)) => continue,
            }
        }
    }
}

fn bone_length(p: &[f32], child: usize, parent: usize) -> f32 {
    let d: Vec<f32> = (0..3)
        .map(|k| p[3 * child + k] - p[3 * parent + k])
        .collect();
    d.iter().map(|v| v * v).sum::<f32>().sqrt()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn frames_are_answered_in_order_exactly_once() {
    let server = start(config(), Duration::ZERO).await;
    let mut c = client(server.local_addr()).await;
    let (mut conn, opened) = Conn::open(&mut c).await;
    assert_eq!(opened.session_id.len(), 32);
    assert!(opened.session_id.bytes().all(|b| b.is_ascii_hexdigit()));
    assert!(!opened.resumed);
    assert_eq!(opened.frames_seen, 0);
    assert_eq!(opened.model, pb::Model::OnlineGru as i32);
    // Pipeline 200 frames with arbitrary (non-monotonic) indices.
    let indices: Vec<u64> = (0..200u64).map(|i| (i * 7919) % 1000).collect();
    for &i in &indices {
        conn.send(frame(i)).await;
    }
    let input = pose();
    for (n, &i) in indices.iter().enumerate() {
        let f = conn.frame().await;
        assert_eq!(f.frame_index, i);
        assert_eq!(f.frames_seen, n as u64 + 1);
        assert_eq!(f.bone_lengths.len(), 16);
        for b in 0..16 {
            assert!((f.bone_lengths[b] - expected_mean(b, n as u64 + 1)).abs() < 1e-5);
        }
        // Root kept, lengths applied, directions kept.
        assert_eq!(&f.adjusted_pose_3d[..3], &input[..3]);
        let parents = blapose_core::skeleton::PARENTS;
        for b in 0..16 {
            let l = bone_length(&f.adjusted_pose_3d, b + 1, parents[b + 1]);
            assert!((l - f.bone_lengths[b]).abs() < 1e-5, "bone {b}");
        }
    }
    conn.send(request(Req::Close(pb::CloseSession {}))).await;
    match conn.next().await.unwrap() {
        Some(Resp::Closed(c)) => {
            assert_eq!(c.session_id, opened.session_id);
            assert_eq!(c.frames_seen, 200);
        }
        other => panic!("expected closed, got {other:?}"),
    }
    assert!(
        conn.next().await.unwrap().is_none(),
        "stream ends OK after close"
    );
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_bad_frame_gets_an_error_and_leaves_the_session_untouched() {
    let server = start(config(), Duration::ZERO).await;
    let mut c = client(server.local_addr()).await;
    let (mut conn, _) = Conn::open(&mut c).await;
    conn.send(frame(0)).await;
    let mut bad = frame(1);
    if let Some(Req::Frame(f)) = &mut bad.kind {
        f.keypoints_2d.pop();
    }
    conn.send(bad).await;
    let mut nan = frame(2);
    if let Some(Req::Frame(f)) = &mut nan.kind {
        f.pose_3d[7] = f32::NAN;
    }
    conn.send(nan).await;
    let mut zero_bone = frame(3);
    if let Some(Req::Frame(f)) = &mut zero_bone.kind {
        let wrist: Vec<f32> = f.pose_3d[36..39].to_vec();
        f.pose_3d[39..42].copy_from_slice(&wrist);
    }
    conn.send(zero_bone).await;
    conn.send(frame(4)).await;

    assert_eq!(conn.frame().await.frames_seen, 1);
    for (index, needle) in [
        (1, "keypoints_2d has 33 values"),
        (2, "non-finite"),
        (3, "zero length"),
    ] {
        match conn.next().await.unwrap() {
            Some(Resp::Error(e)) => {
                assert_eq!(e.frame_index, index);
                assert_eq!(e.code, Code::InvalidArgument as i32);
                assert!(e.message.contains(needle), "{}", e.message);
            }
            other => panic!("expected a frame error, got {other:?}"),
        }
    }
    let f = conn.frame().await;
    assert_eq!(f.frame_index, 4);
    assert_eq!(f.frames_seen, 2, "bad frames are not counted");
    assert!(
        (f.bone_lengths[0] - expected_mean(0, 2)).abs() < 1e-6,
        "bad frames did not move the state"
    );
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn protocol_errors_end_the_stream_with_the_right_code() {
    let mut cfg = config();
    cfg.max_sessions = 1;
    let server = start(cfg, Duration::ZERO).await;
    let mut c = client(server.local_addr()).await;

    let cases: Vec<(pb::StreamRequest, Code, &str)> = vec![
        (
            frame(0),
            Code::FailedPrecondition,
            "before the session was opened",
        ),
        (
            request(Req::Close(pb::CloseSession {})),
            Code::FailedPrecondition,
            "before the session was opened",
        ),
        (
            pb::StreamRequest { kind: None },
            Code::InvalidArgument,
            "empty StreamRequest",
        ),
        (
            request(Req::Resume(pb::ResumeSession {
                session_id: "00112233445566778899aabbccddeeff".into(),
                session_token: Vec::new(),
                session_tokens: false,
            })),
            Code::NotFound,
            "no session",
        ),
        (
            request(Req::Resume(pb::ResumeSession {
                session_id: "garbage".into(),
                session_token: Vec::new(),
                session_tokens: false,
            })),
            Code::NotFound,
            "no session",
        ),
    ];
    for (first, code, needle) in cases {
        let mut conn = Conn::new(&mut c).await;
        conn.send(first).await;
        let status = conn.status().await;
        assert_eq!(status.code(), code, "{}", status.message());
        assert!(status.message().contains(needle), "{}", status.message());
    }

    let bad_opens: Vec<(pb::OpenSession, &str)> = vec![
        (
            pb::OpenSession {
                input_format: None,
                ..Default::default()
            },
            "input_format is required",
        ),
        (
            pb::OpenSession {
                input_format: Some(pb::InputFormat {
                    layout: 0,
                    coordinates: Some(pb::input_format::Coordinates::Normalized(true)),
                }),
                ..Default::default()
            },
            "UNSPECIFIED",
        ),
        (
            pb::OpenSession {
                input_format: Some(pb::InputFormat {
                    layout: 77,
                    coordinates: Some(pb::input_format::Coordinates::Normalized(true)),
                }),
                ..Default::default()
            },
            "not a known KeypointLayout",
        ),
        (
            pb::OpenSession {
                input_format: Some(pb::InputFormat {
                    layout: 1,
                    coordinates: Some(pb::input_format::Coordinates::ImageSize(pb::ImageSize {
                        width: 0,
                        height: 720,
                    })),
                }),
                ..Default::default()
            },
            "must be positive",
        ),
        (
            pb::OpenSession {
                input_format: Some(pb::InputFormat {
                    layout: 1,
                    coordinates: Some(pb::input_format::Coordinates::Normalized(true)),
                }),
                model: pb::Model::OfflineBigru as i32,
                ..Default::default()
            },
            "AdjustSequence",
        ),
    ];
    for (open, needle) in bad_opens {
        let mut conn = Conn::new(&mut c).await;
        conn.send(request(Req::Open(open))).await;
        let status = conn.status().await;
        assert_eq!(status.code(), Code::InvalidArgument, "{}", status.message());
        assert!(status.message().contains(needle), "{}", status.message());
    }

    // A second open on a live stream; then the session limit (1).
    let (mut conn, _) = Conn::open(&mut c).await;
    let mut other = Conn::new(&mut c).await;
    other.send(open_request()).await;
    let status = other.status().await;
    assert_eq!(
        status.code(),
        Code::ResourceExhausted,
        "{}",
        status.message()
    );
    conn.send(frame(0)).await;
    conn.send(open_request()).await;
    assert_eq!(
        conn.frame().await.frame_index,
        0,
        "frames before the error are answered"
    );
    assert_eq!(conn.status().await.code(), Code::FailedPrecondition);

    let err = c
        .close_session(pb::CloseSessionRequest {
            session_id: "ffffffffffffffffffffffffffffffff".into(),
        })
        .await
        .unwrap_err();
    assert_eq!(err.code(), Code::NotFound);
    server.shutdown().await.unwrap();
}

/// A stream that never sends its first message is ended at the open
/// deadline, with a status that names the wait; an opened stream idle for
/// longer is not affected (the deadline is for the first message only).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stream_that_never_opens_ends_at_the_open_deadline() {
    let mut cfg = config();
    cfg.open_timeout = Duration::from_millis(100);
    let server = start(cfg, Duration::ZERO).await;
    let mut c = client(server.local_addr()).await;
    // Opened before the silent stream starts, so idle at least as long.
    let (mut opened, _) = Conn::open(&mut c).await;
    let mut silent = Conn::new(&mut c).await;
    let status = silent.status().await;
    assert_eq!(
        status.code(),
        Code::DeadlineExceeded,
        "{}",
        status.message()
    );
    assert!(
        status
            .message()
            .contains("no open or resume request within 100ms"),
        "{}",
        status.message()
    );
    opened.send(frame(0)).await;
    assert_eq!(opened.frame().await.frames_seen, 1);
    server.shutdown().await.unwrap();
}

/// A message that is not a valid protobuf of the method's request type is
/// refused by tonic's decoder before any handler runs: INTERNAL, as in
/// other gRPC implementations (the server README's error table says so).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_undecodable_message_is_internal() {
    use blapose_proto::codec::SmallBufferCodec;
    use tonic::codegen::http::uri::PathAndQuery;
    let server = start(config(), Duration::ZERO).await;
    let channel =
        tonic::transport::Endpoint::from_shared(format!("http://{}", server.local_addr()))
            .unwrap()
            .connect()
            .await
            .unwrap();
    // A `Frame` has a varint at field 1, where `StreamRequest` and
    // `AdjustSequenceRequest` have a message: their decoders refuse it.
    let bogus = pb::Frame {
        frame_index: 7,
        ..Default::default()
    };
    let mut grpc = tonic::client::Grpc::new(channel);
    grpc.ready().await.unwrap();
    let stream = grpc
        .streaming(
            tonic::Request::new(tokio_stream::iter([bogus.clone()])),
            PathAndQuery::from_static("/blapose.v1.PoseAdjustment/Stream"),
            SmallBufferCodec::<pb::Frame, pb::StreamResponse>::default(),
        )
        .await;
    let status = match stream {
        Err(status) => status,
        Ok(response) => response
            .into_inner()
            .message()
            .await
            .expect_err("an undecodable first message ends the stream"),
    };
    assert_eq!(status.code(), Code::Internal, "{}", status.message());
    assert!(status.message().contains("decode"), "{}", status.message());

    grpc.ready().await.unwrap();
    let status = grpc
        .unary(
            tonic::Request::new(bogus),
            PathAndQuery::from_static("/blapose.v1.PoseAdjustment/AdjustSequence"),
            SmallBufferCodec::<pb::Frame, pb::AdjustSequenceResponse>::default(),
        )
        .await
        .expect_err("an undecodable request is refused");
    assert_eq!(status.code(), Code::Internal, "{}", status.message());
    assert!(status.message().contains("decode"), "{}", status.message());
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_dropped_stream_can_be_resumed_and_a_live_one_is_taken_over() {
    let server = start(config(), Duration::ZERO).await;
    let mut c = client(server.local_addr()).await;
    let (mut conn, opened) = Conn::open(&mut c).await;
    for i in 0..3 {
        conn.send(frame(i)).await;
        conn.frame().await;
    }
    // Resumed whether or not the server has noticed the drop yet (a
    // resume takes a still-attached session over).
    drop(conn);

    let mut resumed = Conn::new(&mut c).await;
    resumed
        .send(request(Req::Resume(pb::ResumeSession {
            session_id: opened.session_id.clone(),
            session_token: Vec::new(),
            session_tokens: false,
        })))
        .await;
    match resumed.next().await.unwrap() {
        Some(Resp::Opened(o)) => {
            assert!(o.resumed);
            assert_eq!(o.session_id, opened.session_id);
            assert_eq!(o.frames_seen, 3);
            assert!((o.bone_lengths[5] - expected_mean(5, 3)).abs() < 1e-6);
            assert_eq!(o.input_format, opened.input_format);
        }
        other => panic!("expected opened, got {other:?}"),
    }
    resumed.send(frame(3)).await;
    let f = resumed.frame().await;
    assert_eq!(f.frames_seen, 4);
    assert!(
        (f.bone_lengths[0] - expected_mean(0, 4)).abs() < 1e-6,
        "state intact across resume"
    );

    // Another stream resumes the live session: the old one is aborted.
    let mut thief = Conn::new(&mut c).await;
    thief
        .send(request(Req::Resume(pb::ResumeSession {
            session_id: opened.session_id.clone(),
            session_token: Vec::new(),
            session_tokens: false,
        })))
        .await;
    assert!(matches!(thief.next().await.unwrap(), Some(Resp::Opened(_))));
    let status = resumed.status().await;
    assert_eq!(status.code(), Code::Aborted, "{}", status.message());
    thief.send(frame(4)).await;
    assert_eq!(thief.frame().await.frames_seen, 5);

    // CloseSession from outside ends the attached stream too.
    let closed = c
        .close_session(pb::CloseSessionRequest {
            session_id: opened.session_id.clone(),
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(closed.frames_seen, 5);
    assert_eq!(thief.status().await.code(), Code::Aborted);
    let mut late = Conn::new(&mut c).await;
    late.send(request(Req::Resume(pb::ResumeSession {
        session_id: opened.session_id,
        session_token: Vec::new(),
        session_tokens: false,
    })))
    .await;
    assert_eq!(late.status().await.code(), Code::NotFound);
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn detached_sessions_expire_after_the_ttl() {
    // The TTL's timing is the session store's test (paused time); this is
    // the wiring: the configured TTL is announced and a detached session
    // goes once it passes. Polled, not timed: each try that still finds
    // the session detaches it again, for another millisecond.
    let mut cfg = config();
    cfg.session_ttl = Duration::from_millis(1);
    let server = start(cfg, Duration::ZERO).await;
    let mut c = client(server.local_addr()).await;
    let (conn, opened) = Conn::open(&mut c).await;
    assert_eq!(opened.session_ttl_ms, 1);
    drop(conn);
    let mut tries = 0;
    loop {
        tries += 1;
        assert!(tries < 10_000, "the detached session never expired");
        tokio::time::sleep(Duration::from_millis(5)).await;
        let mut late = Conn::new(&mut c).await;
        late.send(request(Req::Resume(pb::ResumeSession {
            session_id: opened.session_id.clone(),
            session_token: Vec::new(),
            session_tokens: false,
        })))
        .await;
        match late.next().await {
            Err(status) if status.code() == Code::NotFound => break,
            Ok(Some(Resp::Opened(_))) => continue,
            other => panic!("unexpected {other:?}"),
        }
    }
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn auth_token_and_message_size_are_enforced() {
    let mut cfg = config();
    cfg.auth_token = Some("s3cret".into());
    cfg.max_message_bytes = 2048;
    let server = start(cfg, Duration::ZERO).await;
    let addr = server.local_addr();
    let mut c = client(addr).await;
    let err = c.model_info(pb::ModelInfoRequest {}).await.unwrap_err();
    assert_eq!(err.code(), Code::Unauthenticated);
    let mut req = tonic::Request::new(pb::ModelInfoRequest {});
    req.metadata_mut()
        .insert("authorization", "Bearer wrong".parse().unwrap());
    assert_eq!(
        c.model_info(req).await.unwrap_err().code(),
        Code::Unauthenticated
    );

    // Health stays open without the token.
    assert!(blapose_server::probe_health(addr, None).await.unwrap());

    let channel = Channel::from_shared(format!("http://{addr}"))
        .unwrap()
        .connect()
        .await
        .unwrap();
    let mut authed = PoseAdjustmentClient::with_interceptor(channel, |mut r: tonic::Request<()>| {
        r.metadata_mut()
            .insert("authorization", "Bearer s3cret".parse().unwrap());
        Ok(r)
    });
    let info = authed
        .model_info(pb::ModelInfoRequest {})
        .await
        .unwrap()
        .into_inner();
    assert_eq!(info.models[0].name, "fake");
    assert_eq!(info.protocol, "blapose.v1");
    assert_eq!(info.max_message_bytes, 2048);
    assert_eq!(info.joint_names.len(), 17);
    assert_eq!(info.bone_names.len(), 16);
    assert_eq!(info.layouts.len(), 3);

    // An oversize offline request is refused by the decoder.
    let big = pb::AdjustSequenceRequest {
        input_format: None,
        model: 0,
        num_frames: 10,
        keypoints_2d: vec![0.0; 340],
        confidence: vec![],
        poses_3d: vec![0.0; 510],
        camera: None,
        subject: None,
        motion: None,
    };
    let err = authed.adjust_sequence(big).await.unwrap_err();
    assert_eq!(err.code(), Code::OutOfRange, "{}", err.message());
    // And an oversize frame ends a stream with the same code.
    let (tx, rx) = mpsc::channel(4);
    let mut responses = authed
        .stream(ReceiverStream::new(rx))
        .await
        .unwrap()
        .into_inner();
    tx.send(open_request()).await.unwrap();
    assert!(matches!(
        responses.message().await.unwrap().and_then(|r| r.kind),
        Some(Resp::Opened(_))
    ));
    let mut huge = frame(0);
    if let Some(Req::Frame(f)) = &mut huge.kind {
        f.keypoints_2d = vec![1.0; 1000];
    }
    tx.send(huge).await.unwrap();
    let status = loop {
        match responses.message().await {
            Err(s) => break s,
            Ok(Some(_)) => continue,
            Ok(None) => panic!("stream ended OK"),
        }
    };
    assert_eq!(status.code(), Code::OutOfRange, "{}", status.message());
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn offline_online_model_equals_the_stream() {
    let server = start(config(), Duration::ZERO).await;
    let mut c = client(server.local_addr()).await;
    let (mut conn, _) = Conn::open(&mut c).await;
    let n = 6;
    let mut streamed = Vec::new();
    for i in 0..n {
        conn.send(frame(i)).await;
        streamed.push(conn.frame().await);
    }
    let mut req = pb::AdjustSequenceRequest {
        model: pb::Model::OnlineGru as i32,
        ..sequence_request(n, None)
    };
    let offline = c.adjust_sequence(req.clone()).await.unwrap().into_inner();
    assert_eq!(offline.model, pb::Model::OnlineGru as i32);
    for (t, s) in streamed.iter().enumerate() {
        assert_eq!(
            &offline.bone_lengths[t * 16..(t + 1) * 16],
            &s.bone_lengths[..]
        );
        assert_eq!(
            &offline.adjusted_poses_3d[t * 51..(t + 1) * 51],
            &s.adjusted_pose_3d[..]
        );
    }
    req.model = 0;
    let bigru = c.adjust_sequence(req.clone()).await.unwrap().into_inner();
    assert_eq!(bigru.model, pb::Model::OfflineBigru as i32);
    assert_eq!(bigru.bone_lengths.len(), n as usize * 16);
    assert!(bigru
        .bone_lengths
        .chunks(16)
        .all(|row| (row[3] - 0.303).abs() < 1e-6));
    req.poses_3d[51 * 2 + 9] = f32::INFINITY;
    let err = c.adjust_sequence(req).await.unwrap_err();
    assert_eq!(err.code(), Code::InvalidArgument);
    assert!(err.message().starts_with("frame 2:"), "{}", err.message());
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn shutdown_answers_frames_already_received() {
    // The model holds its steps at a gate (open for the warm-up), so frames
    // are still in flight when shutdown begins.
    let gate = Arc::new(StepGate::new());
    gate.set_open(true);
    let fake = Fake {
        gate: Some(gate.clone()),
        ..Fake::new(Duration::ZERO)
    };
    let server = start_with(config(), fake).await;
    gate.set_open(false);
    let warm_up = gate.entered();
    let addr = server.local_addr();
    assert!(blapose_server::probe_health(addr, None).await.unwrap());
    let mut c = client(addr).await;
    let (mut conn, _) = Conn::open(&mut c).await;
    for i in 0..40 {
        conn.send(frame(i)).await;
    }
    // The first frame is in the model: shut down while it (and whatever
    // else the server has read) waits.
    wait_entered(&gate, warm_up + 1).await;
    server.shutdown_token().cancel();
    let shutdown = tokio::spawn(server.shutdown());
    gate.set_open(true);
    let mut answered = 0;
    let status = loop {
        match conn.next().await {
            Ok(Some(Resp::Frame(f))) => {
                assert_eq!(f.frame_index, answered);
                answered += 1;
            }
            Ok(other) => panic!("unexpected {other:?}"),
            Err(s) => break s,
        }
    };
    assert_eq!(status.code(), Code::Unavailable, "{}", status.message());
    // The text is true: sessions live in this server's memory and end with
    // it, so there is nothing to resume elsewhere.
    assert!(
        status.message().contains("its sessions end with it")
            && status.message().contains("open a new session")
            && !status.message().contains("resume"),
        "{}",
        status.message()
    );
    // Every frame the server received went to the model (it accepts
    // valid frames) and was answered.
    assert!(answered >= 1);
    assert_eq!(
        answered as usize,
        gate.entered() - warm_up,
        "every frame received before shutdown is answered"
    );
    tokio::time::timeout(Duration::from_secs(10), shutdown)
        .await
        .unwrap()
        .unwrap()
        .unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn hostile_frames_never_break_the_stream_or_other_sessions() {
    use rand::{Rng, SeedableRng};
    let server = start(config(), Duration::ZERO).await;
    let mut c = client(server.local_addr()).await;
    let (mut victim, _) = Conn::open(&mut c).await;
    let (mut attacker, _) = Conn::open(&mut c).await;
    let mut rng = rand::rngs::StdRng::seed_from_u64(11);
    let specials = [
        f32::NAN,
        f32::INFINITY,
        f32::NEG_INFINITY,
        f32::MAX,
        -f32::MAX,
        0.0,
        1e30,
        f32::MIN_POSITIVE,
    ];
    let total = 300u64;
    for i in 0..total {
        let mut kp: Vec<f32> = (0..rng.random_range(0..40))
            .map(|_| rng.random_range(-2000.0..2000.0))
            .collect();
        let mut p: Vec<f32> = if rng.random_bool(0.5) {
            pose()
        } else {
            (0..rng.random_range(0..60)).map(|_| rng.random()).collect()
        };
        if !kp.is_empty() && rng.random_bool(0.3) {
            let k = rng.random_range(0..kp.len());
            kp[k] = specials[rng.random_range(0..specials.len())];
        }
        if !p.is_empty() && rng.random_bool(0.3) {
            let k = rng.random_range(0..p.len());
            p[k] = specials[rng.random_range(0..specials.len())];
        }
        let conf: Vec<f32> = if rng.random_bool(0.2) {
            (0..rng.random_range(0..20))
                .map(|_| rng.random_range(-1.0..1.0))
                .collect()
        } else {
            vec![]
        };
        attacker
            .send(request(Req::Frame(pb::Frame {
                frame_index: i,
                keypoints_2d: kp,
                confidence: conf,
                pose_3d: p,
            })))
            .await;
    }
    let mut ok = 0u64;
    for i in 0..total {
        match attacker.next().await.unwrap() {
            Some(Resp::Frame(f)) => {
                assert_eq!(f.frame_index, i);
                ok += 1;
                assert_eq!(f.frames_seen, ok);
                assert!(f.adjusted_pose_3d.iter().all(|v| v.is_finite()));
            }
            Some(Resp::Error(e)) => {
                assert_eq!(e.frame_index, i);
                assert_eq!(e.code, Code::InvalidArgument as i32, "{}", e.message);
            }
            other => panic!("unexpected {other:?}"),
        }
    }
    assert!(ok > 0 && ok < total, "ok {ok}");
    // The victim session is unaffected.
    victim.send(frame(0)).await;
    let f = victim.frame().await;
    assert_eq!(f.frames_seen, 1);
    assert!((f.bone_lengths[0] - expected_mean(0, 1)).abs() < 1e-6);
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn real_engines_serve_random_weights_from_files() {
    use blapose_model::weights::{self, LoadedWeights};
    use blapose_model::ModelKind;
    let dir = std::env::temp_dir().join(format!("blapose-server-test-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let mut paths = Vec::new();
    for (kind, name) in [
        (ModelKind::Gru, "gru.safetensors"),
        (ModelKind::BiGru, "bigru.safetensors"),
    ] {
        let w = LoadedWeights::random(kind, 5).unwrap();
        let path = dir.join(name);
        std::fs::write(&path, weights::to_bytes(w.tensors(), &w.meta).unwrap()).unwrap();
        paths.push(path);
    }
    let mut cfg = config();
    cfg.weights = blapose_server::WeightsSource::File(paths[0].clone());
    cfg.bigru_weights = blapose_server::WeightsSource::File(paths[1].clone());
    cfg.camera_aware = Some(blapose_server::CameraAwareWeights {
        gru: blapose_server::WeightsSource::File(paths[0].clone()),
        bigru: blapose_server::WeightsSource::File(paths[1].clone()),
    });
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let server = blapose_server::spawn(cfg, listener).await.unwrap();
    let mut c = client(server.local_addr()).await;
    let info = c
        .model_info(pb::ModelInfoRequest {})
        .await
        .unwrap()
        .into_inner();
    let names: Vec<(&str, bool)> = info
        .models
        .iter()
        .map(|m| (m.name.as_str(), m.camera_aware))
        .collect();
    assert_eq!(
        names,
        [
            ("bone_length_gru", false),
            ("bone_length_bigru", false),
            ("bone_length_gru_rectified", true),
            ("bone_length_bigru_rectified", true),
        ]
    );
    for m in &info.models {
        assert_eq!(m.parameter_count, 2_390_784);
        assert_eq!(m.hidden_size, 512);
        assert_eq!(m.weights_sha256.len(), 64);
        assert!(m.weights_source.ends_with(".safetensors"));
        assert_eq!(
            m.metadata.get("format").map(String::as_str),
            Some("blapose-bone-length")
        );
        // The precision the server chose (auto, by default) and why.
        let fastest = blapose_model::Precision::fastest().to_string();
        assert_eq!(
            m.metadata.get(blapose_server::models::PRECISION_KEY),
            Some(&fastest)
        );
        let why = &m.metadata[blapose_server::models::PRECISION_REASON_KEY];
        assert!(why.starts_with("auto: the CPU has"), "{why}");
    }
    // Random weights may predict negative lengths, so only the protocol and
    // the state are checked here: one answer per frame, frames counted.
    let (mut conn, _) = Conn::open(&mut c).await;
    for i in 0..5 {
        conn.send(frame(i)).await;
    }
    for i in 0..5 {
        match conn.next().await.unwrap() {
            Some(Resp::Frame(f)) => assert_eq!(f.frames_seen, i + 1),
            Some(Resp::Error(e)) => assert!(e.message.contains("length"), "{}", e.message),
            other => panic!("unexpected {other:?}"),
        }
    }
    server.shutdown().await.unwrap();
    let missing = ServerConfig {
        weights: blapose_server::WeightsSource::File(dir.join("nope.safetensors")),
        camera_aware: None,
        ..config()
    };
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let err = blapose_server::spawn(missing, listener).await.unwrap_err();
    assert!(err.to_string().contains("nope.safetensors"), "{err}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sessions_with_a_camera_get_the_camera_aware_model() {
    let server = start_with(config(), Fake::with_camera_aware(Duration::ZERO)).await;
    let mut c = client(server.local_addr()).await;
    let (mut plain, opened) = Conn::open(&mut c).await;
    assert_eq!(opened.camera, None);
    let (mut aware, opened) = Conn::open_with(&mut c, open_with_camera(Some(calibration()))).await;
    assert_eq!(opened.camera, Some(calibration()));
    // Interleaved, so the two families share batches.
    for i in 0..4 {
        plain.send(frame(i)).await;
        aware.send(frame(i)).await;
    }
    for n in 1..=4 {
        let (p, a) = (plain.frame().await, aware.frame().await);
        assert_eq!((p.frames_seen, a.frames_seen), (n, n));
        for b in 0..16 {
            assert!((p.bone_lengths[b] - expected_mean(b, n)).abs() < 1e-6);
            assert!((a.bone_lengths[b] - (expected_mean(b, n) + 0.1)).abs() < 1e-6);
        }
    }
    // A resumed session keeps its camera and its model.
    drop(aware);
    let (mut resumed, opened) = Conn::open_with(
        &mut c,
        request(Req::Resume(pb::ResumeSession {
            session_id: opened.session_id.clone(),
            session_token: Vec::new(),
            session_tokens: false,
        })),
    )
    .await;
    assert_eq!(opened.camera, Some(calibration()));
    resumed.send(frame(9)).await;
    let f = resumed.frame().await;
    assert_eq!(f.frames_seen, 5);
    assert!((f.bone_lengths[0] - (expected_mean(0, 5) + 0.1)).abs() < 1e-6);

    // Offline: the camera picks the camera-aware Bi-GRU.
    let mut req = sequence_request(2, None);
    let plain_seq = c.adjust_sequence(req.clone()).await.unwrap().into_inner();
    assert!((plain_seq.bone_lengths[0] - 0.3).abs() < 1e-6);
    req.camera = Some(calibration());
    let aware_seq = c.adjust_sequence(req).await.unwrap().into_inner();
    assert!((aware_seq.bone_lengths[0] - 0.4).abs() < 1e-6);
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_or_unserved_cameras_are_refused_at_open() {
    let server = start_with(config(), Fake::with_camera_aware(Duration::ZERO)).await;
    let mut c = client(server.local_addr()).await;
    let bad = [
        (
            pb::CameraCalibration {
                up: vec![0.0, -1.0],
                ..calibration()
            },
            "camera.up has 2 values",
        ),
        (
            pb::CameraCalibration {
                focal_x: f32::NAN,
                ..calibration()
            },
            "camera: focal",
        ),
        (
            pb::CameraCalibration {
                up: vec![0.0, -0.1, -1.0],
                ..calibration()
            },
            "degrees from the horizon",
        ),
        (
            pb::CameraCalibration {
                image_size: Some(pb::ImageSize {
                    width: 640,
                    height: 480,
                }),
                ..calibration()
            },
            "differs from input_format.image_size",
        ),
        (
            pb::CameraCalibration {
                height: 40.0,
                ..calibration()
            },
            "camera.height 40",
        ),
    ];
    for (camera, message) in bad {
        let mut conn = Conn::new(&mut c).await;
        conn.send(open_with_camera(Some(camera))).await;
        let status = conn.status().await;
        assert_eq!(status.code(), Code::InvalidArgument);
        assert!(status.message().contains(message), "{}", status.message());
    }
    // Nothing was opened, and a good session still works.
    let (mut conn, _) = Conn::open_with(&mut c, open_with_camera(Some(calibration()))).await;
    conn.send(frame(0)).await;
    assert_eq!(conn.frame().await.frames_seen, 1);
    server.shutdown().await.unwrap();

    // A server without camera-aware models refuses a camera, stream and
    // offline alike, and serves everything else.
    let server = start(config(), Duration::ZERO).await;
    let mut c = client(server.local_addr()).await;
    let mut conn = Conn::new(&mut c).await;
    conn.send(open_with_camera(Some(calibration()))).await;
    let status = conn.status().await;
    assert_eq!(status.code(), Code::InvalidArgument);
    assert!(
        status.message().contains("no camera-aware models"),
        "{}",
        status.message()
    );
    let req = sequence_request(1, Some(calibration()));
    let err = c.adjust_sequence(req).await.unwrap_err();
    assert_eq!(err.code(), Code::InvalidArgument);
    let (mut conn, _) = Conn::open(&mut c).await;
    conn.send(frame(0)).await;
    assert_eq!(conn.frame().await.frames_seen, 1);
    server.shutdown().await.unwrap();
}

/// Camera-aware models whose input contract reads keypoints scaled to the
/// floor, through the wide cameras: the camera's height is required, a
/// calibration outside those cameras is refused naming the value, and the
/// lengths are the model's own (no scaling), the same bits streamed and
/// offline.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_camera_aware_contract_decides_what_a_calibration_needs() {
    let mut fake = Fake::with_camera_aware(Duration::ZERO);
    fake.camera_aware = Some(Arc::new(Fake {
        offset: 0.1,
        input: ModelInput::from_training(true, true, true),
        ..Fake::new(Duration::ZERO)
    }));
    let server = start_with(config(), fake).await;
    let mut c = client(server.local_addr()).await;
    // Without the camera's height the size cannot be read: refused.
    let no_height = pb::CameraCalibration {
        height: 0.0,
        ..calibration()
    };
    let err = c
        .adjust_sequence(sequence_request(2, Some(no_height.clone())))
        .await
        .unwrap_err();
    assert_eq!(err.code(), Code::InvalidArgument);
    assert!(
        err.message().contains("camera.height is required"),
        "{err:?}"
    );
    let mut conn = Conn::new(&mut c).await;
    conn.send(open_with_camera(Some(no_height))).await;
    let err = conn.status().await;
    assert_eq!(err.code(), Code::InvalidArgument);
    assert!(
        err.message().contains("camera.height is required"),
        "{err:?}"
    );
    // Nor outside the cameras it was trained for, named.
    let too_high = pb::CameraCalibration {
        height: 3.4,
        ..calibration()
    };
    let err = c
        .adjust_sequence(sequence_request(2, Some(too_high)))
        .await
        .unwrap_err();
    assert_eq!(err.code(), Code::InvalidArgument);
    assert!(
        err.message()
            .starts_with("camera.height gives a camera height of 3.40 m"),
        "{err:?}"
    );
    for height in [1.3, 2.6] {
        let camera = pb::CameraCalibration {
            height,
            ..calibration()
        };
        let (mut conn, _) = Conn::open_with(&mut c, open_with_camera(Some(camera.clone()))).await;
        for i in 0..3 {
            conn.send(frame(i)).await;
        }
        let mut streamed = Vec::new();
        for n in 1..=3 {
            let f = conn.frame().await;
            for b in 0..16 {
                let want = expected_mean(b, n) + 0.1;
                assert!((f.bone_lengths[b] - want).abs() < 1e-6, "height {height}");
            }
            streamed.extend(f.bone_lengths);
        }
        // The online GRU offline averages as the stream does: the same
        // bits.
        let gru = c
            .adjust_sequence(pb::AdjustSequenceRequest {
                model: pb::Model::OnlineGru as i32,
                ..sequence_request(3, Some(camera.clone()))
            })
            .await
            .unwrap()
            .into_inner();
        assert_eq!(gru.bone_lengths, streamed, "height {height}");
        let seq = c
            .adjust_sequence(sequence_request(2, Some(camera)))
            .await
            .unwrap()
            .into_inner();
        assert!((seq.bone_lengths[0] - 0.4).abs() < 1e-6, "height {height}");
    }
    // The default models read no camera.
    let (mut conn, _) = Conn::open(&mut c).await;
    conn.send(frame(0)).await;
    assert!((conn.frame().await.bone_lengths[0] - expected_mean(0, 1)).abs() < 1e-6);
    server.shutdown().await.unwrap();
}

/// A subject's stature: every answer's lengths are the stature model's for
/// it (sessions and AdjustSequence alike), echoed on open; a stature out of
/// range, or an unknown sex, is INVALID_ARGUMENT naming the field.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_subject_is_answered_with_the_stature_models_lengths() {
    let server = start(config(), Duration::ZERO).await;
    let mut c = client(server.local_addr()).await;
    let stature = blapose_server::models::embedded_stature_model().unwrap();
    let info = c
        .model_info(pb::ModelInfoRequest {})
        .await
        .unwrap()
        .into_inner();
    assert!(
        info.accepts
            .iter()
            .any(|a| a.starts_with("subject: stature 1-2.3 m")),
        "{:?}",
        info.accepts
    );
    assert!(info.accepts.iter().any(|a| a.starts_with("confidence:")));
    let subject = pb::Subject {
        height_m: 1.64,
        sex: pb::Sex::Female as i32,
    };
    let want = stature.predict(1.64, Some(blapose_model::stature::Sex::Female));
    let mut req = sequence_request(6, None);
    req.subject = Some(subject);
    let done = c.adjust_sequence(req.clone()).await.unwrap().into_inner();
    for lengths in done.bone_lengths.chunks_exact(16) {
        assert_eq!(lengths, want.as_slice());
    }
    let (tx, rx) = mpsc::channel(8);
    let mut open = open_with_camera(None);
    if let Some(Req::Open(o)) = &mut open.kind {
        o.subject = Some(subject);
    }
    tx.send(open).await.unwrap();
    tx.send(frame(0)).await.unwrap();
    let mut responses = c
        .stream(ReceiverStream::new(rx))
        .await
        .unwrap()
        .into_inner();
    match responses.message().await.unwrap().and_then(|r| r.kind) {
        Some(Resp::Opened(o)) => assert_eq!(o.subject, Some(subject)),
        other => panic!("{other:?}"),
    }
    match responses.message().await.unwrap().and_then(|r| r.kind) {
        Some(Resp::Frame(f)) => assert_eq!(f.bone_lengths, want.to_vec()),
        other => panic!("{other:?}"),
    }
    drop(tx);
    for (bad, field) in [
        (
            pb::Subject {
                height_m: 0.9,
                sex: 0,
            },
            "subject.height_m",
        ),
        (
            pb::Subject {
                height_m: f32::NAN,
                sex: 0,
            },
            "subject.height_m",
        ),
        (
            pb::Subject {
                height_m: 1.7,
                sex: 7,
            },
            "subject.sex",
        ),
    ] {
        req.subject = Some(bad);
        let err = c.adjust_sequence(req.clone()).await.unwrap_err();
        assert_eq!(err.code(), Code::InvalidArgument);
        assert!(err.message().contains(field), "{}", err.message());
    }
    server.shutdown().await.unwrap();
}

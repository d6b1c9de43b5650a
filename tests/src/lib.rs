//! blapose-tests: end-to-end tests of the server through the client library.
//!
//! This library holds what the tests in `tests/e2e/` share: a server
//! started in-process on an ephemeral loopback port ([`TestServer`]),
//! deterministic weights written to a temporary directory ([`weights_dir`]),
//! synthetic input ([`synthetic_sequence`]) and the *library path*
//! ([`Reference`]): the same computation done directly with blapose-core and
//! blapose-model's engines, which the server's answers must equal.
//!
//! Weights: the tests must not depend on trained weights being present, so
//! they use seeded random weights with one change: the output layer's
//! weights are made positive and small, so predicted lengths are positive
//! (tens of centimetres) and every adjustment is defined. Only the example
//! replay test needs the shipped weights and skips without them. The server
//! lifter tests use a small causal VideoPose3D with random weights written
//! in the trainer's file format ([`lifter_weights_file`]).

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;
use std::time::Duration;

use blapose_client::{
    CameraCalibration, Client, ClientConfig, Coordinates, KeypointLayout, Sequence,
};
use blapose_core::bones::adjust_pose;
use blapose_core::camera::normalize_screen;
use blapose_core::level::LevelCamera;
use blapose_core::skeleton::NUM_BONES;
use blapose_core::{BoneLengths, Keypoints2d, Pose};
use blapose_lifters::trained::{self, VideoPoseArch};
use blapose_lifters::TrainedLifter;
use blapose_model::weights::{self, LoadedWeights};
use blapose_model::{
    ModelKind, OfflineBiGruEngine, OnlineGruEngine, INPUT_DIM, OUTPUT_DIM, STATE_DIM,
};
use blapose_server::{CameraAwareWeights, ServerConfig, ServerHandle, WeightsSource};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

/// Seed of the test weights.
pub const WEIGHTS_SEED: u64 = 7;
/// Scale of the (positive) output-layer weights: predicted lengths come out
/// at roughly 0.1-0.5 m.
const FC_SCALE: f64 = 0.03;

/// Seeded random weights of `kind` whose output layer is positive.
pub fn test_weights(kind: ModelKind) -> LoadedWeights {
    let random = LoadedWeights::random(kind, WEIGHTS_SEED).expect("random weights");
    let mut tensors = random.tensors().clone();
    if let Some(fc) = tensors.get(blapose_model::names::FC_WEIGHT) {
        let positive = fc
            .abs()
            .and_then(|t| t.affine(FC_SCALE, 0.0))
            .expect("scale fc");
        tensors.insert(blapose_model::names::FC_WEIGHT.to_string(), positive);
    }
    LoadedWeights::from_tensors(tensors, random.meta.clone()).expect("valid weights")
}

/// A directory holding `gru.safetensors` and `bigru.safetensors` made from
/// [`test_weights`], written once per test process. The directory name is
/// fixed (per seed), so repeated runs reuse it instead of leaving a new
/// 19 MB copy behind each time; files are written under a temporary name
/// and renamed, so concurrent test processes never read a partial file.
pub fn weights_dir() -> &'static Path {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        let dir = std::env::temp_dir().join(format!("blapose-tests-weights-seed{WEIGHTS_SEED}"));
        std::fs::create_dir_all(&dir).expect("temp dir");
        for (kind, name) in [
            (ModelKind::Gru, "gru.safetensors"),
            (ModelKind::BiGru, "bigru.safetensors"),
        ] {
            let w = test_weights(kind);
            let bytes = weights::to_bytes(w.tensors(), &w.meta).expect("serialize weights");
            let partial = dir.join(format!("{name}.{}.partial", std::process::id()));
            std::fs::write(&partial, bytes).expect("write weights");
            std::fs::rename(&partial, dir.join(name)).expect("move weights into place");
        }
        dir
    })
}

/// A server configuration for tests: the test weights, loopback only, no
/// metrics exporter, small but sufficient limits.
pub fn test_config() -> ServerConfig {
    let dir = weights_dir();
    ServerConfig {
        weights: WeightsSource::File(dir.join("gru.safetensors")),
        bigru_weights: WeightsSource::File(dir.join("bigru.safetensors")),
        camera_aware: Some(CameraAwareWeights {
            gru: WeightsSource::File(dir.join("gru.safetensors")),
            bigru: WeightsSource::File(dir.join("bigru.safetensors")),
        }),
        metrics_addr: None,
        max_sessions: 1024,
        session_ttl: Duration::from_secs(30),
        max_batch: 32,
        max_queue_delay: Duration::from_millis(1),
        shutdown_grace: Duration::from_secs(10),
        // No server lifter unless a test asks for one (lifter_config).
        lifter: None,
        ..ServerConfig::default()
    }
}

/// Size of the test lifter: 3 x 3 = 9 frames, 16 channels, causal.
pub const TEST_LIFTER: VideoPoseArch = VideoPoseArch {
    filter_width: 3,
    blocks: 1,
    channels: 16,
    dropout: 0.25,
    causal: true,
};

/// Name the server gives the test lifter.
pub const TEST_LIFTER_NAME: &str = "videopose9-causal";

/// Write `bytes` to `name` in the weights directory (under a temporary
/// name, then renamed, so concurrent test processes never read a partial
/// file) and return the path.
fn write_test_file(name: &str, bytes: &[u8]) -> PathBuf {
    let path = weights_dir().join(name);
    let partial = path.with_extension(format!("{}.partial", std::process::id()));
    std::fs::write(&partial, bytes).expect("write test file");
    std::fs::rename(&partial, &path).expect("move test file into place");
    path
}

/// A lifter weights file as `blapose train-lifter` writes it, of size
/// [`TEST_LIFTER`] with seeded random weights; written once per process.
pub fn lifter_weights_file() -> &'static Path {
    static PATH: OnceLock<PathBuf> = OnceLock::new();
    PATH.get_or_init(|| {
        let bytes = trained::random_weights_file(TEST_LIFTER, WEIGHTS_SEED).expect("lifter file");
        write_test_file("lifter_videopose9_causal.safetensors", &bytes)
    })
}

/// The same size and weights, but centred (not servable online).
pub fn centred_lifter_weights_file() -> &'static Path {
    static PATH: OnceLock<PathBuf> = OnceLock::new();
    PATH.get_or_init(|| {
        let arch = VideoPoseArch {
            causal: false,
            ..TEST_LIFTER
        };
        let bytes = trained::random_weights_file(arch, WEIGHTS_SEED).expect("lifter file");
        write_test_file("lifter_videopose9.safetensors", &bytes)
    })
}

/// [`test_config`] with the test lifter as the server lifter.
pub fn lifter_config() -> ServerConfig {
    ServerConfig {
        lifter: Some(WeightsSource::File(lifter_weights_file().to_path_buf())),
        ..test_config()
    }
}

/// The test lifter, loaded as the server loads it.
pub fn test_lifter() -> TrainedLifter {
    TrainedLifter::from_file(lifter_weights_file()).expect("test lifter loads")
}

/// The model input of every frame (see [`Reference::model_inputs`]) as
/// keypoint frames.
pub fn input_frames(seq: &Sequence) -> Vec<Keypoints2d> {
    Reference::model_inputs(seq)
        .chunks_exact(INPUT_DIM)
        .map(|x| std::array::from_fn(|j| [x[2 * j], x[2 * j + 1]]))
        .collect()
}

/// What the server lifter gives for `seq` from a fresh window, frame by
/// frame (the library path: push, lift).
pub fn lifted_reference(lifter: &TrainedLifter, seq: &Sequence) -> Vec<Pose> {
    let mut window = lifter.window();
    input_frames(seq)
        .into_iter()
        .map(|frame| {
            window.push(frame);
            lifter.lift(&mut window).expect("lift")
        })
        .collect()
}

/// A server running in this process on `127.0.0.1:<ephemeral>`.
#[derive(Debug)]
pub struct TestServer {
    /// The server (shut it down with [`TestServer::shutdown`]).
    pub handle: ServerHandle,
    /// Its address.
    pub addr: SocketAddr,
}

impl TestServer {
    /// Start a server with `config` (its `addr` is ignored: the listener is
    /// bound to an ephemeral loopback port).
    pub async fn start(config: ServerConfig) -> TestServer {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
            .await
            .expect("bind loopback");
        let addr = listener.local_addr().expect("local addr");
        let handle = blapose_server::spawn(config, listener)
            .await
            .expect("server starts");
        TestServer { handle, addr }
    }

    /// The URL clients connect to.
    pub fn url(&self) -> String {
        format!("http://{}", self.addr)
    }

    /// A connected client (optionally with a bearer token).
    pub async fn client_with_token(&self, token: Option<&str>) -> Client {
        let mut config = ClientConfig::new(self.url());
        config.token = token.map(str::to_string);
        config.request_timeout = Duration::from_secs(20);
        config.connect_attempts = 3;
        Client::connect(config).await.expect("client connects")
    }

    /// A connected client without a token.
    pub async fn client(&self) -> Client {
        self.client_with_token(None).await
    }

    /// Graceful shutdown.
    pub async fn shutdown(self) {
        self.handle.shutdown().await.expect("clean shutdown");
    }
}

/// A plausible standing pose (metres, camera-like frame, y down) with a
/// little motion at frame `t`; every bone has a non-zero length.
pub fn synthetic_pose(t: usize, rng: &mut StdRng) -> Pose {
    let s = (0.15 * t as f32).sin() * 0.1;
    let mut p: Pose = [
        [0.0, 0.0, 0.0],
        [-0.12, 0.02, 0.0],
        [-0.12 + s, 0.45, 0.05],
        [-0.12 + s, 0.88, 0.1],
        [0.12, 0.02, 0.0],
        [0.12 - s, 0.45, 0.05],
        [0.12 - s, 0.88, 0.1],
        [0.0, -0.22, -0.02],
        [0.0, -0.47, -0.03],
        [0.0, -0.57, -0.08],
        [0.0, -0.69, -0.05],
        [0.15, -0.45, 0.0],
        [0.17 + s, -0.18, 0.02],
        [0.18 + s, 0.06, -0.05],
        [-0.15, -0.45, 0.0],
        [-0.17 - s, -0.18, 0.02],
        [-0.18 - s, 0.06, -0.05],
    ];
    for j in p.iter_mut().skip(1) {
        for v in j.iter_mut() {
            *v += rng.random_range(-0.02..0.02);
        }
    }
    p
}

/// A random but deterministic sequence of `frames` frames in pixels of a
/// 1000 x 1002 image, for `layout`, with ground truth equal to the
/// (unperturbed) poses.
pub fn synthetic_sequence(seed: u64, frames: usize, layout: KeypointLayout) -> Sequence {
    let mut rng = StdRng::seed_from_u64(seed);
    let j = layout.num_joints();
    let mut keypoints = Vec::with_capacity(frames * j * 2);
    let (cx, cy) = (
        rng.random_range(300.0..700.0f32),
        rng.random_range(300.0..700.0f32),
    );
    for t in 0..frames {
        for k in 0..j {
            keypoints.push(
                cx + 8.0 * k as f32 + 3.0 * (t as f32 * 0.2).sin() + rng.random_range(-2.0..2.0),
            );
            keypoints.push(cy + 20.0 * k as f32 - 150.0 + rng.random_range(-2.0..2.0));
        }
    }
    let pose_3d: Vec<Pose> = (0..frames).map(|t| synthetic_pose(t, &mut rng)).collect();
    Sequence {
        input_format: blapose_client::InputFormat::pixels(layout, 1000, 1002),
        keypoints_2d: keypoints,
        confidence: Vec::new(),
        gt_3d: Some(pose_3d.clone()),
        pose_3d,
        fps: Some(50.0),
        camera: None,
        subject: None,
    }
}

/// A camera 14 degrees down, off-centre principal point, for the
/// synthetic sequences' 1000 x 1002 images.
pub fn test_camera() -> CameraCalibration {
    let tilt = 14f32.to_radians();
    CameraCalibration {
        up: [0.02, -tilt.cos(), -tilt.sin()],
        focal: [1150.0, 1148.0],
        principal: [508.0, 497.0],
        image_size: None,
        height: Some(1.45),
        distortion: None,
    }
}

/// The library path: the server's computation done directly.
///
/// Online: convert the keypoints to Human3.6M-17 and normalized screen
/// coordinates, run one GRU step per frame from a zero state, keep the
/// running mean (in f64) of the per-frame predictions, and adjust each pose
/// to it with [`blapose_core::bones::adjust_pose`]. Offline: one Bi-GRU
/// prediction for the whole sequence, applied to every frame.
pub struct Reference {
    gru: OnlineGruEngine,
    bigru: OfflineBiGruEngine,
}

impl Default for Reference {
    fn default() -> Self {
        Self::new()
    }
}

impl Reference {
    /// Engines built from [`test_weights`].
    pub fn new() -> Reference {
        Reference {
            gru: OnlineGruEngine::new(&test_weights(ModelKind::Gru), 1).expect("gru engine"),
            bigru: OfflineBiGruEngine::new(&test_weights(ModelKind::BiGru), 1)
                .expect("bigru engine"),
        }
    }

    /// Normalized Human3.6M-17 model input of every frame (`T x 34`),
    /// rectified with the sequence's camera when it has one (the test
    /// server's camera-aware models are the same random weights, so a
    /// calibrated session differs only by that).
    pub fn model_inputs(seq: &Sequence) -> Vec<f32> {
        let layout = seq.input_format.layout;
        let per_frame = layout.num_joints() * 2;
        let mut out = Vec::with_capacity(seq.len() * INPUT_DIM);
        for frame in seq.keypoints_2d.chunks_exact(per_frame) {
            let points: Vec<[f32; 2]> = frame.chunks_exact(2).map(|c| [c[0], c[1]]).collect();
            let h36m = layout.to_h36m17(&points).expect("valid keypoints");
            for p in h36m {
                let n = match seq.input_format.coordinates {
                    Coordinates::Pixels { width, height } => normalize_screen(p, width, height),
                    Coordinates::Normalized => p,
                };
                out.extend_from_slice(&n);
            }
        }
        if let Some(camera) = &seq.camera {
            Reference::level_camera(seq, camera).rectify_frames(&mut out);
        }
        out
    }

    /// The level twin the server builds from a session's calibration.
    fn level_camera(seq: &Sequence, camera: &CameraCalibration) -> LevelCamera {
        let (width, height) = camera
            .image_size
            .unwrap_or(match seq.input_format.coordinates {
                Coordinates::Pixels { width, height } => (width, height),
                Coordinates::Normalized => {
                    panic!("a normalized sequence's camera needs an image size")
                }
            });
        LevelCamera::from_pixels(
            camera.up.map(f64::from),
            camera.focal.map(f64::from),
            camera.principal.map(f64::from),
            width,
            height,
        )
        .expect("valid camera")
    }

    /// Online results for `seq` from a fresh state: adjusted poses and the
    /// running estimate after each frame.
    pub fn online(&self, seq: &Sequence) -> (Vec<Pose>, Vec<BoneLengths>) {
        let inputs = Reference::model_inputs(seq);
        let mut hidden = vec![0.0f32; STATE_DIM];
        let mut out = vec![0.0f32; OUTPUT_DIM];
        let mut scratch = self.gru.scratch(1);
        let mut sum = [0.0f64; NUM_BONES];
        let mut poses = Vec::with_capacity(seq.len());
        let mut lengths = Vec::with_capacity(seq.len());
        for (t, x) in inputs.chunks_exact(INPUT_DIM).enumerate() {
            self.gru
                .step(x, &mut hidden, &mut out, &mut scratch)
                .expect("gru step");
            for (s, v) in sum.iter_mut().zip(&out) {
                *s += f64::from(*v);
            }
            let estimate: BoneLengths = sum.map(|s| (s / (t + 1) as f64) as f32);
            poses.push(adjust_pose(&seq.pose_3d[t], &estimate).expect("adjust"));
            lengths.push(estimate);
        }
        (poses, lengths)
    }

    /// Online results for `seq` when the poses are `lifted` (one per frame)
    /// instead of the sequence's own: the lengths depend on the keypoints
    /// only, so they are [`Reference::online`]'s.
    pub fn online_lifted(&self, seq: &Sequence, lifted: &[Pose]) -> (Vec<Pose>, Vec<BoneLengths>) {
        let (_, lengths) = self.online(seq);
        let poses = lifted
            .iter()
            .zip(&lengths)
            .map(|(p, l)| adjust_pose(p, l).expect("adjust"))
            .collect();
        (poses, lengths)
    }

    /// Offline Bi-GRU results for `seq`.
    pub fn offline(&self, seq: &Sequence) -> (Vec<Pose>, BoneLengths) {
        let lengths = self
            .bigru
            .predict(&Reference::model_inputs(seq))
            .expect("bigru");
        let poses = seq
            .pose_3d
            .iter()
            .map(|p| adjust_pose(p, &lengths).expect("adjust"))
            .collect();
        (poses, lengths)
    }
}

/// Largest absolute difference between two poses.
pub fn pose_diff(a: &Pose, b: &Pose) -> f32 {
    a.iter()
        .flatten()
        .zip(b.iter().flatten())
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

/// Largest absolute difference between two length vectors.
pub fn lengths_diff(a: &BoneLengths, b: &BoneLengths) -> f32 {
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

/// Tolerance for server-vs-library comparisons (metres): batched and
/// single-row GRU steps may round differently in the last bits.
pub const TOLERANCE: f32 = 2e-5;

/// The workspace root (for `examples/`).
pub fn workspace_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

//! Server configuration: the command line (clap, with a `BLAPOSE_*`
//! environment fallback for every flag) and the plain [`ServerConfig`] the
//! library runs on.
//!
//! The two are separate on purpose: the CLI is about parsing and `--help`,
//! while [`ServerConfig`] is what tests and embedders build directly (with
//! sub-second TTLs, no metrics port, a weights file of their choice) without
//! going through argument strings. [`Cli::into_config`] is the only bridge.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

use blapose_model::Precision;
use clap::builder::TypedValueParser;
use clap::{Parser, ValueEnum};

use crate::token::SessionKey;
use crate::transport::{ConnectionLimits, TlsFiles};
use crate::web::config::{WebArgs, WebConfig};

/// Where a model's weights come from.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub enum WeightsSource {
    /// The safetensors file embedded in the binary at build time
    /// (`models/*.safetensors`).
    #[default]
    Embedded,
    /// A safetensors file on disk.
    File(PathBuf),
}

impl WeightsSource {
    /// The file a weights flag names, or the embedded weights without one.
    pub fn from_flag(path: Option<PathBuf>) -> Self {
        path.map_or(Self::Embedded, Self::File)
    }

    /// Where the weights come from, as `ModelInfo` and messages say it:
    /// "embedded" or the file's path.
    pub fn origin(&self) -> String {
        match self {
            Self::Embedded => "embedded".to_string(),
            Self::File(path) => path.display().to_string(),
        }
    }
}

/// Log output format.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, ValueEnum)]
pub enum LogFormat {
    /// Human-readable lines.
    #[default]
    Text,
    /// One JSON object per line (for log collectors).
    Json,
}

/// Weights of the camera-aware (rectified) model pair.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct CameraAwareWeights {
    /// Online GRU.
    pub gru: WeightsSource,
    /// Offline Bi-GRU.
    pub bigru: WeightsSource,
}

/// Everything the server needs to run; [`Default`] matches the CLI defaults
/// except that no metrics endpoint is started (the Prometheus recorder is
/// process-global, so in-process test servers leave it off).
#[derive(Debug, Clone)]
pub struct ServerConfig {
    /// Prometheus `/metrics` listen address; `None` disables the exporter.
    pub metrics_addr: Option<SocketAddr>,
    /// Online GRU weights.
    pub weights: WeightsSource,
    /// Offline Bi-GRU weights.
    pub bigru_weights: WeightsSource,
    /// The camera-aware models (for sessions and requests that send a
    /// camera calibration); `None`: such sessions are refused.
    pub camera_aware: Option<CameraAwareWeights>,
    /// The trained causal lifter the server runs for sessions that send 2D
    /// keypoints only (`server_lifter`); `None`: no server lifter (clients
    /// send their own 3D poses).
    pub lifter: Option<WeightsSource>,
    /// Maximum number of sessions held (attached or detached).
    pub max_sessions: usize,
    /// How long a detached session survives before it is evicted.
    pub session_ttl: Duration,
    /// Maximum frames per batched GRU step.
    pub max_batch: usize,
    /// Maximum frames per step while frames of more than one client wait.
    pub max_mixed_batch: usize,
    /// Longest time the batcher waits for more sessions' frames before it
    /// runs a partial batch.
    pub max_queue_delay: Duration,
    /// Frames that may wait in the batcher queue (all sessions together);
    /// beyond it frames are refused with RESOURCE_EXHAUSTED.
    pub queue_capacity: usize,
    /// How long a new stream may take to send its first message (open or
    /// resume) before it is ended with DEADLINE_EXCEEDED; without a limit a
    /// silent client would hold its stream forever.
    pub open_timeout: Duration,
    /// Frames one stream may have in flight before the server stops reading
    /// from it (HTTP/2 flow control then pushes back on the client).
    pub max_inflight_per_stream: usize,
    /// Threads the model backend may use for one batched step and for
    /// offline requests.
    pub compute_threads: usize,
    /// Storage precision of the GRU weights in the fast engines (by
    /// default the fastest on this CPU, [`Precision::fastest`]).
    pub weight_precision: Precision,
    /// HTTP/2 streams one connection may have open at once (advertised in
    /// SETTINGS_MAX_CONCURRENT_STREAMS; beyond it, REFUSED_STREAM).
    pub max_concurrent_streams: u32,
    /// Largest header list (all of one request's headers, decoded) a
    /// connection may send (SETTINGS_MAX_HEADER_LIST_SIZE).
    pub max_header_list_bytes: u32,
    /// Connections held at once, all peers together, and from one IP
    /// address; the deadline for a new one's TLS handshake and preface.
    pub connection_limits: ConnectionLimits,
    /// Optional TLS.
    pub tls: Option<TlsFiles>,
    /// Optional bearer token required on blapose.v1 calls.
    pub auth_token: Option<String>,
    /// Largest request message accepted, in bytes.
    pub max_message_bytes: usize,
    /// How long shutdown waits for in-flight work before giving up.
    pub shutdown_grace: Duration,
    /// The key that authenticates session tokens (shared by replicas);
    /// `None`: no tokens are issued or accepted.
    pub session_key: Option<SessionKey>,
    /// With a key: send a session token every this many processed frames
    /// of a session (0: only in SessionOpened and on request).
    pub token_every: u64,
    /// How long a session token is accepted after it was issued.
    pub token_ttl: Duration,
    /// Sessions one client may hold; `None`: half of `max_sessions`.
    pub max_sessions_per_client: Option<usize>,
    /// Frames one session may have waiting in the batcher queue.
    pub max_frames_per_session: usize,
    /// Frames one client may have waiting in the batcher queue; `None`:
    /// half of `queue_capacity`.
    pub max_queued_frames_per_client: Option<usize>,
    /// Header naming the client, set by a load balancer (see
    /// `trusted_proxies`); `None`: the client is the peer address.
    pub client_header: Option<String>,
    /// Peers whose `client_header` is believed.
    pub trusted_proxies: Vec<std::net::IpAddr>,
    /// The browser transport (`--web-addr`); `None`: off.
    pub web: Option<WebConfig>,
    /// Idle and aged connections, control-frame floods.
    pub protection: crate::protect::Protection,
}

impl Default for ServerConfig {
    fn default() -> Self {
        Self {
            metrics_addr: None,
            weights: WeightsSource::Embedded,
            bigru_weights: WeightsSource::Embedded,
            camera_aware: Some(CameraAwareWeights::default()),
            lifter: Some(WeightsSource::Embedded),
            max_sessions: DEFAULT_MAX_SESSIONS,
            session_ttl: Duration::from_secs(DEFAULT_SESSION_TTL_S),
            max_batch: DEFAULT_MAX_BATCH,
            max_mixed_batch: DEFAULT_MAX_MIXED_BATCH,
            max_queue_delay: Duration::from_micros(DEFAULT_MAX_QUEUE_DELAY_US),
            queue_capacity: DEFAULT_QUEUE_CAPACITY,
            open_timeout: Duration::from_secs(DEFAULT_OPEN_TIMEOUT_S),
            max_inflight_per_stream: DEFAULT_MAX_INFLIGHT,
            compute_threads: DEFAULT_COMPUTE_THREADS,
            weight_precision: Precision::fastest(),
            max_concurrent_streams: DEFAULT_MAX_CONCURRENT_STREAMS,
            max_header_list_bytes: DEFAULT_MAX_HEADER_LIST_BYTES,
            connection_limits: ConnectionLimits {
                max_connections: DEFAULT_MAX_CONNECTIONS,
                max_connections_per_peer: DEFAULT_MAX_CONNECTIONS_PER_PEER,
                handshake_timeout: Duration::from_secs(DEFAULT_HANDSHAKE_TIMEOUT_S),
            },
            tls: None,
            auth_token: None,
            max_message_bytes: DEFAULT_MAX_MESSAGE_BYTES,
            shutdown_grace: Duration::from_secs(DEFAULT_SHUTDOWN_GRACE_S),
            session_key: None,
            token_every: DEFAULT_TOKEN_EVERY,
            token_ttl: Duration::from_secs(DEFAULT_TOKEN_TTL_S),
            max_sessions_per_client: None,
            max_frames_per_session: DEFAULT_MAX_FRAMES_PER_SESSION,
            max_queued_frames_per_client: None,
            client_header: None,
            trusted_proxies: Vec::new(),
            web: None,
            protection: crate::protect::Protection::default(),
        }
    }
}

const DEFAULT_TOKEN_TTL_S: u64 = 3600;
const DEFAULT_MAX_FRAMES_PER_SESSION: usize = 128;

const DEFAULT_MAX_SESSIONS: usize = 4096;
const DEFAULT_SESSION_TTL_S: u64 = 60;
const DEFAULT_MAX_BATCH: usize = 64;
// A step of 16 frames takes a quarter of one of 64 and the server made the
// same frames/s with either (bench loadtest, 256 streams, 2-core EPYC: 20.1k
// at 16, 32 and 64); beside 8 saturating clients a new client's p50 went
// from 6.4 to 1.7 ms (tests/abuse/README.md, shares8).
const DEFAULT_MAX_MIXED_BATCH: usize = 16;
const DEFAULT_MAX_QUEUE_DELAY_US: u64 = 1000;
const DEFAULT_QUEUE_CAPACITY: usize = 8192;
const DEFAULT_MAX_INFLIGHT: usize = 64;
const DEFAULT_COMPUTE_THREADS: usize = 1;
const DEFAULT_MAX_MESSAGE_BYTES: usize = 4 * 1024 * 1024;
const DEFAULT_SHUTDOWN_GRACE_S: u64 = 10;
const DEFAULT_OPEN_TIMEOUT_S: u64 = 10;
const DEFAULT_TOKEN_EVERY: u64 = 100;
// Transport limits. 100 streams a connection, the least RFC 9113 advises
// (nginx 128, Go 250): h2 takes that many HEADERS on each connection before
// the stream layer refuses any, about 2 KB each, so 512 connections of one
// address x 1,000 grew the server by 0.7-1.0 GB and x 100 by 108 MB
// (tests/abuse/README.md). Clients queue beyond it or open more
// connections: bench loadtest spreads its streams over a connection per 32.
const DEFAULT_MAX_CONCURRENT_STREAMS: u32 = 100;
const DEFAULT_MAX_HEADER_LIST_BYTES: u32 = 16 * 1024;
const DEFAULT_MAX_CONNECTIONS: usize = 4096;
const DEFAULT_MAX_CONNECTIONS_PER_PEER: usize = 512;
const DEFAULT_HANDSHAKE_TIMEOUT_S: u64 = 10;

/// blapose-server: streaming BLAPose bone-length adjustment over gRPC.
///
/// Clients open a session, stream 2D keypoints and lifted 3D poses frame by
/// frame, and get back poses rebuilt with the bone lengths a GRU predicts
/// from the keypoint stream. Every flag can also be set through the
/// environment variable shown with it.
#[derive(Debug, Clone, Parser)]
#[command(name = "blapose-server", version, about, long_about)]
pub struct Cli {
    /// gRPC listen address (use 0.0.0.0:50051 inside a container).
    #[arg(long, env = "BLAPOSE_ADDR", default_value = "127.0.0.1:50051")]
    pub addr: SocketAddr,

    /// Prometheus metrics listen address; metrics are served at /metrics.
    #[arg(long, env = "BLAPOSE_METRICS_ADDR", default_value = "127.0.0.1:9090")]
    pub metrics_addr: SocketAddr,

    /// Do not start the Prometheus metrics endpoint.
    #[arg(long, env = "BLAPOSE_NO_METRICS")]
    pub no_metrics: bool,

    /// Online GRU weights (safetensors); default: the weights embedded in this binary.
    #[arg(long, env = "BLAPOSE_WEIGHTS", value_name = "FILE")]
    pub weights: Option<PathBuf>,

    /// Offline Bi-GRU weights (safetensors); default: the weights embedded in this binary.
    #[arg(long, env = "BLAPOSE_BIGRU_WEIGHTS", value_name = "FILE")]
    pub bigru_weights: Option<PathBuf>,

    /// Camera-aware online GRU weights, serving sessions that send a camera
    /// calibration; default: the embedded rectified GRU.
    #[arg(long, env = "BLAPOSE_RECTIFIED_WEIGHTS", value_name = "FILE")]
    pub rectified_weights: Option<PathBuf>,

    /// Camera-aware offline Bi-GRU weights (AdjustSequence with a camera
    /// calibration); default: the embedded rectified Bi-GRU.
    #[arg(long, env = "BLAPOSE_RECTIFIED_BIGRU_WEIGHTS", value_name = "FILE")]
    pub rectified_bigru_weights: Option<PathBuf>,

    /// Serve no camera-aware models: sessions and requests that send a camera
    /// calibration are refused with INVALID_ARGUMENT.
    #[arg(long, env = "BLAPOSE_NO_CAMERA_AWARE",
          conflicts_with_all = ["rectified_weights", "rectified_bigru_weights"])]
    pub no_camera_aware: bool,

    /// The causal lifter for sessions opened with server_lifter (they send 2D
    /// keypoints only and the server lifts them): a `blapose train-lifter --model
    /// videopose --causal` weights file; default: the embedded
    /// lifter_videopose27_causal.
    #[arg(long, env = "BLAPOSE_LIFTER_WEIGHTS", value_name = "FILE")]
    pub lifter_weights: Option<PathBuf>,

    /// Serve no lifter: sessions that ask for server_lifter are refused with
    /// INVALID_ARGUMENT (clients send their own 3D poses).
    #[arg(long, env = "BLAPOSE_NO_LIFTER", conflicts_with = "lifter_weights")]
    pub no_lifter: bool,

    /// Maximum sessions held at once (attached or detached); more -> RESOURCE_EXHAUSTED.
    #[arg(long, env = "BLAPOSE_MAX_SESSIONS", default_value_t = DEFAULT_MAX_SESSIONS,
          value_parser = clap::value_parser!(u32).range(1..).map(|v| v as usize))]
    pub max_sessions: usize,

    /// How long a session without a stream is kept for resumption (e.g. 60s, 500ms, 5m).
    #[arg(long, env = "BLAPOSE_SESSION_TTL", default_value = "60s", value_parser = parse_duration)]
    pub session_ttl: Duration,

    /// Maximum frames (one per session) per batched GRU step.
    #[arg(long, env = "BLAPOSE_MAX_BATCH", default_value_t = DEFAULT_MAX_BATCH,
          value_parser = clap::value_parser!(u32).range(1..=4096).map(|v| v as usize))]
    pub max_batch: usize,

    /// Maximum frames per batched step while frames of more than one client are waiting:
    /// a client's frame then waits for short steps of the others (default 16, at most
    /// --max-batch).
    #[arg(long, env = "BLAPOSE_MAX_MIXED_BATCH", default_value_t = DEFAULT_MAX_MIXED_BATCH,
          value_parser = clap::value_parser!(u32).range(1..=4096).map(|v| v as usize))]
    pub max_mixed_batch: usize,

    /// Longest wait for more sessions' frames before running a partial batch (e.g. 1ms, 500us, 0).
    #[arg(long, env = "BLAPOSE_MAX_QUEUE_DELAY", default_value = "1ms", value_parser = parse_duration)]
    pub max_queue_delay: Duration,

    /// Frames that may wait for the model, all sessions together; beyond it -> RESOURCE_EXHAUSTED.
    #[arg(long, env = "BLAPOSE_QUEUE_CAPACITY", default_value_t = DEFAULT_QUEUE_CAPACITY,
          value_parser = clap::value_parser!(u32).range(1..).map(|v| v as usize))]
    pub queue_capacity: usize,

    /// How long a new stream may take to send its open or resume request; then DEADLINE_EXCEEDED.
    #[arg(long, env = "BLAPOSE_OPEN_TIMEOUT", default_value = "10s", value_parser = parse_open_timeout)]
    pub open_timeout: Duration,

    /// Frames one stream may have in flight before the server stops reading it (flow control).
    #[arg(long, env = "BLAPOSE_MAX_INFLIGHT_PER_STREAM", default_value_t = DEFAULT_MAX_INFLIGHT,
          value_parser = clap::value_parser!(u32).range(1..).map(|v| v as usize))]
    pub max_inflight_per_stream: usize,

    /// Threads for model computation (batched steps and offline requests).
    #[arg(long, env = "BLAPOSE_COMPUTE_THREADS", default_value_t = DEFAULT_COMPUTE_THREADS,
          value_parser = clap::value_parser!(u32).range(1..=256).map(|v| v as usize))]
    pub compute_threads: usize,

    /// Storage precision of the GRU weights: auto (the default: what
    /// serves fastest on this CPU, bf16 with AMX, f16 elsewhere, AMD Zen 4
    /// included; the choice and why are in the start-up log and
    /// ModelInfo), f16 (lengths within ~1e-5 m of f32; arithmetic stays
    /// f32), bf16 (bf16 weights and matrix inputs on the CPU's bf16 units,
    /// AMX or AVX512-BF16; refused at start on CPUs without AVX512-BF16) or
    /// f32 (agrees with the reference to ~1e-6; only on request).
    #[arg(long, env = "BLAPOSE_WEIGHT_PRECISION", default_value = "auto", value_parser = parse_precision)]
    pub weight_precision: Precision,

    /// Log format.
    #[arg(long, env = "BLAPOSE_LOG_FORMAT", value_enum, default_value_t = LogFormat::Text)]
    pub log_format: LogFormat,

    /// TLS certificate chain (PEM); requires --tls-key. Without both, plaintext HTTP/2.
    #[arg(
        long,
        env = "BLAPOSE_TLS_CERT",
        value_name = "PEM",
        requires = "tls_key"
    )]
    pub tls_cert: Option<PathBuf>,

    /// TLS private key (PEM); requires --tls-cert.
    #[arg(
        long,
        env = "BLAPOSE_TLS_KEY",
        value_name = "PEM",
        requires = "tls_cert"
    )]
    pub tls_key: Option<PathBuf>,

    /// Require `authorization: Bearer <TOKEN>` on blapose.v1 calls (health and reflection stay open).
    #[arg(
        long,
        env = "BLAPOSE_AUTH_TOKEN",
        value_name = "TOKEN",
        hide_env_values = true
    )]
    pub auth_token: Option<String>,

    /// Largest request message accepted, in bytes; larger -> OUT_OF_RANGE.
    #[arg(long, env = "BLAPOSE_MAX_MESSAGE_BYTES", default_value_t = DEFAULT_MAX_MESSAGE_BYTES,
          value_parser = clap::value_parser!(u32).range(1024..).map(|v| v as usize))]
    pub max_message_bytes: usize,

    /// On SIGTERM/Ctrl-C, how long to wait for in-flight frames before exiting anyway.
    #[arg(long, env = "BLAPOSE_SHUTDOWN_GRACE", default_value = "10s", value_parser = parse_duration)]
    pub shutdown_grace: Duration,

    /// Key authenticating session tokens (HMAC-SHA256), shared by every replica that may resume
    /// another's sessions: `hex:<digits>`, `base64:<text>`, or else the string's own bytes; at
    /// least 16 bytes (32 random bytes recommended, e.g. `hex:$(openssl rand -hex 32)`). With
    /// it, clients get a session token on open/resume, every --token-every frames and on request,
    /// and a resume with a token restores the session on a replica that does not hold it.
    /// Without it, no tokens are issued or accepted.
    #[arg(long, env = "BLAPOSE_SESSION_KEY", value_name = "KEY", hide_env_values = true,
          value_parser = parse_session_key)]
    pub session_key: Option<SessionKey>,

    /// With --session-key: send each session a token every N processed frames (0: only when
    /// opened or resumed and on request).
    #[arg(long, env = "BLAPOSE_TOKEN_EVERY", value_name = "N", default_value_t = DEFAULT_TOKEN_EVERY)]
    pub token_every: u64,

    /// With --session-key: how long a session token is accepted after it was issued (every
    /// replica refuses it afterwards); also how long a closed session's id is remembered.
    #[arg(long, env = "BLAPOSE_TOKEN_TTL", default_value = "1h", value_parser = parse_duration)]
    pub token_ttl: Duration,

    /// Sessions one client (see --client-header) may hold; more -> RESOURCE_EXHAUSTED.
    /// Default: half of --max-sessions, at least 1024 (all of a smaller table).
    #[arg(long, env = "BLAPOSE_MAX_SESSIONS_PER_CLIENT", value_name = "N",
          value_parser = clap::value_parser!(u32).range(1..).map(|v| v as usize))]
    pub max_sessions_per_client: Option<usize>,

    /// Frames one session may have waiting for the model; more -> RESOURCE_EXHAUSTED.
    #[arg(long, env = "BLAPOSE_MAX_FRAMES_PER_SESSION", default_value_t = DEFAULT_MAX_FRAMES_PER_SESSION,
          value_parser = clap::value_parser!(u32).range(1..).map(|v| v as usize))]
    pub max_frames_per_session: usize,

    /// Frames one client may have waiting for the model; more -> RESOURCE_EXHAUSTED.
    /// Default: half of --queue-capacity, at least 1024 (all of a smaller queue).
    #[arg(long, env = "BLAPOSE_MAX_QUEUED_FRAMES_PER_CLIENT", value_name = "N",
          value_parser = clap::value_parser!(u32).range(1..).map(|v| v as usize))]
    pub max_queued_frames_per_client: Option<usize>,

    /// Header that names the client behind a load balancer (e.g. x-blapose-client), believed
    /// only from --trusted-proxies; without it a client is its peer IP address.
    #[arg(long, env = "BLAPOSE_CLIENT_HEADER", value_name = "HEADER")]
    pub client_header: Option<String>,

    /// Comma-separated IP addresses of the load balancers allowed to set --client-header.
    #[arg(
        long,
        env = "BLAPOSE_TRUSTED_PROXIES",
        value_name = "IP,...",
        value_delimiter = ','
    )]
    pub trusted_proxies: Vec<std::net::IpAddr>,

    /// Act as a health-check client instead: query grpc.health.v1 at --addr, exit 0 if SERVING,
    /// else 1. With --tls-cert it connects over TLS (see --tls-ca, --tls-domain).
    #[arg(long)]
    pub health_check: bool,

    /// For --health-check over TLS: PEM of the CA to trust; default: the certificates in
    /// --tls-cert (right for a self-signed certificate or a file with the full chain).
    #[arg(long, env = "BLAPOSE_TLS_CA", value_name = "PEM")]
    pub tls_ca: Option<PathBuf>,

    /// For --health-check over TLS: the name to verify the server's certificate against
    /// (one of its DNS names); default: localhost.
    #[arg(long, env = "BLAPOSE_TLS_DOMAIN", value_name = "NAME")]
    pub tls_domain: Option<String>,

    /// HTTP/2 streams one connection may have open at once (advertised to clients, which
    /// queue beyond it; a client that ignores it gets REFUSED_STREAM).
    #[arg(long, env = "BLAPOSE_MAX_CONCURRENT_STREAMS", default_value_t = DEFAULT_MAX_CONCURRENT_STREAMS,
          value_parser = clap::value_parser!(u32).range(1..))]
    pub max_concurrent_streams: u32,

    /// Largest header list (one request's headers, decoded) a client may send, in bytes.
    #[arg(long, env = "BLAPOSE_MAX_HEADER_LIST_BYTES", default_value_t = DEFAULT_MAX_HEADER_LIST_BYTES,
          value_parser = clap::value_parser!(u32).range(1024..))]
    pub max_header_list_bytes: u32,

    /// TCP connections held at once, all clients together; more are closed at accept.
    #[arg(long, env = "BLAPOSE_MAX_CONNECTIONS", default_value_t = DEFAULT_MAX_CONNECTIONS,
          value_parser = clap::value_parser!(u32).range(1..).map(|v| v as usize))]
    pub max_connections: usize,

    /// TCP connections held at once from one IP address (a load balancer is one address:
    /// raise it there); more are closed at accept.
    #[arg(long, env = "BLAPOSE_MAX_CONNECTIONS_PER_PEER", default_value_t = DEFAULT_MAX_CONNECTIONS_PER_PEER,
          value_parser = clap::value_parser!(u32).range(1..).map(|v| v as usize))]
    pub max_connections_per_peer: usize,

    /// Time a new connection has to finish its TLS handshake and send the HTTP/2 preface.
    #[arg(long, env = "BLAPOSE_HANDSHAKE_TIMEOUT", default_value = "10s", value_parser = parse_open_timeout)]
    pub handshake_timeout: Duration,

    #[command(flatten)]
    pub web: WebArgs,
    /// Idle and aged connections, control-frame floods.
    #[command(flatten)]
    pub protection: crate::protect::ProtectionArgs,
}

/// How `--health-check` connects to a server with TLS on: it verifies the
/// server's certificate as any client would (blapose-client takes the same
/// `--tls-ca` and `--tls-domain`), trusting `ca` and checking `domain`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct HealthCheckTls {
    /// PEM certificates to trust.
    pub ca: PathBuf,
    /// The name the certificate must be valid for.
    pub domain: String,
}

/// The name `--health-check` checks the certificate against by default: it
/// connects to the server's own port on the loopback interface.
pub const DEFAULT_HEALTH_CHECK_DOMAIN: &str = "localhost";

impl Cli {
    /// How `--health-check` reaches a server these flags start: over TLS
    /// when `--tls-cert` is set (the server then speaks nothing else),
    /// trusting `--tls-ca` or else the certificate file itself, for the name
    /// `--tls-domain` or else `localhost`; `None`: plaintext.
    pub fn health_check_tls(&self) -> Option<HealthCheckTls> {
        let cert = self.tls_cert.as_ref()?;
        Some(HealthCheckTls {
            ca: self.tls_ca.clone().unwrap_or_else(|| cert.clone()),
            domain: self
                .tls_domain
                .clone()
                .filter(|d| !d.is_empty())
                .unwrap_or_else(|| DEFAULT_HEALTH_CHECK_DOMAIN.to_string()),
        })
    }

    /// The library configuration these flags describe.
    pub fn into_config(self) -> ServerConfig {
        let tls = match (self.tls_cert, self.tls_key) {
            (Some(cert), Some(key)) => Some(TlsFiles { cert, key }),
            _ => None,
        };
        ServerConfig {
            metrics_addr: (!self.no_metrics).then_some(self.metrics_addr),
            weights: WeightsSource::from_flag(self.weights),
            bigru_weights: WeightsSource::from_flag(self.bigru_weights),
            camera_aware: (!self.no_camera_aware).then(|| CameraAwareWeights {
                gru: WeightsSource::from_flag(self.rectified_weights),
                bigru: WeightsSource::from_flag(self.rectified_bigru_weights),
            }),
            lifter: (!self.no_lifter).then(|| WeightsSource::from_flag(self.lifter_weights)),
            max_sessions: self.max_sessions,
            session_ttl: self.session_ttl,
            max_batch: self.max_batch,
            max_mixed_batch: self.max_mixed_batch,
            max_queue_delay: self.max_queue_delay,
            queue_capacity: self.queue_capacity,
            open_timeout: self.open_timeout,
            max_inflight_per_stream: self.max_inflight_per_stream,
            compute_threads: self.compute_threads,
            weight_precision: self.weight_precision,
            max_concurrent_streams: self.max_concurrent_streams,
            max_header_list_bytes: self.max_header_list_bytes,
            connection_limits: ConnectionLimits {
                max_connections: self.max_connections,
                max_connections_per_peer: self.max_connections_per_peer,
                handshake_timeout: self.handshake_timeout,
            },
            tls,
            auth_token: self.auth_token.filter(|t| !t.is_empty()),
            max_message_bytes: self.max_message_bytes,
            shutdown_grace: self.shutdown_grace,
            session_key: self.session_key,
            token_every: self.token_every,
            token_ttl: self.token_ttl,
            max_sessions_per_client: self.max_sessions_per_client,
            max_frames_per_session: self.max_frames_per_session,
            max_queued_frames_per_client: self.max_queued_frames_per_client,
            client_header: self.client_header,
            trusted_proxies: self.trusted_proxies,
            web: self.web.into_config(),
            protection: self.protection.into(),
        }
    }
}

/// Parse `--session-key` (see [`SessionKey::parse`]); a key shorter than
/// 16 bytes is a start-up error.
pub fn parse_session_key(text: &str) -> Result<SessionKey, String> {
    SessionKey::parse(text).map_err(|e| e.to_string())
}

/// Parse `f32`, `f16`, `bf16` or `auto` ([`Precision::fastest`] on this
/// CPU, [`blapose_model::PrecisionChoice`]).
pub fn parse_precision(text: &str) -> Result<Precision, String> {
    if text.trim().eq_ignore_ascii_case("auto") {
        return Ok(Precision::fastest());
    }
    text.parse().map_err(|_: blapose_model::ModelError| {
        format!("unknown weight precision {text:?} (expected f32, f16, bf16 or auto)")
    })
}

/// Parse `--open-timeout`: a [`parse_duration`] above zero (a zero
/// deadline would refuse every stream).
pub fn parse_open_timeout(text: &str) -> Result<Duration, String> {
    match parse_duration(text)? {
        Duration::ZERO => Err(format!("{text:?}: the timeout must be above zero")),
        d => Ok(d),
    }
}

pub use crate::duration::parse_duration;

#[cfg(test)]
mod tests {
    use super::*;
    use clap::CommandFactory;

    #[test]
    fn durations_parse_with_units() {
        assert_eq!(parse_duration("60s"), Ok(Duration::from_secs(60)));
        assert_eq!(parse_duration("500ms"), Ok(Duration::from_millis(500)));
        assert_eq!(parse_duration("250us"), Ok(Duration::from_micros(250)));
        assert_eq!(parse_duration("1.5s"), Ok(Duration::from_millis(1500)));
        assert_eq!(parse_duration("5m"), Ok(Duration::from_secs(300)));
        assert_eq!(parse_duration("0"), Ok(Duration::ZERO));
        assert!(parse_duration("10").is_err());
        assert!(parse_duration("ten s").is_err());
        assert!(parse_duration("1 fortnight").is_err());
        assert!(parse_duration("-1s").is_err());
    }

    #[test]
    fn cli_defaults_match_config_defaults() {
        let cli = Cli::try_parse_from(["blapose-server"]).expect("no arguments needed");
        assert_eq!(cli.addr, "127.0.0.1:50051".parse().unwrap());
        let cfg = cli.into_config();
        let def = ServerConfig::default();
        assert_eq!(cfg.weight_precision, def.weight_precision);
        assert_eq!(cfg.metrics_addr, Some("127.0.0.1:9090".parse().unwrap()));
        assert_eq!(cfg.max_sessions, def.max_sessions);
        assert_eq!(cfg.session_ttl, def.session_ttl);
        assert_eq!(cfg.max_batch, def.max_batch);
        assert_eq!(cfg.max_mixed_batch, def.max_mixed_batch);
        assert_eq!(cfg.max_queue_delay, def.max_queue_delay);
        assert_eq!(cfg.queue_capacity, def.queue_capacity);
        assert_eq!(cfg.max_inflight_per_stream, def.max_inflight_per_stream);
        assert_eq!(cfg.max_message_bytes, def.max_message_bytes);
        assert_eq!(cfg.shutdown_grace, def.shutdown_grace);
        assert_eq!(cfg.open_timeout, def.open_timeout);
        assert_eq!(cfg.max_concurrent_streams, def.max_concurrent_streams);
        assert_eq!(cfg.max_header_list_bytes, def.max_header_list_bytes);
        assert_eq!(cfg.connection_limits, def.connection_limits);
        assert_eq!(def.open_timeout, Duration::from_secs(10));
        assert_eq!(cfg.weights, WeightsSource::Embedded);
        assert_eq!(
            cfg.lifter,
            Some(WeightsSource::Embedded),
            "the embedded lifter"
        );
        assert_eq!(def.lifter, cfg.lifter);
    }

    #[test]
    fn lifter_weights_flag_sets_the_server_lifter() {
        let cli = Cli::try_parse_from([
            "blapose-server",
            "--lifter-weights",
            "models/lifter_videopose27_causal.safetensors",
        ])
        .unwrap();
        assert_eq!(
            cli.into_config().lifter,
            Some(WeightsSource::File(PathBuf::from(
                "models/lifter_videopose27_causal.safetensors"
            )))
        );
        let cli = Cli::try_parse_from(["blapose-server", "--no-lifter"]).unwrap();
        assert_eq!(cli.into_config().lifter, None);
        assert!(
            Cli::try_parse_from(["blapose-server", "--no-lifter", "--lifter-weights", "f"])
                .is_err()
        );
    }

    #[test]
    fn tls_needs_both_files_and_zero_batch_is_refused() {
        assert!(Cli::try_parse_from(["blapose-server", "--tls-cert", "c.pem"]).is_err());
        assert!(Cli::try_parse_from(["blapose-server", "--max-batch", "0"]).is_err());
        let cli = Cli::try_parse_from([
            "blapose-server",
            "--tls-cert",
            "c.pem",
            "--tls-key",
            "k.pem",
            "--no-metrics",
            "--auth-token",
            "",
        ])
        .unwrap();
        let cfg = cli.into_config();
        assert!(cfg.tls.is_some());
        assert_eq!(cfg.metrics_addr, None);
        assert_eq!(cfg.auth_token, None, "an empty token means no auth");
    }

    #[test]
    fn weight_precision_parses_and_bad_values_are_refused() {
        let cli = Cli::try_parse_from(["blapose-server", "--weight-precision", "f16"]).unwrap();
        assert_eq!(cli.into_config().weight_precision, Precision::F16);
        let Err(err) = Cli::try_parse_from(["blapose-server", "--weight-precision", "f8"]) else {
            panic!("f8 is refused");
        };
        assert!(err.to_string().contains("f32, f16, bf16 or auto"), "{err}");
        let cli = Cli::try_parse_from(["blapose-server", "--weight-precision", "bf16"]).unwrap();
        assert_eq!(cli.into_config().weight_precision, Precision::Bf16);
        let cli = Cli::try_parse_from(["blapose-server", "--weight-precision", "auto"]).unwrap();
        assert_eq!(cli.into_config().weight_precision, Precision::fastest());
        // auto is the default, of the flags and of an embedded server.
        let cli = Cli::try_parse_from(["blapose-server"]).unwrap();
        assert_eq!(cli.into_config().weight_precision, Precision::fastest());
        assert_eq!(
            ServerConfig::default().weight_precision,
            Precision::fastest()
        );
    }

    #[test]
    fn health_check_speaks_tls_exactly_when_the_server_does() {
        let plain = Cli::try_parse_from(["blapose-server", "--health-check"]).unwrap();
        assert_eq!(plain.health_check_tls(), None);
        let tls = Cli::try_parse_from([
            "blapose-server",
            "--health-check",
            "--tls-cert",
            "c.pem",
            "--tls-key",
            "k.pem",
        ])
        .unwrap();
        assert_eq!(
            tls.health_check_tls(),
            Some(HealthCheckTls {
                ca: PathBuf::from("c.pem"),
                domain: "localhost".into()
            }),
            "trusts the server's own certificate, for localhost"
        );
        let tls = Cli::try_parse_from([
            "blapose-server",
            "--health-check",
            "--tls-cert",
            "c.pem",
            "--tls-key",
            "k.pem",
            "--tls-ca",
            "ca.pem",
            "--tls-domain",
            "pose.example.com",
        ])
        .unwrap();
        assert_eq!(
            tls.health_check_tls(),
            Some(HealthCheckTls {
                ca: PathBuf::from("ca.pem"),
                domain: "pose.example.com".into()
            })
        );
    }

    #[test]
    fn open_timeout_parses_and_zero_is_refused() {
        let cli = Cli::try_parse_from(["blapose-server", "--open-timeout", "250ms"]).unwrap();
        assert_eq!(cli.into_config().open_timeout, Duration::from_millis(250));
        assert!(Cli::try_parse_from(["blapose-server", "--open-timeout", "0"]).is_err());
        assert!(Cli::try_parse_from(["blapose-server", "--open-timeout", "0s"]).is_err());
    }

    #[test]
    fn session_key_parses_and_short_keys_are_refused() {
        let cfg = Cli::try_parse_from(["blapose-server"])
            .unwrap()
            .into_config();
        assert_eq!(cfg.session_key, None, "no key, no tokens");
        assert_eq!(cfg.token_every, 100);
        let cli = Cli::try_parse_from([
            "blapose-server",
            "--session-key",
            "hex:000102030405060708090a0b0c0d0e0f",
            "--token-every",
            "0",
        ])
        .unwrap();
        let cfg = cli.into_config();
        assert!(cfg.session_key.is_some());
        assert_eq!(cfg.token_every, 0);
        let Err(err) = Cli::try_parse_from(["blapose-server", "--session-key", "too-short"]) else {
            panic!("a 9-byte key is refused");
        };
        assert!(err.to_string().contains("at least 16"), "{err}");
    }

    #[test]
    fn help_is_consistent() {
        Cli::command().debug_assert();
    }
}

//! blapose-client: a typed async client for the blapose service.
//!
//! The server keeps each person's bone-length estimate in a *session*: a
//! client opens one, streams frames (2D keypoints plus a lifter's 3D pose)
//! and gets every pose back rebuilt with the estimated bone lengths. A
//! server started with a lifter can also lift the poses itself: open the
//! session with [`SessionOptions::server_lifter`] and send keypoints only. A
//! client that knows its camera's calibration ([`CameraCalibration`]) can
//! send it ([`SessionOptions::camera`], [`SequenceInput::camera`], or a
//! replay file's `camera_*` arrays, the optional `camera_height` among
//! them) to be served by the server's camera-aware models. This crate hides the protobuf messages behind types
//! from [`blapose_core`]:
//!
//! ```no_run
//! # async fn demo() -> Result<(), blapose_client::ClientError> {
//! use blapose_client::{Client, ClientConfig, InputFormat, KeypointLayout, Sequence};
//! let client = Client::connect(ClientConfig::new("http://127.0.0.1:50051")).await?;
//! let seq = Sequence::load("examples/cmu_02_02_walk.npz", None)?;
//! let mut session = client
//!     .open_session(InputFormat::pixels(KeypointLayout::H36m17, 1000, 1000), Some("cam0"))
//!     .await?;
//! let answer = session.adjust(&seq.frame(0)).await?;
//! println!("{:?}", answer.bone_lengths);
//! let summary = session.close().await?;
//! # let _ = summary; Ok(()) }
//! ```
//!
//! Modules: [`client`] (connection, unary calls), [`session`] (the
//! bidirectional stream), [`types`] (typed messages), [`sequence`] (replay
//! files), [`replay`](mod@replay) (whole-sequence drivers), [`report`] (before/after
//! metrics), [`html`] (the self-contained HTML report of `--html`).

pub mod client;
pub mod error;
pub mod html;
pub mod replay;
pub mod report;
pub mod sequence;
pub mod session;
pub mod types;

pub use client::{
    new_affinity_key, Client, ClientConfig, OfflineAdjustment, SequenceInput, SessionOptions,
    TlsOptions, AFFINITY_HEADER, DEFAULT_SERVER,
};
pub use error::ClientError;
pub use html::{HtmlError, ReportData};
pub use replay::{adjust_offline, replay, replay_across, replay_session, Adjusted, ReplayOptions};
pub use report::{evaluate, Evaluation, PoseMetrics};
pub use sequence::{Sequence, SequenceError};
pub use session::{EventReceiver, FrameRejection, FrameSender, Session, SessionEvent};
pub use types::{
    AdjustedFrame, CameraCalibration, CameraError, Coordinates, FrameInput, InputFormat,
    KeypointLayout, LiftedPose, LifterDescription, ModelChoice, ModelDescription, ModelInfo,
    SessionInfo, SessionSummary, SessionToken, Sex, Subject, MAX_CAMERA_HEIGHT, MIN_CAMERA_HEIGHT,
};

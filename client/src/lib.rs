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
//! Modules, each importing only those above it in this list: [`error`]
//! (the one error type), [`types`] (typed messages), [`config`] (how to
//! reach a server), [`session`] (the bidirectional stream), [`client`]
//! (connection, unary calls), [`replay`](mod@replay) (whole-sequence
//! drivers); [`sequence`] re-exports the replay-file format
//! (`blapose_data::replay`). Accuracy before and after an adjustment is
//! [`blapose_core::metrics`]' ([`evaluate`], re-exported). The command
//! line and its HTML report are the `blapose-client` binary's, beside the
//! library.

pub mod client;
pub mod config;
pub mod error;
pub mod offline;
pub mod replay;
pub mod sequence;
pub mod session;
pub mod types;

pub use blapose_core::metrics::{evaluate, Evaluation, PoseMetrics};
pub use client::{Client, OfflineAdjustment, Placement, SequenceInput, SessionOptions};
pub use config::{new_affinity_key, ClientConfig, TlsOptions, AFFINITY_HEADER, DEFAULT_SERVER};
pub use error::ClientError;
pub use offline::{adjust_offline, adjust_offline_with_motion};
pub use replay::{replay, replay_across, replay_session, Adjusted, ReplayOptions};
pub use sequence::{Sequence, SequenceError};
pub use session::{EventReceiver, FrameRejection, FrameSender, Session, SessionEvent};
pub use types::{
    AdjustedFrame, CameraCalibration, CameraError, Coordinates, FrameInput, InputFormat,
    KeypointLayout, LiftedPose, LifterDescription, ModelDescription, ModelInfo, ModelKind,
    PlacedRoot, SessionInfo, SessionSummary, SessionToken, Sex, Subject, ToProto,
    MAX_CAMERA_HEIGHT, MIN_CAMERA_HEIGHT,
};

//! blapose-server: BLAPose bone-length adjustment as a streaming gRPC
//! service.
//!
//! Clients open a session per person/camera stream and send, frame by
//! frame, 2D keypoints and the 3D pose their lifting model produced. The
//! server keeps each session's GRU state, batches the frames of all sessions
//! into one GRU step at a time (Triton-style "oldest" sequence batching), and
//! answers each frame with the pose rebuilt from the lifter's bone directions
//! and the session's running bone-length estimate. The contract is
//! `proto/blapose/v1/blapose.proto` (crate `blapose-proto`).
//!
//! Optionally (`--lifter-weights`) the server also runs a trained causal
//! lifter, so a client with only a 2D detector can open a session with
//! `server_lifter` and send keypoints alone: each frame's pose is then lifted
//! from the session's window of recent keypoints (batched across sessions
//! like the GRU step) and adjusted as a client's pose would be. Without the
//! flag nothing about serving changes.
//!
//! Sessions and offline requests that send their camera's calibration
//! (`CameraCalibration`) are served by a second, camera-aware model pair
//! ([`models::Family::CameraAware`]), fed their keypoints as those weights'
//! input contract says (`blapose_model::input`: undistorted, rectified to a
//! level camera at the same place, scaled to the floor), in the same
//! batcher as every other session.
//!
//! A frame's way through the server, one module per stage, in the order
//! the code runs it: [`validate`] (checks and typed errors, on the
//! stream's tokio task) -> [`batch`] (the queue and the "oldest" rule
//! only) -> on the batcher thread ([`pipeline`]): [`prepare`] (missing
//! joints held, the server lifter, the camera the model reads through; it
//! needs the previous frame's outcome, so it runs after the queue) ->
//! [`step`] (the batched GRU step) -> [`answer`] (lengths, adjustment,
//! token snapshots) -> [`motion`] (bone directions smoothed, the root
//! placed, feet held; `AdjustSequence` only so far). The types the stages
//! pass live in [`frame`].
//! [`stream`] drives a streamed frame through them (after [`attach`] has
//! opened, resumed or restored its session), [`offline`] a whole sequence
//! (`AdjustSequence`, which shares prepare and answer).
//!
//! Around them: [`server`] (the wiring: listeners, services, tasks),
//! [`transport`] (accepting within limits, handshakes), [`connection`]
//! (hyper's HTTP/2 per connection, closed when idle, aged or flooding:
//! [`activity`], [`frames`], settings in [`protect`]),
//! [`config`] (flags and [`ServerConfig`]), [`session`] (store, TTL,
//! resume), [`backend`] (the model-execution trait), [`engine`]
//! (blapose-model's fast engines behind it), [`models`] (weights, their
//! input contract, providers), [`service`] (the tonic service), [`state`]
//! (what its handlers share), [`auth`], [`metrics`], [`shutdown`],
//! [`telemetry`], [`health`] (the `--health-check` probe), [`token`]
//! (portable session state: session tokens), [`web`] (the browser
//! transport, `--web-addr`: the same stream handler over a WebSocket, and
//! the live page). Test helpers live in the dev-only blapose-test-support
//! crate, not here.
//!
//! Embedding (tests, load generators): [`spawn`] starts a server on a bound
//! listener and returns a [`ServerHandle`]; [`serve`] runs until a future
//! completes.

// The stages, in the order a frame flows (kept apart by blank lines so
// that rustfmt leaves the order alone).
pub mod validate;

pub mod batch;

pub mod pipeline;

pub mod prepare;

pub mod step;

pub mod answer;

pub mod motion;

// What the stages pass, and who drives frames through them.
pub mod attach;
pub mod frame;
pub mod offline;
pub mod stream;

// Around them.
pub mod activity;
pub mod auth;
pub mod backend;
pub mod budget;
pub mod config;
pub mod connection;
pub mod duration;
pub mod engine;
pub mod error;
#[cfg(test)]
mod fakes;
pub mod frames;
pub mod health;
pub mod metrics;
pub mod models;
pub mod protect;
pub mod quota;
pub mod restore_check;
pub mod server;
pub mod service;
pub mod session;
pub mod shutdown;
pub mod state;
pub mod telemetry;
pub mod token;
pub mod transport;
pub mod web;

pub use blapose_model::input::ModelInput;
pub use config::CameraAwareWeights;
pub use config::{Cli, HealthCheckTls, LogFormat, ServerConfig, WeightsSource};
pub use error::ServerError;
pub use health::probe_health;
pub use models::{
    embedded_bigru, embedded_bigru_rectified, embedded_gru, embedded_gru_rectified, Family,
    LoadedLifter, ModelProvider, WeightsProvider,
};
pub use server::{serve, spawn, spawn_with_provider, ServerHandle};
pub use transport::TlsFiles;
pub use web::WebConfig;

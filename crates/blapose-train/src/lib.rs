//! blapose-train: what reproduces the shipped bone-length weights and their
//! evaluation (the library behind the `blapose` CLI). Research that goes
//! beyond the shipped evaluation (the many-bodies benchmark, its oracles,
//! the eval diagnostics) lives above it, in `blapose-lab`.
//!
//! - [`lengths`], [`ansur`]: what bone lengths synthetic sequences get,
//!   both from the training subjects' [`training_lengths`];
//! - [`ansur_split`]: the held-out ANSUR people training never draws;
//! - [`camera_range`]: the wide camera distribution the camera-aware
//!   models are trained through;
//! - [`stature`]: the stature regression the server answers a known
//!   height with;
//! - [`noise`]: 2D detector-noise models fitted to real detections;
//! - [`synth`], [`loader`]: the augmentation pipeline and batch prefetching;
//! - [`dataset`]: Human3.6M as training and evaluation read it;
//! - [`train`], [`fastnet`]: the bone-length training loop and its
//!   hand-written network; [`run`]: the run directory, schedule and log
//!   every trainer shares; [`adam`]: the optimizer with checkpointable
//!   state;
//! - [`eval`]: the bone-length evaluation protocol and one evaluation run;
//!   [`plot`]: curves; [`cli`]: the flags both command lines share;
//! - [`lifter`]: 2D-to-3D lifters trained on the real detections;
//! - [`eval_adjust`]: lifter accuracy before and after the bone-length
//!   adjustment (the paper's Tables 2 and 3).

// Numeric kernels index several parallel buffers with one loop variable;
// iterator chains would hide the indexing the maths is written in.
#![allow(clippy::needless_range_loop)]

pub mod adam;
pub mod ansur;
pub mod ansur_split;
pub mod camera_range;
pub mod cli;
pub mod dataset;
pub mod error;
pub mod eval;
pub mod eval_adjust;
pub mod fastnet;
pub mod lengths;
pub mod lifter;
pub mod loader;
pub mod motion_eval;
pub mod noise;
pub mod plot;
pub mod run;
pub mod stature;
pub mod synth;
pub mod train;
pub mod training_lengths;

pub use error::TrainError;

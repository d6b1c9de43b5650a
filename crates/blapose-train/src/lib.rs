//! blapose-train: training and evaluation of the BLAPose bone-length models
//! (the library behind the `blapose` CLI).
//!
//! - [`lengths`], [`ansur`]: what bone lengths synthetic sequences get;
//! - [`ansur_split`]: the held-out ANSUR people training never draws;
//! - [`bodies`], [`bench_camera`]: the many-bodies cross-camera benchmark
//!   on those people; [`stature`]: its stature-regression baseline;
//! - [`noise`]: 2D detector-noise models fitted to real detections;
//! - [`synth`], [`loader`]: the augmentation pipeline and batch prefetching;
//! - [`dataset`]: Human3.6M as training and evaluation read it;
//! - [`train`], [`fastnet`]: the bone-length training loop and its
//!   hand-written network; [`run`]: the run directory, schedule and log
//!   every trainer shares; [`adam`]: the optimizer with checkpointable
//!   state;
//! - [`eval`]: the bone-length evaluation protocol; [`plot`]: curves;
//! - [`lifter`]: 2D-to-3D lifters trained on the real detections;
//! - [`eval_adjust`]: lifter accuracy before and after the bone-length
//!   adjustment (the paper's Tables 2 and 3).

// Numeric kernels index several parallel buffers with one loop variable;
// iterator chains would hide the indexing the maths is written in.
#![allow(clippy::needless_range_loop)]

pub mod adam;
pub mod ansur;
pub mod ansur_split;
pub mod bench_camera;
pub mod bodies;
pub mod dataset;
pub mod error;
pub mod eval;
pub mod eval_adjust;
pub mod fastnet;
pub mod height_fusion;
pub mod joint_dropout;
pub mod lengths;
pub mod lifter;
pub mod loader;
pub mod noise;
pub mod plot;
pub mod real_check;
pub mod run;
pub mod stature;
pub mod synth;
pub mod train;

pub use error::TrainError;

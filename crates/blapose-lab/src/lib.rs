//! blapose-lab: the research around the shipped bone-length models, kept
//! apart from what reproduces and evaluates them (`blapose-train`), so the
//! product's code and command line carry only what a user needs, and a
//! study that has measured what it set out to measure can leave in one
//! place (its finding stays in `docs/research.md`).
//!
//! It sits above `blapose-train` (which it reuses, never copies: the
//! evaluation protocol, the evaluation run, the data) and nothing depends
//! on it.
//!
//! - [`bodies`]: the many-bodies cross-camera benchmark (held-out ANSUR II
//!   people on S9/S11 motion through the wide cameras), its baselines and
//!   size oracles; [`real_check`]: its rows on the training subjects' own
//!   detections; [`height_fusion`]: its networks combined with a known
//!   stature; [`models`]: the models these benchmarks score and the
//!   contract each is fed through;
//! - [`diagnose`]: the eval diagnostics (trials joined mid-way, rectified
//!   without the contract, the online state restarted);
//!   [`joint_dropout`]: lost joints; [`stature_proxy`]: statures where
//!   nobody measured one, to score the stature regression on Human3.6M;
//! - [`motion_sweep`]: every candidate motion filter on the training
//!   subjects, from which the served ones were chosen;
//!   [`motion_refiner`]: learned linear refiners of the lifter's
//!   directions; [`root_scale`]: where the root solve's error sits.

// Numeric code indexes several parallel buffers with one loop variable,
// as the training library does.
#![allow(clippy::needless_range_loop)]

pub mod bodies;
pub mod diagnose;
pub mod height_fusion;
pub mod joint_dropout;
pub mod models;
pub mod motion_refiner;
pub mod motion_sweep;
pub mod real_check;
pub mod root_scale;
pub mod stature_proxy;

//! Fast CPU inference for serving: hand-written kernels instead of candle.
//!
//! * [`OnlineGruEngine`]: one batched online step for many sessions.
//! * [`OfflineBiGruEngine`]: the Bi-GRU over a whole sequence.
//!
//! Both are built from [`crate::LoadedWeights`], repack the weights once
//! (`pack`) and run the fused panel kernel (`kernel`) in the best
//! instruction set of the CPU ([`Isa`]). They agree with the reference
//! candle models to 1e-4 (tests in `tests/fast_agreement.rs`).

pub(crate) mod kernel;
pub mod linalg;
pub(crate) mod math;
mod offline;
mod online;
pub(crate) mod pack;

/// The instruction set, shared with blapose-lifters' kernels (see
/// [`blapose_core::isa`] for why it lives there).
pub use blapose_core::isa::{Isa, IsaError};
pub use offline::OfflineBiGruEngine;
pub use online::{OnlineGruEngine, StepScratch};
pub use pack::Precision;

use crate::ModelError;

/// How a fast engine runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct EngineOptions {
    /// Worker threads (1: run on the caller's thread).
    pub threads: usize,
    /// Instruction set; `None` picks the best this CPU supports.
    pub isa: Option<Isa>,
    /// Storage precision of the GRU weights.
    pub precision: Precision,
}

impl Default for EngineOptions {
    fn default() -> Self {
        Self {
            threads: 1,
            isa: None,
            precision: Precision::F32,
        }
    }
}

impl EngineOptions {
    /// Default options with `threads` worker threads.
    pub fn threads(threads: usize) -> Self {
        Self {
            threads,
            ..Self::default()
        }
    }

    fn resolved_isa(&self) -> Result<Isa, ModelError> {
        Ok(self.isa.unwrap_or_else(Isa::detect).require()?)
    }
}

/// A dedicated rayon pool for `threads > 1` (None: run on the caller).
fn build_pool(threads: usize, name: &'static str) -> Result<Option<rayon::ThreadPool>, ModelError> {
    if threads == 0 {
        return Err(ModelError::Config("thread count must be at least 1".into()));
    }
    if threads == 1 {
        return Ok(None);
    }
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .thread_name(move |i| format!("{name}-{i}"))
        .build()
        .map(Some)
        .map_err(|e| ModelError::Config(format!("cannot start {threads} threads: {e}")))
}

/// The first non-finite value of `values` (rows of `width`), as an error.
fn check_finite(values: &[f32], width: usize) -> Result<(), ModelError> {
    match values.iter().position(|v| !v.is_finite()) {
        None => Ok(()),
        Some(i) => Err(ModelError::NonFiniteInput {
            row: i / width,
            col: i % width,
        }),
    }
}

//! Fast CPU inference for serving: hand-written kernels instead of candle.
//!
//! * [`OnlineGruEngine`]: one batched online step for many sessions.
//! * [`OfflineBiGruEngine`]: the Bi-GRU over a whole sequence.
//!
//! Both are built from [`crate::LoadedWeights`], repack the weights once
//! (`pack`) and run the fused panel kernel (`kernel`) in the best
//! instruction set of the CPU ([`Isa`]). They agree with the reference
//! candle models to 1e-4 (tests in `tests/fast_agreement.rs`). With
//! [`Precision::Bf16`] the GRU products run on the CPU's bfloat16 units
//! ([`Bf16Unit`]: AMX tiles where the CPU and OS allow, else AVX512-BF16).
//! Which precision serves fastest on a CPU is [`PrecisionChoice`]'s.

mod choice;
pub(crate) mod kernel;
pub mod linalg;
pub(crate) mod math;
mod offline;
mod online;
pub(crate) mod pack;

/// The instruction set, shared with blapose-lifters' kernels (see
/// [`blapose_core::isa`] for why it lives there).
pub use blapose_core::isa::{Bf16Unit, Isa, IsaError};
pub use choice::{CpuFeatures, PrecisionChoice};
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
    /// With [`Precision::Bf16`]: the bf16 unit; `None` picks AMX where the
    /// CPU has it and the OS grants it, else AVX512-BF16. Ignored for other
    /// precisions.
    pub bf16_unit: Option<Bf16Unit>,
}

impl Default for EngineOptions {
    fn default() -> Self {
        Self {
            threads: 1,
            isa: None,
            precision: Precision::F32,
            bf16_unit: None,
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

    /// The bf16 unit the engine runs on (`None` unless the precision is
    /// bf16), or why bf16 cannot run here.
    fn resolved_bf16(&self, isa: Isa) -> Result<Option<Bf16Unit>, ModelError> {
        if self.precision != Precision::Bf16 {
            return Ok(None);
        }
        if isa != Isa::Avx512 {
            return Err(ModelError::Config(format!(
                "bf16 weights need the avx512 instruction set (asked for {isa})"
            )));
        }
        let missing = |unit: Bf16Unit| {
            unit.missing_feature().map(|f| {
                ModelError::Config(format!(
                    "bf16 weights on {unit} need {f}, which this CPU lacks"
                ))
            })
        };
        if let Some(e) = missing(Bf16Unit::Avx512Bf16) {
            return Err(e);
        }
        match self.bf16_unit {
            Some(Bf16Unit::Avx512Bf16) => Ok(Some(Bf16Unit::Avx512Bf16)),
            Some(Bf16Unit::Amx) => {
                if let Some(e) = missing(Bf16Unit::Amx) {
                    return Err(e);
                }
                amx_permission()
                    .map(|()| Some(Bf16Unit::Amx))
                    .map_err(|e| ModelError::Config(format!("cannot use AMX: {e}")))
            }
            None => Ok(Some(match amx_permission() {
                Ok(()) => Bf16Unit::Amx,
                Err(_) => Bf16Unit::Avx512Bf16,
            })),
        }
    }
}

/// Whether this process may use AMX tiles (asked of the OS once).
fn amx_permission() -> Result<(), String> {
    #[cfg(target_arch = "x86_64")]
    return kernel::amx::permission();
    #[cfg(not(target_arch = "x86_64"))]
    Err("AMX needs x86-64".into())
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

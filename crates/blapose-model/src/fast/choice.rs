//! Which weight precision serves fastest on the CPU at hand
//! (`--weight-precision auto`, the default of the server, `gru-step` and
//! the load test).
//!
//! Every precision but f32 keeps the accuracy bar (mean bone-length error
//! within 0.02 mm of f32 on Human3.6M S9/S11), so the choice is about speed
//! alone, and measured rather than inferred from the instruction set:
//! - **AMX** (Intel Sapphire Rapids and later): bf16 on the AMX tiles. The
//!   unpaced 256-stream load test serves 67,086 frames/s with bf16 against
//!   27,225 with f16 on a Xeon with AMX.
//! - **AVX512-BF16 without AMX** (AMD Zen 4): f16. `vdpbf16ps` alone makes
//!   batches slower than f16's (17-20k against 25-26k frames/s at batch 64).
//! - **Neither**: f16, half f32's weight traffic (the batch-1 step is bound
//!   by it).
//!
//! f32 is only ever what a user asks for. The choice is a pure function of
//! [`CpuFeatures`], so it is tested with the CPU mocked; the reason travels
//! with it into the server's start-up log and `ModelInfo`.

use super::{Bf16Unit, Precision};

/// What the choice reads of the CPU.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct CpuFeatures {
    /// AVX512-BF16 (`vdpbf16ps`), with the AVX-512 it needs.
    pub avx512_bf16: bool,
    /// AMX tiles with bf16, enabled by the OS.
    pub amx: bool,
}

impl CpuFeatures {
    /// This CPU's.
    pub fn detect() -> Self {
        Self {
            avx512_bf16: Bf16Unit::Avx512Bf16.is_available(),
            amx: Bf16Unit::Amx.is_available(),
        }
    }
}

/// A precision and why it was chosen.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PrecisionChoice {
    /// The precision.
    pub precision: Precision,
    /// Why, in a few words (for logs and `ModelInfo`).
    pub reason: &'static str,
}

impl PrecisionChoice {
    /// The fastest precision on a CPU with `cpu`'s features.
    pub fn fastest_on(cpu: CpuFeatures) -> Self {
        let (precision, reason) = if cpu.amx && cpu.avx512_bf16 {
            (
                Precision::Bf16,
                "auto: the CPU has AMX, where bf16 serves about 2.5x the frames of f16",
            )
        } else if cpu.avx512_bf16 {
            (
                Precision::F16,
                "auto: the CPU has AVX512-BF16 but no AMX, where bf16 batches are slower than f16",
            )
        } else {
            (
                Precision::F16,
                "auto: the CPU has no bf16 unit; f16 halves f32's weight traffic",
            )
        };
        Self { precision, reason }
    }

    /// `requested` on a CPU with `cpu`'s features, with why: the automatic
    /// choice's reason when it is that, else that it was asked for.
    pub fn requested(requested: Precision, cpu: CpuFeatures) -> Self {
        let fastest = Self::fastest_on(cpu);
        if requested == fastest.precision {
            fastest
        } else {
            Self {
                precision: requested,
                reason: "requested with --weight-precision (auto would choose otherwise here)",
            }
        }
    }
}

impl Precision {
    /// The fastest precision on this CPU ([`PrecisionChoice::fastest_on`]).
    pub fn fastest() -> Precision {
        PrecisionChoice::fastest_on(CpuFeatures::detect()).precision
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bf16_only_with_amx_f16_elsewhere_f32_never() {
        let cpu = |avx512_bf16, amx| CpuFeatures { avx512_bf16, amx };
        // A Xeon with AMX.
        assert_eq!(
            PrecisionChoice::fastest_on(cpu(true, true)).precision,
            Precision::Bf16
        );
        // AMD Zen 4: AVX512-BF16, no AMX.
        assert_eq!(
            PrecisionChoice::fastest_on(cpu(true, false)).precision,
            Precision::F16
        );
        // No bf16 unit at all (AVX2 machines, or AMX reported without the
        // AVX512-BF16 the engine also needs).
        assert_eq!(
            PrecisionChoice::fastest_on(cpu(false, false)).precision,
            Precision::F16
        );
        assert_eq!(
            PrecisionChoice::fastest_on(cpu(false, true)).precision,
            Precision::F16
        );
        for c in [cpu(true, true), cpu(true, false), cpu(false, false)] {
            let auto = PrecisionChoice::fastest_on(c);
            assert!(auto.reason.starts_with("auto"));
            assert_eq!(PrecisionChoice::requested(auto.precision, c), auto);
            let f32 = PrecisionChoice::requested(Precision::F32, c);
            assert_eq!(f32.precision, Precision::F32);
            assert!(f32.reason.starts_with("requested"));
        }
        assert_eq!(
            Precision::fastest(),
            PrecisionChoice::fastest_on(CpuFeatures::detect()).precision
        );
    }
}

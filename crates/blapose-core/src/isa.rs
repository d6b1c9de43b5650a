//! Which SIMD instruction set a hand-written CPU kernel runs, chosen at run
//! time.
//!
//! One binary must run on any x86-64 (and on other architectures through
//! the scalar path), so kernels are compiled for several targets with
//! `#[target_feature]` and picked after `is_x86_feature_detected!`. The
//! scalar path is always available and is the one the SIMD paths are
//! tested against.
//!
//! Why this lives in blapose-core, which is otherwise geometry: two crates
//! carry such kernels, blapose-model (the fast GRU engines) and
//! blapose-lifters (the lifters' packed products), and neither depends on
//! the other; core is the one crate both stand on. The enum needs no
//! dependency, so core stays as light as it was, whereas making the lifters
//! depend on blapose-model for it would tie them to the bone-length
//! networks (and to gemm, half and rand). Each level's feature set is the
//! union of what the kernels of both crates enable, so a level that
//! [`Isa::is_available`] confirms is safe for every kernel compiled for it.

use std::fmt;
use std::str::FromStr;

/// Why an instruction set cannot be used.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum IsaError {
    /// The CPU lacks a feature the level needs.
    #[error("instruction set {0} is not supported by this CPU")]
    Unavailable(Isa),
    /// A name that is no level.
    #[error("unknown instruction set {0:?}")]
    Unknown(String),
}

/// An instruction-set level of the CPU kernels.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Isa {
    /// Portable Rust, no explicit SIMD.
    Scalar,
    /// x86-64 AVX2 + FMA (+F16C), 8 lanes.
    Avx2,
    /// x86-64 AVX-512F (+AVX2, FMA), 16 lanes.
    Avx512,
}

impl Isa {
    /// Every level, slowest first.
    pub const ALL: [Isa; 3] = [Isa::Scalar, Isa::Avx2, Isa::Avx512];

    /// The best level this CPU supports.
    pub fn detect() -> Isa {
        Isa::ALL
            .into_iter()
            .rev()
            .find(|isa| isa.is_available())
            .unwrap_or(Isa::Scalar)
    }

    /// Whether this CPU can run the level.
    pub fn is_available(self) -> bool {
        match self {
            Isa::Scalar => true,
            #[cfg(target_arch = "x86_64")]
            Isa::Avx2 => {
                std::arch::is_x86_feature_detected!("avx2")
                    && std::arch::is_x86_feature_detected!("fma")
                    && std::arch::is_x86_feature_detected!("f16c")
            }
            #[cfg(target_arch = "x86_64")]
            Isa::Avx512 => {
                std::arch::is_x86_feature_detected!("avx512f")
                    && std::arch::is_x86_feature_detected!("avx2")
                    && std::arch::is_x86_feature_detected!("fma")
            }
            #[cfg(not(target_arch = "x86_64"))]
            _ => false,
        }
    }

    /// `self` if available, else [`IsaError::Unavailable`].
    pub fn require(self) -> Result<Isa, IsaError> {
        if self.is_available() {
            Ok(self)
        } else {
            Err(IsaError::Unavailable(self))
        }
    }

    /// Lower-case name (`scalar`, `avx2`, `avx512`).
    pub const fn as_str(self) -> &'static str {
        match self {
            Isa::Scalar => "scalar",
            Isa::Avx2 => "avx2",
            Isa::Avx512 => "avx512",
        }
    }
}

impl fmt::Display for Isa {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

impl FromStr for Isa {
    type Err = IsaError;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Isa::ALL
            .into_iter()
            .find(|i| i.as_str().eq_ignore_ascii_case(s.trim()))
            .ok_or_else(|| IsaError::Unknown(s.to_string()))
    }
}

/// A bfloat16 dot-product unit a bf16 kernel can run on, on top of
/// [`Isa::Avx512`].
///
/// Kept apart from [`Isa`] because only the bf16 GRU kernels use these
/// units: the levels of [`Isa`] stay what every kernel of both crates is
/// compiled for, and a bf16 path is an extra, opt-in choice within
/// [`Isa::Avx512`]. AMX also needs the operating system's consent per
/// process (on Linux an `arch_prctl` permission request), which the kernel
/// that uses it asks for; [`Bf16Unit::is_available`] only says what the CPU
/// has and whether the OS enabled the tile state at all.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Bf16Unit {
    /// AVX512-BF16's `vdpbf16ps`: 16 f32 lanes, each the sum of two bf16
    /// products, per instruction (twice the multiplies of an f32 FMA).
    Avx512Bf16,
    /// AMX tiles' `tdpbf16ps`: a 16 x 16 f32 tile += 16 x 32 by 32 x 16 bf16
    /// per instruction.
    Amx,
}

impl Bf16Unit {
    /// Every unit, slowest first.
    pub const ALL: [Bf16Unit; 2] = [Bf16Unit::Avx512Bf16, Bf16Unit::Amx];

    /// The first CPU feature (as Linux's `/proc/cpuinfo` names it) that this
    /// unit needs and the CPU (or the OS) lacks; `None` when it has all.
    pub fn missing_feature(self) -> Option<&'static str> {
        #[cfg(target_arch = "x86_64")]
        {
            if !Isa::Avx512.is_available() {
                return Some("avx512f");
            }
            if !std::arch::is_x86_feature_detected!("avx512bw") {
                return Some("avx512bw");
            }
            if !std::arch::is_x86_feature_detected!("avx512bf16") {
                return Some("avx512_bf16");
            }
            match self {
                Bf16Unit::Avx512Bf16 => None,
                Bf16Unit::Amx => amx_missing_feature(),
            }
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            let _ = self;
            Some("x86_64")
        }
    }

    /// Whether the CPU has the unit (for AMX: and the OS enabled the tile
    /// state; the per-process permission is asked for separately).
    pub fn is_available(self) -> bool {
        self.missing_feature().is_none()
    }

    /// The best unit this CPU has, if any.
    pub fn detect() -> Option<Bf16Unit> {
        Bf16Unit::ALL.into_iter().rev().find(|u| u.is_available())
    }

    /// Lower-case name (`avx512bf16`, `amx`).
    pub const fn as_str(self) -> &'static str {
        match self {
            Bf16Unit::Avx512Bf16 => "avx512bf16",
            Bf16Unit::Amx => "amx",
        }
    }
}

impl fmt::Display for Bf16Unit {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

impl FromStr for Bf16Unit {
    type Err = IsaError;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Bf16Unit::ALL
            .into_iter()
            .find(|u| u.as_str().eq_ignore_ascii_case(s.trim()))
            .ok_or_else(|| IsaError::Unknown(s.to_string()))
    }
}

/// AMX-TILE and AMX-BF16 from CPUID leaf 7, and the tile state (XCR0 bits
/// 17 and 18) enabled by the OS. `is_x86_feature_detected!("amx-bf16")` is
/// not stable in Rust, hence CPUID by hand.
#[cfg(target_arch = "x86_64")]
fn amx_missing_feature() -> Option<&'static str> {
    use std::arch::x86_64::{__cpuid, __cpuid_count, _xgetbv};
    let leaf7 = __cpuid_count(7, 0);
    if leaf7.edx & (1 << 24) == 0 {
        return Some("amx_tile");
    }
    if leaf7.edx & (1 << 22) == 0 {
        return Some("amx_bf16");
    }
    // OSXSAVE (CPUID.1:ECX bit 27): XGETBV may be executed.
    if __cpuid(1).ecx & (1 << 27) == 0 {
        return Some("osxsave");
    }
    #[target_feature(enable = "xsave")]
    fn xcr0() -> u64 {
        // SAFETY: OSXSAVE was checked by the caller, so XGETBV is enabled.
        unsafe { _xgetbv(0) }
    }
    // SAFETY: the xsave feature is implied by OSXSAVE, checked above.
    let xcr0 = unsafe { xcr0() };
    if xcr0 & (0b11 << 17) != 0b11 << 17 {
        return Some("amx tile state (XCR0) not enabled by the OS");
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_round_trip_and_detect_is_available() {
        for isa in Isa::ALL {
            assert_eq!(isa.as_str().parse::<Isa>(), Ok(isa));
            assert_eq!(isa.to_string().to_uppercase().parse::<Isa>(), Ok(isa));
        }
        assert_eq!("neon".parse::<Isa>(), Err(IsaError::Unknown("neon".into())));
        assert!(Isa::Scalar.is_available());
        assert_eq!(Isa::detect().require(), Ok(Isa::detect()));
        for isa in Isa::ALL.into_iter().filter(|i| !i.is_available()) {
            assert_eq!(isa.require(), Err(IsaError::Unavailable(isa)));
        }
    }

    #[test]
    fn bf16_unit_names_round_trip_and_amx_implies_avx512_bf16() {
        for unit in Bf16Unit::ALL {
            assert_eq!(unit.as_str().parse::<Bf16Unit>(), Ok(unit));
        }
        assert!("avx2".parse::<Bf16Unit>().is_err());
        if Bf16Unit::Amx.is_available() {
            assert!(Bf16Unit::Avx512Bf16.is_available());
        }
        if let Some(unit) = Bf16Unit::detect() {
            assert!(unit.is_available());
        }
        eprintln!(
            "bf16 units: avx512bf16 missing {:?}, amx missing {:?}",
            Bf16Unit::Avx512Bf16.missing_feature(),
            Bf16Unit::Amx.missing_feature()
        );
    }
}

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
}

//! Vectorized `exp`, `sigmoid` and `tanh` for the kernels' epilogues.
//!
//! The gate non-linearities are evaluated once per hidden unit per frame,
//! where libm calls would cost more than the surrounding SIMD work. `exp`
//! uses the classic reduction `x = k·ln2 + r`, |r| <= ln2/2, a degree-6
//! Taylor polynomial for `e^r` (truncation error below 2e-7 relative) and an
//! exponent shift for `2^k`. Inputs are clamped to ±87 so results stay
//! normal; `sigmoid` saturates correctly there. `tanh(x) = 2σ(2x) − 1`
//! (absolute error ~1e-7, far inside the 1e-4 agreement budget). The
//! scalar versions use libm and serve as the portable path and the oracle.

/// Scalar reference versions.
pub(crate) mod scalar {
    /// Logistic function.
    #[inline]
    pub fn sigmoid(x: f32) -> f32 {
        1.0 / (1.0 + (-x).exp())
    }

    /// Hyperbolic tangent.
    #[inline]
    pub fn tanh(x: f32) -> f32 {
        x.tanh()
    }
}

const CLAMP: f32 = 87.0;
const LOG2E: f32 = std::f32::consts::LOG2_E;
// ln 2 split in a part exact in f32 and the remainder (Cody–Waite reduction).
const LN2_HI: f32 = 0.693_359_4;
const LN2_LO: f32 = -2.121_944_4e-4;
const C2: f32 = 1.0 / 2.0;
const C3: f32 = 1.0 / 6.0;
const C4: f32 = 1.0 / 24.0;
const C5: f32 = 1.0 / 120.0;
const C6: f32 = 1.0 / 720.0;

/// 8-lane AVX2 + FMA versions.
#[cfg(target_arch = "x86_64")]
pub(crate) mod avx2 {
    use super::*;
    use std::arch::x86_64::*;

    /// `e^x` per lane.
    #[inline]
    #[target_feature(enable = "avx2,fma")]
    pub fn exp(x: __m256) -> __m256 {
        let x = _mm256_min_ps(
            _mm256_max_ps(x, _mm256_set1_ps(-CLAMP)),
            _mm256_set1_ps(CLAMP),
        );
        let k = _mm256_round_ps::<{ _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC }>(
            _mm256_mul_ps(x, _mm256_set1_ps(LOG2E)),
        );
        let r = _mm256_fnmadd_ps(k, _mm256_set1_ps(LN2_HI), x);
        let r = _mm256_fnmadd_ps(k, _mm256_set1_ps(LN2_LO), r);
        let mut p = _mm256_set1_ps(C6);
        p = _mm256_fmadd_ps(p, r, _mm256_set1_ps(C5));
        p = _mm256_fmadd_ps(p, r, _mm256_set1_ps(C4));
        p = _mm256_fmadd_ps(p, r, _mm256_set1_ps(C3));
        p = _mm256_fmadd_ps(p, r, _mm256_set1_ps(C2));
        p = _mm256_fmadd_ps(p, r, _mm256_set1_ps(1.0));
        p = _mm256_fmadd_ps(p, r, _mm256_set1_ps(1.0));
        let bits = _mm256_slli_epi32::<23>(_mm256_add_epi32(
            _mm256_cvtps_epi32(k),
            _mm256_set1_epi32(127),
        ));
        _mm256_mul_ps(p, _mm256_castsi256_ps(bits))
    }

    /// Logistic function per lane.
    #[inline]
    #[target_feature(enable = "avx2,fma")]
    pub fn sigmoid(x: __m256) -> __m256 {
        let one = _mm256_set1_ps(1.0);
        let e = exp(_mm256_sub_ps(_mm256_setzero_ps(), x));
        _mm256_div_ps(one, _mm256_add_ps(one, e))
    }

    /// Hyperbolic tangent per lane.
    #[inline]
    #[target_feature(enable = "avx2,fma")]
    pub fn tanh(x: __m256) -> __m256 {
        let two = _mm256_set1_ps(2.0);
        _mm256_fmsub_ps(two, sigmoid(_mm256_mul_ps(two, x)), _mm256_set1_ps(1.0))
    }
}

/// 16-lane AVX-512F versions.
#[cfg(target_arch = "x86_64")]
pub(crate) mod avx512 {
    use super::*;
    use std::arch::x86_64::*;

    /// `e^x` per lane.
    #[inline]
    #[target_feature(enable = "avx512f")]
    pub fn exp(x: __m512) -> __m512 {
        let x = _mm512_min_ps(
            _mm512_max_ps(x, _mm512_set1_ps(-CLAMP)),
            _mm512_set1_ps(CLAMP),
        );
        let k = _mm512_roundscale_ps::<{ _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC }>(
            _mm512_mul_ps(x, _mm512_set1_ps(LOG2E)),
        );
        let r = _mm512_fnmadd_ps(k, _mm512_set1_ps(LN2_HI), x);
        let r = _mm512_fnmadd_ps(k, _mm512_set1_ps(LN2_LO), r);
        let mut p = _mm512_set1_ps(C6);
        p = _mm512_fmadd_ps(p, r, _mm512_set1_ps(C5));
        p = _mm512_fmadd_ps(p, r, _mm512_set1_ps(C4));
        p = _mm512_fmadd_ps(p, r, _mm512_set1_ps(C3));
        p = _mm512_fmadd_ps(p, r, _mm512_set1_ps(C2));
        p = _mm512_fmadd_ps(p, r, _mm512_set1_ps(1.0));
        p = _mm512_fmadd_ps(p, r, _mm512_set1_ps(1.0));
        _mm512_scalef_ps(p, k)
    }

    /// Logistic function per lane.
    #[inline]
    #[target_feature(enable = "avx512f")]
    pub fn sigmoid(x: __m512) -> __m512 {
        let one = _mm512_set1_ps(1.0);
        let e = exp(_mm512_sub_ps(_mm512_setzero_ps(), x));
        _mm512_div_ps(one, _mm512_add_ps(one, e))
    }

    /// Hyperbolic tangent per lane.
    #[inline]
    #[target_feature(enable = "avx512f")]
    pub fn tanh(x: __m512) -> __m512 {
        let two = _mm512_set1_ps(2.0);
        _mm512_fmsub_ps(two, sigmoid(_mm512_mul_ps(two, x)), _mm512_set1_ps(1.0))
    }
}

#[cfg(all(test, target_arch = "x86_64"))]
mod tests {
    use super::*;
    use crate::fast::Isa;
    use std::arch::x86_64::*;

    fn grid() -> Vec<f32> {
        (-4000..=4000)
            .map(|i| i as f32 * 0.01)
            .chain([-200.0, -90.0, 90.0, 300.0])
            .collect()
    }

    #[test]
    fn avx2_matches_libm() {
        if !Isa::Avx2.is_available() {
            eprintln!("skipping: no AVX2");
            return;
        }
        for chunk in grid().chunks_exact(8) {
            let mut s = [0f32; 8];
            let mut t = [0f32; 8];
            // SAFETY: AVX2/FMA availability checked above; arrays hold 8 floats.
            unsafe {
                let v = _mm256_loadu_ps(chunk.as_ptr());
                _mm256_storeu_ps(s.as_mut_ptr(), avx2::sigmoid(v));
                _mm256_storeu_ps(t.as_mut_ptr(), avx2::tanh(v));
            }
            for i in 0..8 {
                assert!(
                    (s[i] - scalar::sigmoid(chunk[i])).abs() < 3e-7,
                    "{}",
                    chunk[i]
                );
                assert!((t[i] - scalar::tanh(chunk[i])).abs() < 6e-7, "{}", chunk[i]);
            }
        }
    }

    #[test]
    fn avx512_matches_libm() {
        if !Isa::Avx512.is_available() {
            eprintln!("skipping: no AVX-512");
            return;
        }
        for chunk in grid().chunks_exact(16) {
            let mut s = [0f32; 16];
            let mut t = [0f32; 16];
            let mut e = [0f32; 16];
            // SAFETY: AVX-512F availability checked above; arrays hold 16 floats.
            unsafe {
                let v = _mm512_loadu_ps(chunk.as_ptr());
                _mm512_storeu_ps(s.as_mut_ptr(), avx512::sigmoid(v));
                _mm512_storeu_ps(t.as_mut_ptr(), avx512::tanh(v));
                _mm512_storeu_ps(e.as_mut_ptr(), avx512::exp(v));
            }
            for i in 0..16 {
                let x = chunk[i];
                assert!((s[i] - scalar::sigmoid(x)).abs() < 3e-7, "{x}");
                assert!((t[i] - scalar::tanh(x)).abs() < 6e-7, "{x}");
                if x.abs() < 80.0 {
                    assert!((e[i] / x.exp() - 1.0).abs() < 5e-7, "{x}");
                }
            }
        }
    }
}

//! AVX2 + FMA version of the panel kernel: a panel's 16 units are two `ymm`
//! per gate, so a row needs six accumulators; with 16 registers a tile holds
//! at most two rows, and a single row unrolls `k` twice to hide latency.
//! As in the AVX-512 kernel, accumulators are separate variables (an array
//! indexed in loops was kept in memory by LLVM).

use std::arch::x86_64::*;

use super::TileArgs;
use crate::fast::math::avx2::{sigmoid, tanh};
use crate::fast::pack::{LANES, ROW};
use crate::{HIDDEN, OUTPUT_DIM};

/// Kernel for `rows <= 2` rows.
///
/// # Safety
/// See the [`TileArgs`] contract; AVX2 and FMA must be available.
pub(crate) unsafe fn tile(rows: usize, a: &TileArgs) {
    match (rows, a.half) {
        (1, false) => tile1(a),
        (2, false) => tile2(a),
        (1, true) => tile1_h(a),
        (2, true) => tile2_h(a),
        _ => unreachable!("tile of {rows} rows"),
    }
}

/// 8 f32 weights.
macro_rules! ld_f32 {
    ($p:expr) => {
        _mm256_load_ps($p)
    };
}

/// 8 f16 weights, widened to f32.
macro_rules! ld_f16 {
    ($p:expr) => {
        _mm256_cvtph_ps(_mm_load_si128($p as *const __m128i))
    };
}

/// Accumulate `len` values of `k` into the named per-"slot" accumulators;
/// each slot is `(r_lo, r_hi, z_lo, z_hi, n_lo, n_hi, x offset, w offset)`.
/// `x` advances by `$xstep` and `w` by `$wstep` rows per iteration.
macro_rules! accumulate {
    ($ld:ident, $w:ident, $x:ident, $len:expr, $xstep:expr, $wstep:expr,
     $(($rl:ident, $rh:ident, $zl:ident, $zh:ident, $nl:ident, $nh:ident, $xo:expr, $wo:expr)),+) => {
        for _ in 0..$len {
            $(
                let xv = _mm256_set1_ps(*$x.add($xo));
                let wp = $w.add($wo * ROW);
                $rl = _mm256_fmadd_ps($ld!(wp), xv, $rl);
                $rh = _mm256_fmadd_ps($ld!(wp.add(8)), xv, $rh);
                $zl = _mm256_fmadd_ps($ld!(wp.add(LANES)), xv, $zl);
                $zh = _mm256_fmadd_ps($ld!(wp.add(LANES + 8)), xv, $zh);
                $nl = _mm256_fmadd_ps($ld!(wp.add(2 * LANES)), xv, $nl);
                $nh = _mm256_fmadd_ps($ld!(wp.add(2 * LANES + 8)), xv, $nh);
            )+
            $w = $w.add($wstep * ROW);
            $x = $x.add($xstep);
        }
    };
}

/// Two rows, one `k` per iteration.
macro_rules! tile2_fn {
    ($name:ident, $ld:ident, $ty:ty) => {
        #[target_feature(enable = "avx2,fma,f16c")]
        unsafe fn $name(a: &TileArgs) {
            let zero = _mm256_setzero_ps();
            let (mut ar0, mut br0, mut az0, mut bz0, mut an0, mut bn0) =
                (zero, zero, zero, zero, zero, zero);
            let (mut ar1, mut br1, mut az1, mut bz1, mut an1, mut bn1) =
                (zero, zero, zero, zero, zero, zero);
            let mut w = a.w as *const $ty;
            let mut x = a.x;
            accumulate!(
                $ld,
                w,
                x,
                a.k_in,
                2,
                1,
                (ar0, br0, az0, bz0, an0, bn0, 0, 0),
                (ar1, br1, az1, bz1, an1, bn1, 1, 0)
            );
            let ni = [[an0, bn0], [an1, bn1]];
            (an0, bn0, an1, bn1) = (zero, zero, zero, zero);
            accumulate!(
                $ld,
                w,
                x,
                HIDDEN,
                2,
                1,
                (ar0, br0, az0, bz0, an0, bn0, 0, 0),
                (ar1, br1, az1, bz1, an1, bn1, 1, 0)
            );
            let acc = [
                [[ar0, br0], [az0, bz0], [an0, bn0]],
                [[ar1, br1], [az1, bz1], [an1, bn1]],
            ];
            epilogue(a, &acc, &ni);
        }
    };
}

/// One row, `k` unrolled twice (12 independent accumulators).
macro_rules! tile1_fn {
    ($name:ident, $ld:ident, $ty:ty) => {
        #[target_feature(enable = "avx2,fma,f16c")]
        unsafe fn $name(a: &TileArgs) {
            let zero = _mm256_setzero_ps();
            let (mut ar0, mut br0, mut az0, mut bz0, mut an0, mut bn0) =
                (zero, zero, zero, zero, zero, zero);
            let (mut ar1, mut br1, mut az1, mut bz1, mut an1, mut bn1) =
                (zero, zero, zero, zero, zero, zero);
            let mut w = a.w as *const $ty;
            let mut x = a.x;
            // k_in and HIDDEN are even
            accumulate!(
                $ld,
                w,
                x,
                a.k_in / 2,
                2,
                2,
                (ar0, br0, az0, bz0, an0, bn0, 0, 0),
                (ar1, br1, az1, bz1, an1, bn1, 1, 1)
            );
            let ni = [[_mm256_add_ps(an0, an1), _mm256_add_ps(bn0, bn1)]];
            (an0, bn0, an1, bn1) = (zero, zero, zero, zero);
            accumulate!(
                $ld,
                w,
                x,
                HIDDEN / 2,
                2,
                2,
                (ar0, br0, az0, bz0, an0, bn0, 0, 0),
                (ar1, br1, az1, bz1, an1, bn1, 1, 1)
            );
            let acc = [[
                [_mm256_add_ps(ar0, ar1), _mm256_add_ps(br0, br1)],
                [_mm256_add_ps(az0, az1), _mm256_add_ps(bz0, bz1)],
                [_mm256_add_ps(an0, an1), _mm256_add_ps(bn0, bn1)],
            ]];
            epilogue(a, &acc, &ni);
        }
    };
}

tile2_fn!(tile2, ld_f32, f32);
tile2_fn!(tile2_h, ld_f16, u16);
tile1_fn!(tile1, ld_f32, f32);
tile1_fn!(tile1_h, ld_f16, u16);

/// Gates -> new states (and output contributions) for each row:
/// `acc[b][gate][half]` pre-activations without biases (`gate` 2 is the
/// recurrent part of `n`), `ni[b][half]` the input part of `n`.
#[inline]
#[target_feature(enable = "avx2,fma,f16c")]
unsafe fn epilogue<const BT: usize>(
    a: &TileArgs,
    acc: &[[[__m256; 2]; 3]; BT],
    ni: &[[__m256; 2]; BT],
) {
    for b in 0..BT {
        let mut h_new = [_mm256_setzero_ps(); 2];
        for half in 0..2 {
            let g = [acc[b][0][half], acc[b][1][half], acc[b][2][half]];
            let lane = |gate: usize| gate * LANES + half * 8;
            let mut pr = _mm256_add_ps(g[0], _mm256_loadu_ps(a.bias.add(lane(0))));
            let mut pz = _mm256_add_ps(g[1], _mm256_loadu_ps(a.bias.add(lane(1))));
            let mut pn = _mm256_add_ps(ni[b][half], _mm256_loadu_ps(a.bias.add(lane(2))));
            let nh = _mm256_add_ps(g[2], _mm256_loadu_ps(a.bias.add(lane(3))));
            if !a.pre.is_null() {
                let pre = a.pre.add(b * a.pre_stride + a.unit0 + half * 8);
                pr = _mm256_add_ps(pr, _mm256_loadu_ps(pre));
                pz = _mm256_add_ps(pz, _mm256_loadu_ps(pre.add(HIDDEN)));
                pn = _mm256_add_ps(pn, _mm256_loadu_ps(pre.add(2 * HIDDEN)));
            }
            let r = sigmoid(pr);
            let z = sigmoid(pz);
            let n = tanh(_mm256_fmadd_ps(r, nh, pn));
            let h_old = _mm256_loadu_ps(a.h.add(b * a.h_stride + a.unit0 + half * 8));
            h_new[half] = _mm256_fmadd_ps(z, _mm256_sub_ps(h_old, n), n);
            _mm256_storeu_ps(a.out.add(b * a.out_stride + half * 8), h_new[half]);
            if !a.save.is_null() {
                let s = a.save.add(b * a.save_stride + a.unit0 + half * 8);
                _mm256_storeu_ps(s, r);
                _mm256_storeu_ps(s.add(HIDDEN), z);
                _mm256_storeu_ps(s.add(2 * HIDDEN), n);
                _mm256_storeu_ps(s.add(3 * HIDDEN), nh);
            }
        }
        if !a.fc.is_null() {
            let mut s = [0.0f32; LANES];
            _mm256_storeu_ps(s.as_mut_ptr(), sigmoid(h_new[0]));
            _mm256_storeu_ps(s.as_mut_ptr().add(8), sigmoid(h_new[1]));
            let y = a.y.add(b * a.y_stride);
            let mut y0 = _mm256_loadu_ps(y);
            let mut y1 = _mm256_loadu_ps(y.add(8));
            for (u, &su) in s.iter().enumerate() {
                let sv = _mm256_set1_ps(su);
                let row = a.fc.add(u * OUTPUT_DIM);
                y0 = _mm256_fmadd_ps(sv, _mm256_load_ps(row), y0);
                y1 = _mm256_fmadd_ps(sv, _mm256_load_ps(row.add(8)), y1);
            }
            _mm256_storeu_ps(y, y0);
            _mm256_storeu_ps(y.add(8), y1);
        }
    }
}

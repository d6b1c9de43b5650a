//! AVX-512 version of the panel kernel: a panel's 16 units are one `zmm`
//! per gate. For each input index `k` the three gate vectors are loaded
//! once and multiplied into every row of the tile (up to 8 rows, 24
//! accumulators). A single row unrolls `k` four ways into independent
//! accumulators so the FMA latency does not serialize the loop.
//!
//! The accumulators are spelled out as separate variables by a macro:
//! written as an array indexed in loops, LLVM kept the array in memory and
//! stored every accumulator back after every FMA (4x slower).

use std::arch::x86_64::*;

use super::TileArgs;
use crate::fast::math::avx512::{sigmoid, tanh};
use crate::fast::pack::{LANES, ROW};
use crate::{HIDDEN, OUTPUT_DIM};

/// Kernel for `rows <= 8` rows.
///
/// # Safety
/// See the [`TileArgs`] contract; AVX-512F must be available.
pub(crate) unsafe fn tile(rows: usize, a: &TileArgs) {
    match (rows, a.half) {
        (1, false) => tile1(a),
        (2, false) => tile2(a),
        (3, false) => tile3(a),
        (4, false) => tile4(a),
        (5, false) => tile5(a),
        (6, false) => tile6(a),
        (7, false) => tile7(a),
        (8, false) => tile8(a),
        (1, true) => tile1_h(a),
        (2, true) => tile2_h(a),
        (3, true) => tile3_h(a),
        (4, true) => tile4_h(a),
        (5, true) => tile5_h(a),
        (6, true) => tile6_h(a),
        (7, true) => tile7_h(a),
        (8, true) => tile8_h(a),
        _ => unreachable!("tile of {rows} rows"),
    }
}

/// 16 f32 weights.
macro_rules! ld_f32 {
    ($p:expr) => {
        _mm512_load_ps($p)
    };
}

/// 16 f16 weights, widened to f32.
macro_rules! ld_f16 {
    ($p:expr) => {
        _mm512_cvtph_ps(_mm256_load_si256($p as *const __m256i))
    };
}

/// A kernel for a fixed number of rows; each `(r, z, n, offset)` names one
/// row's accumulators and its offset in the packed `[k][row]` inputs.
macro_rules! tile_fn {
    ($name:ident, $ld:ident, $ty:ty, $rows:expr, $(($r:ident, $z:ident, $n:ident, $b:expr)),+) => {
        #[target_feature(enable = "avx512f,avx2,fma")]
        unsafe fn $name(a: &TileArgs) {
            let zero = _mm512_setzero_ps();
            $(let mut $r = zero; let mut $z = zero; let mut $n = zero;)+
            let mut w = a.w as *const $ty;
            let mut x = a.x;
            for _ in 0..a.k_in {
                let wr = $ld!(w);
                let wz = $ld!(w.add(LANES));
                let wn = $ld!(w.add(2 * LANES));
                $(
                    let xv = _mm512_set1_ps(*x.add($b));
                    $r = _mm512_fmadd_ps(wr, xv, $r);
                    $z = _mm512_fmadd_ps(wz, xv, $z);
                    $n = _mm512_fmadd_ps(wn, xv, $n);
                )+
                w = w.add(ROW);
                x = x.add($rows);
            }
            let ni = [$($n),+];
            $($n = zero;)+
            for _ in 0..HIDDEN {
                let wr = $ld!(w);
                let wz = $ld!(w.add(LANES));
                let wn = $ld!(w.add(2 * LANES));
                $(
                    let xv = _mm512_set1_ps(*x.add($b));
                    $r = _mm512_fmadd_ps(wr, xv, $r);
                    $z = _mm512_fmadd_ps(wz, xv, $z);
                    $n = _mm512_fmadd_ps(wn, xv, $n);
                )+
                w = w.add(ROW);
                x = x.add($rows);
            }
            epilogue(a, &[$([$r, $z, $n]),+], &ni);
        }
    };
}

/// The f32 and f16 kernels for one tile size.
macro_rules! tile_fns {
    ($f32:ident, $f16:ident, $rows:expr, $(($r:ident, $z:ident, $n:ident, $b:expr)),+) => {
        tile_fn!($f32, ld_f32, f32, $rows, $(($r, $z, $n, $b)),+);
        tile_fn!($f16, ld_f16, u16, $rows, $(($r, $z, $n, $b)),+);
    };
}

tile_fns!(tile2, tile2_h, 2, (r0, z0, n0, 0), (r1, z1, n1, 1));
tile_fns!(
    tile3,
    tile3_h,
    3,
    (r0, z0, n0, 0),
    (r1, z1, n1, 1),
    (r2, z2, n2, 2)
);
tile_fns!(
    tile4,
    tile4_h,
    4,
    (r0, z0, n0, 0),
    (r1, z1, n1, 1),
    (r2, z2, n2, 2),
    (r3, z3, n3, 3)
);
tile_fns!(
    tile5,
    tile5_h,
    5,
    (r0, z0, n0, 0),
    (r1, z1, n1, 1),
    (r2, z2, n2, 2),
    (r3, z3, n3, 3),
    (r4, z4, n4, 4)
);
tile_fns!(
    tile6,
    tile6_h,
    6,
    (r0, z0, n0, 0),
    (r1, z1, n1, 1),
    (r2, z2, n2, 2),
    (r3, z3, n3, 3),
    (r4, z4, n4, 4),
    (r5, z5, n5, 5)
);
tile_fns!(
    tile7,
    tile7_h,
    7,
    (r0, z0, n0, 0),
    (r1, z1, n1, 1),
    (r2, z2, n2, 2),
    (r3, z3, n3, 3),
    (r4, z4, n4, 4),
    (r5, z5, n5, 5),
    (r6, z6, n6, 6)
);
tile_fns!(
    tile8,
    tile8_h,
    8,
    (r0, z0, n0, 0),
    (r1, z1, n1, 1),
    (r2, z2, n2, 2),
    (r3, z3, n3, 3),
    (r4, z4, n4, 4),
    (r5, z5, n5, 5),
    (r6, z6, n6, 6),
    (r7, z7, n7, 7)
);

/// One row, `k` unrolled four ways (12 independent accumulators).
macro_rules! tile1_fn {
    ($name:ident, $ld:ident, $ty:ty) => {
        #[target_feature(enable = "avx512f,avx2,fma")]
        unsafe fn $name(a: &TileArgs) {
            let zero = _mm512_setzero_ps();
            let mut acc = [[zero; 3]; 4];
            let mut w = a.w as *const $ty;
            let mut x = a.x;
            let mut ni = zero;
            for (phase, len) in [a.k_in, HIDDEN].into_iter().enumerate() {
                let (mut r0, mut z0, mut n0) = (acc[0][0], acc[0][1], acc[0][2]);
                let (mut r1, mut z1, mut n1) = (acc[1][0], acc[1][1], acc[1][2]);
                let (mut r2, mut z2, mut n2) = (acc[2][0], acc[2][1], acc[2][2]);
                let (mut r3, mut z3, mut n3) = (acc[3][0], acc[3][1], acc[3][2]);
                macro_rules! k_step {
                    ($r:ident, $z:ident, $n:ident, $u:expr) => {
                        let xv = _mm512_set1_ps(*x.add($u));
                        let wu = w.add($u * ROW);
                        $r = _mm512_fmadd_ps($ld!(wu), xv, $r);
                        $z = _mm512_fmadd_ps($ld!(wu.add(LANES)), xv, $z);
                        $n = _mm512_fmadd_ps($ld!(wu.add(2 * LANES)), xv, $n);
                    };
                }
                // k_in and HIDDEN are multiples of 4
                for _ in 0..len / 4 {
                    k_step!(r0, z0, n0, 0);
                    k_step!(r1, z1, n1, 1);
                    k_step!(r2, z2, n2, 2);
                    k_step!(r3, z3, n3, 3);
                    w = w.add(4 * ROW);
                    x = x.add(4);
                }
                acc = [[r0, z0, n0], [r1, z1, n1], [r2, z2, n2], [r3, z3, n3]];
                if phase == 0 {
                    for part in &mut acc {
                        ni = _mm512_add_ps(ni, part[2]);
                        part[2] = zero;
                    }
                }
            }
            let mut g = acc[0];
            for part in &acc[1..] {
                for (gi, pi) in g.iter_mut().zip(part) {
                    *gi = _mm512_add_ps(*gi, *pi);
                }
            }
            epilogue(a, &[g], &[ni]);
        }
    };
}

tile1_fn!(tile1, ld_f32, f32);
tile1_fn!(tile1_h, ld_f16, u16);

/// Gates -> new states (and output contributions) for each row of a tile:
/// `acc[b] = [r, z, n_h]` pre-activations without biases, `ni[b]` the
/// input part of `n`.
#[inline]
#[target_feature(enable = "avx512f,avx2,fma")]
pub(crate) unsafe fn epilogue<const BT: usize>(
    a: &TileArgs,
    acc: &[[__m512; 3]; BT],
    ni: &[__m512; BT],
) {
    let b_r = _mm512_loadu_ps(a.bias);
    let b_z = _mm512_loadu_ps(a.bias.add(LANES));
    let b_ni = _mm512_loadu_ps(a.bias.add(2 * LANES));
    let b_nh = _mm512_loadu_ps(a.bias.add(3 * LANES));
    for b in 0..BT {
        let g = acc[b];
        let mut pr = _mm512_add_ps(g[0], b_r);
        let mut pz = _mm512_add_ps(g[1], b_z);
        let mut pn = _mm512_add_ps(ni[b], b_ni);
        if !a.pre.is_null() {
            let pre = a.pre.add(b * a.pre_stride + a.unit0);
            pr = _mm512_add_ps(pr, _mm512_loadu_ps(pre));
            pz = _mm512_add_ps(pz, _mm512_loadu_ps(pre.add(HIDDEN)));
            pn = _mm512_add_ps(pn, _mm512_loadu_ps(pre.add(2 * HIDDEN)));
        }
        let r = sigmoid(pr);
        let z = sigmoid(pz);
        let nh = _mm512_add_ps(g[2], b_nh);
        let n = tanh(_mm512_fmadd_ps(r, nh, pn));
        let h_old = _mm512_loadu_ps(a.h.add(b * a.h_stride + a.unit0));
        let h_new = _mm512_fmadd_ps(z, _mm512_sub_ps(h_old, n), n);
        _mm512_storeu_ps(a.out.add(b * a.out_stride), h_new);
        if !a.save.is_null() {
            let s = a.save.add(b * a.save_stride + a.unit0);
            _mm512_storeu_ps(s, r);
            _mm512_storeu_ps(s.add(HIDDEN), z);
            _mm512_storeu_ps(s.add(2 * HIDDEN), n);
            _mm512_storeu_ps(s.add(3 * HIDDEN), nh);
        }
        if !a.fc.is_null() {
            let mut s = [0.0f32; LANES];
            _mm512_storeu_ps(s.as_mut_ptr(), sigmoid(h_new));
            let y = a.y.add(b * a.y_stride);
            let mut y0 = _mm512_loadu_ps(y);
            let mut y1 = _mm512_setzero_ps();
            for u in (0..LANES).step_by(2) {
                y0 = _mm512_fmadd_ps(
                    _mm512_set1_ps(s[u]),
                    _mm512_load_ps(a.fc.add(u * OUTPUT_DIM)),
                    y0,
                );
                y1 = _mm512_fmadd_ps(
                    _mm512_set1_ps(s[u + 1]),
                    _mm512_load_ps(a.fc.add((u + 1) * OUTPUT_DIM)),
                    y1,
                );
            }
            _mm512_storeu_ps(y, _mm512_add_ps(y0, y1));
        }
    }
}

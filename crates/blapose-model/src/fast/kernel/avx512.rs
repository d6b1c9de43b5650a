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
    match rows {
        1 => tile1(a),
        2 => tile2(a),
        3 => tile3(a),
        4 => tile4(a),
        5 => tile5(a),
        6 => tile6(a),
        7 => tile7(a),
        8 => tile8(a),
        _ => unreachable!("tile of {rows} rows"),
    }
}

/// A kernel for a fixed number of rows; each `(r, z, n, offset)` names one
/// row's accumulators and its offset in the packed `[k][row]` inputs.
macro_rules! tile_fn {
    ($name:ident, $rows:expr, $(($r:ident, $z:ident, $n:ident, $b:expr)),+) => {
        #[target_feature(enable = "avx512f,avx2,fma")]
        unsafe fn $name(a: &TileArgs) {
            let zero = _mm512_setzero_ps();
            $(let mut $r = zero; let mut $z = zero; let mut $n = zero;)+
            let mut w = a.w;
            let mut x = a.x;
            for _ in 0..a.k_in {
                let wr = _mm512_load_ps(w);
                let wz = _mm512_load_ps(w.add(LANES));
                let wn = _mm512_load_ps(w.add(2 * LANES));
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
                let wr = _mm512_load_ps(w);
                let wz = _mm512_load_ps(w.add(LANES));
                let wn = _mm512_load_ps(w.add(2 * LANES));
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

tile_fn!(tile2, 2, (r0, z0, n0, 0), (r1, z1, n1, 1));
tile_fn!(tile3, 3, (r0, z0, n0, 0), (r1, z1, n1, 1), (r2, z2, n2, 2));
tile_fn!(tile4, 4, (r0, z0, n0, 0), (r1, z1, n1, 1), (r2, z2, n2, 2), (r3, z3, n3, 3));
tile_fn!(
    tile5,
    5,
    (r0, z0, n0, 0),
    (r1, z1, n1, 1),
    (r2, z2, n2, 2),
    (r3, z3, n3, 3),
    (r4, z4, n4, 4)
);
tile_fn!(
    tile6,
    6,
    (r0, z0, n0, 0),
    (r1, z1, n1, 1),
    (r2, z2, n2, 2),
    (r3, z3, n3, 3),
    (r4, z4, n4, 4),
    (r5, z5, n5, 5)
);
tile_fn!(
    tile7,
    7,
    (r0, z0, n0, 0),
    (r1, z1, n1, 1),
    (r2, z2, n2, 2),
    (r3, z3, n3, 3),
    (r4, z4, n4, 4),
    (r5, z5, n5, 5),
    (r6, z6, n6, 6)
);
tile_fn!(
    tile8,
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
#[target_feature(enable = "avx512f,avx2,fma")]
unsafe fn tile1(a: &TileArgs) {
    let zero = _mm512_setzero_ps();
    let mut acc = [[zero; 3]; 4];
    let mut w = a.w;
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
                $r = _mm512_fmadd_ps(_mm512_load_ps(wu), xv, $r);
                $z = _mm512_fmadd_ps(_mm512_load_ps(wu.add(LANES)), xv, $z);
                $n = _mm512_fmadd_ps(_mm512_load_ps(wu.add(2 * LANES)), xv, $n);
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

/// Gates -> new states (and output contributions) for each row of a tile:
/// `acc[b] = [r, z, n_h]` pre-activations without biases, `ni[b]` the
/// input part of `n`.
#[inline]
#[target_feature(enable = "avx512f,avx2,fma")]
unsafe fn epilogue<const BT: usize>(a: &TileArgs, acc: &[[__m512; 3]; BT], ni: &[__m512; BT]) {
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
            let pre = a.pre.add(b * a.pre_stride);
            pr = _mm512_add_ps(pr, _mm512_loadu_ps(pre));
            pz = _mm512_add_ps(pz, _mm512_loadu_ps(pre.add(LANES)));
            pn = _mm512_add_ps(pn, _mm512_loadu_ps(pre.add(2 * LANES)));
        }
        let r = sigmoid(pr);
        let z = sigmoid(pz);
        let n = tanh(_mm512_fmadd_ps(r, _mm512_add_ps(g[2], b_nh), pn));
        let h_old = _mm512_loadu_ps(a.h.add(b * a.h_stride + a.unit0));
        let h_new = _mm512_fmadd_ps(z, _mm512_sub_ps(h_old, n), n);
        _mm512_storeu_ps(a.out.add(b * a.out_stride), h_new);
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

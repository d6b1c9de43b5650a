//! AVX-512 version of the panel kernel: a panel's 16 units are one `zmm`
//! per gate. For each input index `k` the three gate vectors are loaded
//! once and multiplied into every row of the tile (`BT` rows), and with few
//! rows the `k` loop is unrolled `KU` ways into independent accumulators so
//! the FMA latency (4 cycles) does not serialize the loop.

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
        1 => tile_n::<1, 4>(a),
        2 => tile_n::<2, 2>(a),
        3 => tile_n::<3, 2>(a),
        4 => tile_n::<4, 2>(a),
        5 => tile_n::<5, 1>(a),
        6 => tile_n::<6, 1>(a),
        7 => tile_n::<7, 1>(a),
        8 => tile_n::<8, 1>(a),
        _ => unreachable!("tile of {rows} rows"),
    }
}

/// `acc[u][b][g] += W[k+u][g] * x[b][k+u]` over `len` values of `k`.
macro_rules! accumulate {
    ($acc:ident, $w:expr, $x:expr, $stride:expr, $len:expr, $BT:ident, $KU:ident) => {{
        let mut w = $w;
        let mut k = 0;
        while k < $len {
            for u in 0..$KU {
                let wr = _mm512_load_ps(w);
                let wz = _mm512_load_ps(w.add(LANES));
                let wn = _mm512_load_ps(w.add(2 * LANES));
                for b in 0..$BT {
                    let xv = _mm512_set1_ps(*$x.add(b * $stride + k + u));
                    $acc[u][b][0] = _mm512_fmadd_ps(wr, xv, $acc[u][b][0]);
                    $acc[u][b][1] = _mm512_fmadd_ps(wz, xv, $acc[u][b][1]);
                    $acc[u][b][2] = _mm512_fmadd_ps(wn, xv, $acc[u][b][2]);
                }
                w = w.add(ROW);
            }
            k += $KU;
        }
    }};
}

#[target_feature(enable = "avx512f,avx2,fma")]
unsafe fn tile_n<const BT: usize, const KU: usize>(a: &TileArgs) {
    let zero = _mm512_setzero_ps();
    let mut acc = [[[zero; 3]; BT]; KU];
    accumulate!(acc, a.w, a.x_in, a.x_stride, a.k_in, BT, KU);
    let mut ni = [zero; BT];
    for b in 0..BT {
        for part in &mut acc {
            ni[b] = _mm512_add_ps(ni[b], part[b][2]);
            part[b][2] = zero;
        }
    }
    accumulate!(acc, a.w.add(a.k_in * ROW), a.h, a.h_stride, HIDDEN, BT, KU);

    let b_r = _mm512_loadu_ps(a.bias);
    let b_z = _mm512_loadu_ps(a.bias.add(LANES));
    let b_ni = _mm512_loadu_ps(a.bias.add(2 * LANES));
    let b_nh = _mm512_loadu_ps(a.bias.add(3 * LANES));
    for b in 0..BT {
        let mut g = acc[0][b];
        for part in acc.iter().skip(1) {
            for (gi, pi) in g.iter_mut().zip(part[b]) {
                *gi = _mm512_add_ps(*gi, pi);
            }
        }
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
            let mut y1 = zero;
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

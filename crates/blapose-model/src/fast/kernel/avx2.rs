//! AVX2 + FMA version of the panel kernel: a panel's 16 units are two `ymm`
//! per gate, so a row needs six accumulators; with 16 registers a tile holds
//! at most two rows, and a single row unrolls `k` twice to hide latency.

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
    match rows {
        1 => tile_n::<1, 2>(a),
        2 => tile_n::<2, 1>(a),
        _ => unreachable!("tile of {rows} rows"),
    }
}

/// `acc[u][b][g][half] += W[k+u][g][half] * x[k+u][b]` over `len` values
/// of `k`, advancing `w` and `x`.
macro_rules! accumulate {
    ($acc:ident, $w:ident, $x:ident, $len:expr, $BT:ident, $KU:ident) => {{
        let mut k = 0;
        while k < $len {
            for u in 0..$KU {
                for b in 0..$BT {
                    let xv = _mm256_set1_ps(*$x.add(b));
                    for g in 0..3 {
                        for half in 0..2 {
                            $acc[u][b][g][half] = _mm256_fmadd_ps(
                                _mm256_load_ps($w.add(g * LANES + half * 8)),
                                xv,
                                $acc[u][b][g][half],
                            );
                        }
                    }
                }
                $w = $w.add(ROW);
                $x = $x.add($BT);
            }
            k += $KU;
        }
    }};
}

#[target_feature(enable = "avx2,fma")]
unsafe fn tile_n<const BT: usize, const KU: usize>(a: &TileArgs) {
    let zero = _mm256_setzero_ps();
    let mut acc = [[[[zero; 2]; 3]; BT]; KU];
    let mut w = a.w;
    let mut x = a.x;
    accumulate!(acc, w, x, a.k_in, BT, KU);
    let mut ni = [[zero; 2]; BT];
    for b in 0..BT {
        for part in &mut acc {
            for half in 0..2 {
                ni[b][half] = _mm256_add_ps(ni[b][half], part[b][2][half]);
                part[b][2][half] = zero;
            }
        }
    }
    accumulate!(acc, w, x, HIDDEN, BT, KU);

    for b in 0..BT {
        let mut h_new = [zero; 2];
        for half in 0..2 {
            let mut g = [zero; 3];
            for part in &acc {
                for (gi, gate) in g.iter_mut().zip(part[b]) {
                    *gi = _mm256_add_ps(*gi, gate[half]);
                }
            }
            let lane = |gate: usize| gate * LANES + half * 8;
            let mut pr = _mm256_add_ps(g[0], _mm256_loadu_ps(a.bias.add(lane(0))));
            let mut pz = _mm256_add_ps(g[1], _mm256_loadu_ps(a.bias.add(lane(1))));
            let mut pn = _mm256_add_ps(ni[b][half], _mm256_loadu_ps(a.bias.add(lane(2))));
            let nh = _mm256_add_ps(g[2], _mm256_loadu_ps(a.bias.add(lane(3))));
            if !a.pre.is_null() {
                let pre = a.pre.add(b * a.pre_stride);
                pr = _mm256_add_ps(pr, _mm256_loadu_ps(pre.add(lane(0))));
                pz = _mm256_add_ps(pz, _mm256_loadu_ps(pre.add(lane(1))));
                pn = _mm256_add_ps(pn, _mm256_loadu_ps(pre.add(lane(2))));
            }
            let r = sigmoid(pr);
            let z = sigmoid(pz);
            let n = tanh(_mm256_fmadd_ps(r, nh, pn));
            let h_old = _mm256_loadu_ps(a.h.add(b * a.h_stride + a.unit0 + half * 8));
            h_new[half] = _mm256_fmadd_ps(z, _mm256_sub_ps(h_old, n), n);
            _mm256_storeu_ps(a.out.add(b * a.out_stride + half * 8), h_new[half]);
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

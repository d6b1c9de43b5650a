//! Portable version of the panel kernel: plain loops, libm non-linearities.
//! It is the oracle the SIMD versions are tested against and the path on
//! CPUs without AVX2.

use super::TileArgs;
use crate::fast::math::scalar::{sigmoid, tanh};
use crate::fast::pack::{LANES, ROW};
use crate::{HIDDEN, OUTPUT_DIM};

const MAX_ROWS: usize = 4;

/// Weight `i` of the panel, widened from f16 when the panel is half precision.
#[inline]
unsafe fn weight(a: &TileArgs, i: usize) -> f32 {
    if a.half {
        half::f16::from_bits(*a.w.cast::<u16>().add(i)).to_f32()
    } else {
        *a.w.cast::<f32>().add(i)
    }
}

/// Kernel for `rows <= 4` rows.
///
/// # Safety
/// See the [`TileArgs`] contract.
pub(crate) unsafe fn tile(rows: usize, a: &TileArgs) {
    assert!(rows <= MAX_ROWS);
    let mut acc = [[[0.0f32; LANES]; 3]; MAX_ROWS];
    let mut ni = [[0.0f32; LANES]; MAX_ROWS];
    // input part (k < k_in), then recurrent part
    for (phase, (k0, len)) in [(0, a.k_in), (a.k_in, HIDDEN)].into_iter().enumerate() {
        for k in k0..k0 + len {
            let w: [f32; ROW] = std::array::from_fn(|i| weight(a, k * ROW + i));
            for (b, acc_b) in acc.iter_mut().enumerate().take(rows) {
                let xv = *a.x.add(k * rows + b);
                for (g, acc_g) in acc_b.iter_mut().enumerate() {
                    for (l, v) in acc_g.iter_mut().enumerate() {
                        *v += w[g * LANES + l] * xv;
                    }
                }
            }
        }
        if phase == 0 {
            for b in 0..rows {
                ni[b] = acc[b][2];
                acc[b][2] = [0.0; LANES];
            }
        }
    }
    let bias = std::slice::from_raw_parts(a.bias, 4 * LANES);
    for b in 0..rows {
        let pre = (!a.pre.is_null())
            .then(|| std::slice::from_raw_parts(a.pre.add(b * a.pre_stride), 3 * HIDDEN));
        let mut save = (!a.save.is_null())
            .then(|| std::slice::from_raw_parts_mut(a.save.add(b * a.save_stride), 4 * HIDDEN));
        let h_old = std::slice::from_raw_parts(a.h.add(b * a.h_stride + a.unit0), LANES);
        let out = std::slice::from_raw_parts_mut(a.out.add(b * a.out_stride), LANES);
        let mut hnew = [0.0f32; LANES];
        for l in 0..LANES {
            let p = |g: usize| pre.map_or(0.0, |p| p[g * HIDDEN + a.unit0 + l]);
            let r = sigmoid(acc[b][0][l] + bias[l] + p(0));
            let z = sigmoid(acc[b][1][l] + bias[LANES + l] + p(1));
            let nh = acc[b][2][l] + bias[3 * LANES + l];
            let n = tanh(ni[b][l] + bias[2 * LANES + l] + p(2) + r * nh);
            hnew[l] = n + z * (h_old[l] - n);
            if let Some(s) = save.as_deref_mut() {
                for (g, v) in [r, z, n, nh].into_iter().enumerate() {
                    s[g * HIDDEN + a.unit0 + l] = v;
                }
            }
        }
        out.copy_from_slice(&hnew);
        if !a.fc.is_null() {
            let fc = std::slice::from_raw_parts(a.fc, LANES * OUTPUT_DIM);
            let y = std::slice::from_raw_parts_mut(a.y.add(b * a.y_stride), OUTPUT_DIM);
            for (u, &hv) in hnew.iter().enumerate() {
                let s = sigmoid(hv);
                for (o, yo) in y.iter_mut().enumerate() {
                    *yo += fc[u * OUTPUT_DIM + o] * s;
                }
            }
        }
    }
}

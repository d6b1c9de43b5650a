//! Products with a constant right-hand side: `Y = X W + b` where `W` is a
//! layer's (inference) weight matrix.
//!
//! Online lifting multiplies a handful of rows (1 to 81 frames) by large
//! weight matrices (up to 6144 x 1024). A general-purpose GEMM repacks `W`
//! on every call, which for so few rows costs more than the arithmetic
//! (candle's CPU matmul reached 5-15 GFLOP/s on these shapes on the 2-core
//! development VM). Here `W` is packed once, when the model is built, into
//! column panels of [`NR`] floats (`K x NR`, contiguous, zero-padded), and a
//! register-blocked micro-kernel streams each panel once per block of
//! [`MR`] rows; a panel (at most 1.5 MB) stays in L2 while the row blocks
//! reuse it. Panels are split across rayon's threads when the product is
//! large enough to pay for the hand-off.
//!
//! The kernel is one generic Rust loop nest compiled three times — for
//! AVX-512, for AVX2+FMA, and portably — and picked at run time by
//! blapose-core's [`Isa`] (the one the bone-length engines use too), so one
//! binary runs anywhere. Results match a plain dot product up to the
//! rounding of the summation order (tested against candle).

use blapose_core::isa::Isa;
use rayon::prelude::*;

/// Panel width (columns per panel): four AVX-512 vectors.
pub(crate) const NR: usize = 64;
/// Rows per register block with AVX-512 (6 x 4 accumulators + 4 loads + 1 broadcast <= 32 registers).
pub(crate) const MR: usize = 6;

/// Work (multiply-adds) below which a product runs on the calling thread.
const PARALLEL_MIN_MACS: usize = 1 << 20;

/// A `K x N` matrix packed into zero-padded `K x NR` column panels.
#[derive(Debug, Clone)]
pub(crate) struct PackedMatrix {
    k: usize,
    n: usize,
    panels: Vec<f32>,
    isa: Isa,
}

impl PackedMatrix {
    /// Pack a row-major `k x n` matrix.
    pub(crate) fn new(w: &[f32], k: usize, n: usize) -> Self {
        assert_eq!(
            w.len(),
            k * n,
            "packing a {k} x {n} matrix from {} values",
            w.len()
        );
        let count = n.div_ceil(NR);
        let mut panels = vec![0.0; count * k * NR];
        for (p, panel) in panels.chunks_exact_mut(k * NR).enumerate() {
            let c0 = p * NR;
            let width = NR.min(n - c0);
            for (row, dst) in panel.chunks_exact_mut(NR).enumerate() {
                dst[..width].copy_from_slice(&w[row * n + c0..row * n + c0 + width]);
            }
        }
        Self {
            k,
            n,
            panels,
            isa: Isa::detect(),
        }
    }

    /// Rows of the matrix (the product's inner dimension).
    pub(crate) fn k(&self) -> usize {
        self.k
    }

    /// Columns of the matrix.
    pub(crate) fn n(&self) -> usize {
        self.n
    }

    /// `x` (`m x k`, row-major) times this matrix, plus `bias` (length
    /// `n`) if given: `m x n`, row-major.
    pub(crate) fn matmul(&self, x: &[f32], bias: Option<&[f32]>) -> Vec<f32> {
        let (k, n) = (self.k, self.n);
        assert_eq!(
            x.len() % k.max(1),
            0,
            "input is not a whole number of {k}-wide rows"
        );
        assert!(bias.is_none_or(|b| b.len() == n), "bias length");
        let m = x.len().checked_div(k).unwrap_or(0);
        let count = n.div_ceil(NR);
        // Panel-major result: panel p holds columns p*NR.. of every row.
        let mut by_panel = vec![0.0f32; count * m * NR];
        let run = |(p, out): (usize, &mut [f32])| {
            let panel = &self.panels[p * k * NR..(p + 1) * k * NR];
            let mut b = [0.0f32; NR];
            if let Some(bias) = bias {
                let c0 = p * NR;
                let width = NR.min(n - c0);
                b[..width].copy_from_slice(&bias[c0..c0 + width]);
            }
            panel_product(self.isa, x, k, panel, &b, out);
        };
        if m * k * n >= PARALLEL_MIN_MACS && count > 1 && rayon::current_num_threads() > 1 {
            by_panel.par_chunks_mut(m * NR).enumerate().for_each(run);
        } else {
            by_panel.chunks_mut(m * NR).enumerate().for_each(run);
        }
        let mut out = vec![0.0f32; m * n];
        for (p, panel) in by_panel.chunks_exact(m * NR).enumerate() {
            let c0 = p * NR;
            let width = NR.min(n - c0);
            for (row, src) in panel.chunks_exact(NR).enumerate() {
                out[row * n + c0..row * n + c0 + width].copy_from_slice(&src[..width]);
            }
        }
        out
    }
}

/// One panel against all rows of `x`, into `out` (`m x NR`).
fn panel_product(isa: Isa, x: &[f32], k: usize, panel: &[f32], bias: &[f32; NR], out: &mut [f32]) {
    match isa {
        // SAFETY: `Isa::detect` found the features each function enables.
        #[cfg(target_arch = "x86_64")]
        Isa::Avx512 => unsafe { panel_avx512(x, k, panel, bias, out) },
        #[cfg(target_arch = "x86_64")]
        Isa::Avx2 => unsafe { panel_avx2(x, k, panel, bias, out) },
        // Elsewhere `detect` never yields a SIMD level.
        _ => panel_rows::<false, 1>(x, k, panel, bias, out),
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx2,fma")]
unsafe fn panel_avx512(x: &[f32], k: usize, panel: &[f32], bias: &[f32; NR], out: &mut [f32]) {
    panel_rows::<true, MR>(x, k, panel, bias, out)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn panel_avx2(x: &[f32], k: usize, panel: &[f32], bias: &[f32; NR], out: &mut [f32]) {
    panel_rows::<true, 1>(x, k, panel, bias, out)
}

/// All rows in blocks of `R`, then the remaining rows as one smaller block
/// (so every row block streams the panel once).
#[inline(always)]
fn panel_rows<const FMA: bool, const R: usize>(
    x: &[f32],
    k: usize,
    panel: &[f32],
    bias: &[f32; NR],
    out: &mut [f32],
) {
    let m = out.len() / NR;
    let mut row = 0;
    while row + R <= m {
        rows::<FMA, R>(x, k, panel, bias, out, row);
        row += R;
    }
    match m - row {
        0 => {}
        1 => rows::<FMA, 1>(x, k, panel, bias, out, row),
        2 => rows::<FMA, 2>(x, k, panel, bias, out, row),
        3 => rows::<FMA, 3>(x, k, panel, bias, out, row),
        4 => rows::<FMA, 4>(x, k, panel, bias, out, row),
        5 => rows::<FMA, 5>(x, k, panel, bias, out, row),
        _ => {
            // Only reachable with R > 6: finish one row at a time.
            for r in row..m {
                rows::<FMA, 1>(x, k, panel, bias, out, r);
            }
        }
    }
}

/// Rows `row .. row + R` into `out`.
#[inline(always)]
fn rows<const FMA: bool, const R: usize>(
    x: &[f32],
    k: usize,
    panel: &[f32],
    bias: &[f32; NR],
    out: &mut [f32],
    row: usize,
) {
    let xs: [&[f32]; R] = std::array::from_fn(|r| &x[(row + r) * k..(row + r + 1) * k]);
    let acc = block::<FMA, R>(xs, k, panel, bias);
    for (r, a) in acc.iter().enumerate() {
        out[(row + r) * NR..(row + r + 1) * NR].copy_from_slice(a);
    }
}

/// `R` rows times one panel: `R x NR` accumulators kept in registers.
#[inline(always)]
fn block<const FMA: bool, const R: usize>(
    xs: [&[f32]; R],
    k: usize,
    panel: &[f32],
    bias: &[f32; NR],
) -> [[f32; NR]; R] {
    let mut acc = [*bias; R];
    let panel = &panel[..k * NR];
    for xr in &xs {
        assert!(xr.len() >= k);
    }
    for (kk, w) in panel.chunks_exact(NR).enumerate() {
        for r in 0..R {
            let xv = xs[r][kk];
            for j in 0..NR {
                acc[r][j] = if FMA {
                    xv.mul_add(w[j], acc[r][j])
                } else {
                    acc[r][j] + xv * w[j]
                };
            }
        }
    }
    acc
}

#[cfg(test)]
mod tests {
    use super::*;

    fn naive(x: &[f32], w: &[f32], bias: &[f32], m: usize, k: usize, n: usize) -> Vec<f32> {
        let mut y = vec![0.0f32; m * n];
        for i in 0..m {
            for j in 0..n {
                let mut s = bias[j] as f64;
                for l in 0..k {
                    s += x[i * k + l] as f64 * w[l * n + j] as f64;
                }
                y[i * n + j] = s as f32;
            }
        }
        y
    }

    #[test]
    fn packed_product_matches_naive_for_awkward_shapes() {
        for (m, k, n) in [
            (1, 1, 1),
            (7, 5, 3),
            (13, 33, 130),
            (1, 300, 64),
            (27, 96, 200),
            (6, 64, 65),
            (200, 70, 90),
        ] {
            let x: Vec<f32> = (0..m * k)
                .map(|i| ((i * 7 % 13) as f32 - 6.0) / 7.0)
                .collect();
            let w: Vec<f32> = (0..k * n)
                .map(|i| ((i * 5 % 11) as f32 - 5.0) / 9.0)
                .collect();
            let b: Vec<f32> = (0..n).map(|i| i as f32 * 0.01).collect();
            let packed = PackedMatrix::new(&w, k, n);
            assert_eq!((packed.k(), packed.n()), (k, n));
            let want = naive(&x, &w, &b, m, k, n);
            let got = packed.matmul(&x, Some(&b));
            let err = want
                .iter()
                .zip(&got)
                .map(|(a, b)| (a - b).abs())
                .fold(0.0f32, f32::max);
            assert!(err < 1e-4, "{m}x{k}x{n}: max error {err}");
            let nob = packed.matmul(&x, None);
            let err = nob
                .iter()
                .zip(&got)
                .enumerate()
                .map(|(i, (a, c))| (a + b[i % n] - c).abs())
                .fold(0.0, f32::max);
            assert!(err < 1e-5);
        }
        // All three instruction-set paths agree (where the CPU has them).
        let (m, k, n) = (9, 40, 70);
        let x: Vec<f32> = (0..m * k).map(|i| (i as f32 * 0.37).sin()).collect();
        let w: Vec<f32> = (0..k * n).map(|i| (i as f32 * 0.11).cos()).collect();
        let mut packed = PackedMatrix::new(&w, k, n);
        let best = packed.matmul(&x, None);
        packed.isa = Isa::Scalar;
        let portable = packed.matmul(&x, None);
        let err = best
            .iter()
            .zip(&portable)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0f32, f32::max);
        assert!(err < 1e-4, "{err}");
    }
}

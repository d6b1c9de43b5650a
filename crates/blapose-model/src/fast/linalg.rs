//! A safe row-major wrapper around the `gemm` crate for the batched parts
//! of the fast paths (whole-sequence embedding and input projection), where
//! a tuned GEMM beats any hand-written loop; public because the trainer's
//! hand-written backward pass (blapose-train's `fastnet`) uses the same one.

/// `dst = a · b` (or `dst += a · b` when `accumulate`), all row-major:
/// `a` is `m x k`, `b` is `k x n`, `dst` is `m x n`. `threads > 1` splits the
/// work over the current rayon pool.
pub fn matmul(
    dst: &mut [f32],
    a: &[f32],
    b: &[f32],
    dims: (usize, usize, usize),
    accumulate: bool,
    threads: usize,
) {
    matmul_t(dst, (a, false), (b, false), dims, accumulate, threads)
}

/// As [`matmul`], with either operand stored transposed: `(a, true)` means
/// `a` holds the `k x m` matrix whose transpose is the left factor, and
/// `(b, true)` that `b` holds `n x k`.
pub fn matmul_t(
    dst: &mut [f32],
    (a, a_t): (&[f32], bool),
    (b, b_t): (&[f32], bool),
    (m, k, n): (usize, usize, usize),
    accumulate: bool,
    threads: usize,
) {
    assert_eq!(a.len(), m * k, "lhs size");
    assert_eq!(b.len(), k * n, "rhs size");
    assert_eq!(dst.len(), m * n, "dst size");
    // (row stride, column stride) of each operand as stored
    let (a_rs, a_cs) = if a_t {
        (1, m as isize)
    } else {
        (k as isize, 1)
    };
    let (b_rs, b_cs) = if b_t {
        (1, k as isize)
    } else {
        (n as isize, 1)
    };
    if m == 0 || n == 0 {
        return;
    }
    let parallelism = if threads > 1 {
        gemm::Parallelism::Rayon(threads)
    } else {
        gemm::Parallelism::None
    };
    // SAFETY: the asserts above guarantee every (row, col) the strides
    // describe lies inside its slice; `dst` is exclusively borrowed and
    // cannot alias the shared inputs.
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            dst.as_mut_ptr(),
            1,
            n as isize,
            accumulate,
            a.as_ptr(),
            a_cs,
            a_rs,
            b.as_ptr(),
            b_cs,
            b_rs,
            1.0,
            1.0,
            false,
            false,
            false,
            parallelism,
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn transposed_operands() {
        let (m, k, n) = (4, 6, 5);
        let a: Vec<f32> = (0..m * k).map(|i| (i as f32 * 0.37).sin()).collect();
        let b: Vec<f32> = (0..k * n).map(|i| (i as f32 * 0.11).cos()).collect();
        let at: Vec<f32> = (0..k * m).map(|i| a[(i % m) * k + i / m]).collect();
        let bt: Vec<f32> = (0..n * k).map(|i| b[(i % k) * n + i / k]).collect();
        let mut want = vec![0.0; m * n];
        matmul(&mut want, &a, &b, (m, k, n), false, 1);
        for (aa, bb) in [
            ((&at, true), (&b, false)),
            ((&a, false), (&bt, true)),
            ((&at, true), (&bt, true)),
        ] {
            let mut d = vec![0.0; m * n];
            matmul_t(&mut d, (aa.0, aa.1), (bb.0, bb.1), (m, k, n), false, 2);
            for (x, y) in d.iter().zip(&want) {
                assert!((x - y).abs() < 1e-5);
            }
        }
    }

    #[test]
    fn matches_naive_product() {
        let (m, k, n) = (5, 7, 3);
        let a: Vec<f32> = (0..m * k).map(|i| (i as f32 * 0.37).sin()).collect();
        let b: Vec<f32> = (0..k * n).map(|i| (i as f32 * 0.11).cos()).collect();
        let mut d = vec![1.0; m * n];
        matmul(&mut d, &a, &b, (m, k, n), true, 1);
        for i in 0..m {
            for j in 0..n {
                let v: f32 = (0..k).map(|t| a[i * k + t] * b[t * n + j]).sum();
                assert!((d[i * n + j] - 1.0 - v).abs() < 1e-5);
            }
        }
    }
}

//! A safe row-major wrapper around the `gemm` crate for the batched parts
//! of the fast paths (whole-sequence embedding and input projection), where
//! a tuned GEMM beats any hand-written loop.

/// `dst = a · b` (or `dst += a · b` when `accumulate`), all row-major:
/// `a` is `m x k`, `b` is `k x n`, `dst` is `m x n`. `threads > 1` splits the
/// work over the current rayon pool.
pub(crate) fn matmul(
    dst: &mut [f32],
    a: &[f32],
    b: &[f32],
    (m, k, n): (usize, usize, usize),
    accumulate: bool,
    threads: usize,
) {
    assert_eq!(a.len(), m * k, "lhs size");
    assert_eq!(b.len(), k * n, "rhs size");
    assert_eq!(dst.len(), m * n, "dst size");
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
            1,
            k as isize,
            b.as_ptr(),
            1,
            n as isize,
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

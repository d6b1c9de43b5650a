//! Averaging of left/right bone pairs, the models' last step.
//!
//! A body's left and right bones have equal lengths, so the paper averages
//! each symmetric pair of predictions. Averaging is linear, so it is also a
//! 16x16 matrix: the reference models multiply by it (which keeps autograd
//! trivial) and the fast kernels fold it into the output weights once at
//! load time instead of paying for it per frame.

use blapose_core::skeleton::{NUM_BONES, SYMMETRIC_BONE_PAIRS};

/// Replace each symmetric pair of lengths by the pair's mean, in place.
pub fn average_pairs(lengths: &mut [f32; NUM_BONES]) {
    for &(r, l) in &SYMMETRIC_BONE_PAIRS {
        let mean = 0.5 * (lengths[r] + lengths[l]);
        lengths[r] = mean;
        lengths[l] = mean;
    }
}

/// The matrix `S` with `y_sym = y · S` for a row vector `y` of 16 lengths
/// (symmetric, so also `S · y` for a column vector).
pub fn averaging_matrix() -> [[f32; NUM_BONES]; NUM_BONES] {
    let mut s = [[0.0f32; NUM_BONES]; NUM_BONES];
    for (i, row) in s.iter_mut().enumerate() {
        row[i] = 1.0;
    }
    for &(r, l) in &SYMMETRIC_BONE_PAIRS {
        s[r][r] = 0.5;
        s[l][l] = 0.5;
        s[r][l] = 0.5;
        s[l][r] = 0.5;
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pairs_become_equal_and_others_stay() {
        let mut y: [f32; NUM_BONES] = std::array::from_fn(|i| i as f32);
        average_pairs(&mut y);
        for &(r, l) in &SYMMETRIC_BONE_PAIRS {
            assert_eq!(y[r], y[l]);
            assert_eq!(y[r], 0.5 * (r + l) as f32);
        }
        // spine, thorax, neck, head are unpaired
        for (i, &v) in y.iter().enumerate().take(10).skip(6) {
            assert_eq!(v, i as f32);
        }
    }

    #[test]
    fn matrix_matches_in_place_average() {
        let y: [f32; NUM_BONES] = std::array::from_fn(|i| (i * i) as f32 * 0.1);
        let s = averaging_matrix();
        let mut expect = y;
        average_pairs(&mut expect);
        for j in 0..NUM_BONES {
            let v: f32 = (0..NUM_BONES).map(|i| y[i] * s[i][j]).sum();
            assert!((v - expect[j]).abs() < 1e-6);
        }
    }
}

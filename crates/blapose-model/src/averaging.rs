//! Running mean of per-frame predictions, as the reference uses them online.
//!
//! An online session predicts bone lengths after every frame from its
//! running hidden state; the paper's online evaluation reports the mean of
//! all predictions so far (early frames are noisy, the mean settles).
//! Servers and evaluators share this one definition.

use crate::OUTPUT_DIM;

/// Mean of the per-frame predictions pushed so far (f64 accumulation, so
/// long streams do not drift).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RunningMean {
    sum: [f64; OUTPUT_DIM],
    count: u64,
}

impl Default for RunningMean {
    fn default() -> Self {
        Self {
            sum: [0.0; OUTPUT_DIM],
            count: 0,
        }
    }
}

impl RunningMean {
    /// An empty mean.
    pub fn new() -> Self {
        Self::default()
    }

    /// Add one frame's prediction and return the mean including it.
    pub fn push(&mut self, lengths: &[f32; OUTPUT_DIM]) -> [f32; OUTPUT_DIM] {
        for (s, &v) in self.sum.iter_mut().zip(lengths) {
            *s += f64::from(v);
        }
        self.count += 1;
        self.mean().unwrap_or([0.0; OUTPUT_DIM])
    }

    /// The current mean, `None` before the first frame.
    pub fn mean(&self) -> Option<[f32; OUTPUT_DIM]> {
        (self.count > 0).then(|| std::array::from_fn(|i| (self.sum[i] / self.count as f64) as f32))
    }

    /// Frames averaged so far.
    pub fn count(&self) -> u64 {
        self.count
    }

    /// The running sum of the predictions (f64), per bone.
    pub fn sum(&self) -> &[f64; OUTPUT_DIM] {
        &self.sum
    }

    /// A mean with exactly this `sum` over `count` predictions (what
    /// [`RunningMean::sum`] and [`RunningMean::count`] gave): restores a
    /// saved mean bit for bit.
    pub fn from_parts(sum: [f64; OUTPUT_DIM], count: u64) -> Self {
        Self { sum, count }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn averages_all_frames_seen() {
        let mut m = RunningMean::new();
        assert_eq!(m.mean(), None);
        let a = [1.0f32; OUTPUT_DIM];
        let b: [f32; OUTPUT_DIM] = std::array::from_fn(|i| i as f32);
        assert_eq!(m.push(&a), a);
        let mean = m.push(&b);
        for (i, v) in mean.iter().enumerate() {
            assert_eq!(*v, (1.0 + i as f32) / 2.0);
        }
        assert_eq!(m.count(), 2);
    }
}

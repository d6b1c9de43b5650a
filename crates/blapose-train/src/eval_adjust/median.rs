//! The `lifter_median` baseline's lengths: per bone, the running median of
//! the lifter's own lengths over the frames so far (causal, like the GRU).

use std::cmp::{Ordering, Reverse};
use std::collections::BinaryHeap;

use blapose_core::bones::bone_lengths;
use blapose_core::skeleton::NUM_BONES;
use blapose_core::{BoneLengths, Pose};

/// Total order on lengths for the median heaps (lengths are finite).
#[derive(Debug, Clone, Copy, PartialEq)]
struct Length(f32);

impl Eq for Length {}

impl PartialOrd for Length {
    fn partial_cmp(&self, other: &Self) -> Option<Ordering> {
        Some(self.cmp(other))
    }
}

impl Ord for Length {
    fn cmp(&self, other: &Self) -> Ordering {
        self.0.total_cmp(&other.0)
    }
}

/// Median of the values pushed so far, in O(log n) per value: the lower
/// half in a max-heap, the upper half in a min-heap, the lower one at most
/// one larger. An even count gives the mean of the two middle values.
#[derive(Debug, Default)]
struct RunningMedian {
    lower: BinaryHeap<Length>,
    upper: BinaryHeap<Reverse<Length>>,
}

impl RunningMedian {
    fn push(&mut self, v: f32) -> f32 {
        match self.lower.peek() {
            Some(top) if v > top.0 => self.upper.push(Reverse(Length(v))),
            _ => self.lower.push(Length(v)),
        }
        if self.lower.len() > self.upper.len() + 1 {
            let moved = self.lower.pop().map(Reverse);
            self.upper.extend(moved);
        } else if self.upper.len() > self.lower.len() {
            let moved = self.upper.pop().map(|Reverse(l)| l);
            self.lower.extend(moved);
        }
        let low = self.lower.peek().map_or(v, |l| l.0);
        if self.lower.len() == self.upper.len() {
            let high = self.upper.peek().map_or(low, |Reverse(l)| l.0);
            (low + high) / 2.0
        } else {
            low
        }
    }
}

/// The running per-bone median of `poses`' own bone lengths: entry `t` is
/// the median over frames `0..=t` (the `lifter_median` baseline).
pub fn running_median_lengths(poses: &[Pose]) -> Vec<BoneLengths> {
    let mut medians: [RunningMedian; NUM_BONES] = std::array::from_fn(|_| RunningMedian::default());
    poses
        .iter()
        .map(|p| {
            let l = bone_lengths(p);
            std::array::from_fn(|b| medians[b].push(l[b]))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A pose whose 16 bones all have non-zero length.
    fn pose(scale: f32) -> Pose {
        std::array::from_fn(|j| {
            let j = j as f32;
            [
                0.1 * j * scale,
                0.05 * (j % 3.0) * scale,
                0.02 * j * j * scale,
            ]
        })
    }

    #[test]
    fn running_median_is_causal_and_averages_the_middle_pair() {
        let scales = [1.0, 3.0, 2.0, 0.5, 10.0];
        let poses: Vec<Pose> = scales.iter().map(|&s| pose(s)).collect();
        let medians = running_median_lengths(&poses);
        let base = bone_lengths(&pose(1.0));
        // Medians of the scales so far: 1; (1+3)/2; 2; (1+2)/2; 2.
        for (t, want) in [1.0f32, 2.0, 2.0, 1.5, 2.0].into_iter().enumerate() {
            for b in 0..NUM_BONES {
                let got = medians[t][b];
                let expected = base[b] * want;
                assert!(
                    (got - expected).abs() <= 1e-5 * expected,
                    "frame {t} bone {b}: {got} vs {expected}"
                );
            }
        }
    }

    #[test]
    fn one_outlier_frame_does_not_move_the_median() {
        let mut m = RunningMedian::default();
        for v in [0.30, 0.31, 0.29, 0.30] {
            m.push(v);
        }
        let with_outlier = m.push(5.0);
        assert!((with_outlier - 0.30).abs() < 1e-6, "{with_outlier}");
    }
}

//! Latency percentiles.
//!
//! A load test keeps every per-frame latency (8 bytes a frame: a million
//! frames is 8 MB), so percentiles are exact order statistics rather than
//! histogram estimates; with few samples an estimate would hide exactly the
//! tail the test is about. The convention is nearest rank: the p-th
//! percentile of n samples is the ceil(p/100 * n)-th smallest, so it is
//! always a latency that was actually observed.

use serde::Serialize;

/// The nearest-rank `p`-th percentile (0 < p <= 100) of `sorted`
/// (ascending); `None` for no samples or a `p` outside (0, 100].
pub fn percentile(sorted: &[u64], p: f64) -> Option<u64> {
    if sorted.is_empty() || !(p > 0.0 && p <= 100.0) {
        return None;
    }
    let rank = (p / 100.0 * sorted.len() as f64).ceil() as usize;
    Some(sorted[rank.clamp(1, sorted.len()) - 1])
}

/// Latency summary in milliseconds (send to answer).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct LatencyMs {
    /// Median.
    pub p50: f64,
    /// 90th percentile.
    pub p90: f64,
    /// 99th percentile.
    pub p99: f64,
    /// Largest latency observed.
    pub max: f64,
}

impl LatencyMs {
    /// Summarize latencies given in nanoseconds (sorts them in place);
    /// `None` when there are none.
    pub fn from_nanos(samples: &mut [u64]) -> Option<Self> {
        samples.sort_unstable();
        let ms = |p| percentile(samples, p).map(|ns| ns as f64 / 1e6);
        Some(LatencyMs {
            p50: ms(50.0)?,
            p90: ms(90.0)?,
            p99: ms(99.0)?,
            max: ms(100.0)?,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nearest_rank_percentiles() {
        let v: Vec<u64> = (1..=100).collect();
        assert_eq!(percentile(&v, 50.0), Some(50));
        assert_eq!(percentile(&v, 90.0), Some(90));
        assert_eq!(percentile(&v, 99.0), Some(99));
        assert_eq!(percentile(&v, 100.0), Some(100));
        assert_eq!(percentile(&v, 0.1), Some(1));
        // Few samples: p99 is the largest, never an interpolated value.
        assert_eq!(percentile(&[3, 7, 9], 99.0), Some(9));
        assert_eq!(percentile(&[3, 7, 9], 50.0), Some(7));
        assert_eq!(percentile(&[5], 50.0), Some(5));
        assert_eq!(percentile(&[], 50.0), None);
        assert_eq!(percentile(&v, 0.0), None);
        assert_eq!(percentile(&v, 101.0), None);
        assert_eq!(percentile(&v, f64::NAN), None);
    }

    #[test]
    fn summary_sorts_and_converts_to_ms() {
        let mut ns = vec![4_000_000, 1_000_000, 3_000_000, 2_000_000];
        let s = LatencyMs::from_nanos(&mut ns).unwrap();
        assert_eq!(s.p50, 2.0);
        assert_eq!(s.p90, 4.0);
        assert_eq!(s.p99, 4.0);
        assert_eq!(s.max, 4.0);
        assert!(LatencyMs::from_nanos(&mut []).is_none());
    }
}

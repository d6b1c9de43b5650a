//! Timing a per-frame step the way the benchmark tables report it: steps
//! per wall-clock second after untimed warm-up steps, with the process's
//! CPU use over the same interval (these machines are shared, so a slow
//! run must be told apart from a starved one), and medians over runs that
//! skip what a run could not measure.
//!
//! Why a module: the protocol is the tables' and deserves its own tests;
//! the binaries only say what one step is.

use std::time::Instant;

use anyhow::{Context, Result};
use blapose_core::Keypoints2d;
use serde::Serialize;

use crate::machine::process_cpu_seconds;

/// One timed measurement.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct Measurement {
    /// Steps per wall-clock second.
    pub fps: f64,
    /// Process CPU time over wall time, in percent (100 = one core busy
    /// throughout; below the thread count means the process waited for a
    /// CPU, i.e. the machine was shared).
    pub cpu_pct: Option<f64>,
    /// With the adjustment: the share of the timed wall time spent in the
    /// adjustment itself, in percent (timed inside the same steps, so it is
    /// robust to load changes between runs).
    pub adjustment_share_pct: Option<f64>,
}

impl Measurement {
    /// `fps` steps per second at `cpu_pct` CPU use, no adjustment share.
    pub fn new(fps: f64, cpu_pct: Option<f64>) -> Self {
        Self {
            fps,
            cpu_pct,
            adjustment_share_pct: None,
        }
    }
}

/// Time `steps` calls of `step` after `warmup` untimed ones, cycling
/// through `stream`.
pub fn measure(
    stream: &[Keypoints2d],
    warmup: usize,
    steps: usize,
    mut step: impl FnMut(&Keypoints2d) -> Result<()>,
) -> Result<Measurement> {
    let mut frames = stream.iter().cycle();
    for _ in 0..warmup {
        step(frames.next().context("empty stream")?)?;
    }
    let cpu0 = process_cpu_seconds();
    let start = Instant::now();
    for _ in 0..steps {
        step(frames.next().context("empty stream")?)?;
    }
    let wall = start.elapsed().as_secs_f64();
    let cpu_pct = cpu0
        .zip(process_cpu_seconds())
        .map(|(a, b)| 100.0 * (b - a) / wall);
    Ok(Measurement::new(steps as f64 / wall, cpu_pct))
}

/// Median of the defined values of `f` over `runs` (`None` if there are none).
pub fn median_of(runs: &[Measurement], f: impl Fn(&Measurement) -> Option<f64>) -> Option<f64> {
    let mut v: Vec<f64> = runs.iter().filter_map(f).collect();
    v.sort_by(f64::total_cmp);
    let n = v.len();
    match n {
        0 => None,
        _ if n % 2 == 1 => Some(v[n / 2]),
        _ => Some(0.5 * (v[n / 2 - 1] + v[n / 2])),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn m(fps: f64, cpu: Option<f64>) -> Measurement {
        Measurement::new(fps, cpu)
    }

    #[test]
    fn medians_skip_missing_values() {
        let runs = [m(3.0, Some(50.0)), m(1.0, None), m(2.0, Some(70.0))];
        assert_eq!(median_of(&runs, |r| Some(r.fps)), Some(2.0));
        assert_eq!(median_of(&runs, |r| r.cpu_pct), Some(60.0));
        assert_eq!(median_of(&[], |r| Some(r.fps)), None);
    }

    #[test]
    fn measure_counts_steps_and_warmup() {
        let stream = [[[0.0f32; 2]; blapose_core::NUM_JOINTS]; 5];
        let mut calls = 0;
        let r = measure(&stream, 3, 10, |_| {
            calls += 1;
            Ok(())
        })
        .unwrap();
        assert_eq!(calls, 13);
        assert!(r.fps > 0.0);
        assert!(measure(&stream, 0, 1, |_| anyhow::bail!("boom")).is_err());
        assert!(measure(&[], 0, 1, |_| Ok(())).is_err(), "empty stream");
    }
}

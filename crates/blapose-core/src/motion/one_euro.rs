//! The One Euro filter (Casiez, Roussel and Vogel, CHI 2012): a first-order
//! low-pass whose cutoff rises with the signal's speed, so slow motion is
//! smoothed hard and fast motion lags little. MediaPipe smooths its
//! landmarks with it; here it is one of the causal candidates measured on
//! bone directions and on 2D keypoints (`blapose-lab motion`).
//!
//! A bank filters many channels that share one clock; its state is plain
//! numbers so a session token can carry it bit for bit.

use std::f64::consts::PI;

/// The filter's three settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OneEuroParams {
    /// Cutoff at rest (Hz).
    pub min_cutoff_hz: f64,
    /// How fast the cutoff rises with speed (per unit of the signal's speed
    /// in units/s).
    pub beta: f64,
    /// Cutoff of the speed estimate (Hz).
    pub derivative_cutoff_hz: f64,
}

/// Smoothing factor of a first-order low-pass at `cutoff_hz` sampled at
/// `rate_hz`.
fn alpha(cutoff_hz: f64, rate_hz: f64) -> f64 {
    let tau = 1.0 / (2.0 * PI * cutoff_hz);
    1.0 / (1.0 + tau * rate_hz)
}

/// One Euro filters over `channels` signals sampled together.
#[derive(Debug, Clone, PartialEq)]
pub struct OneEuroBank {
    params: OneEuroParams,
    rate_hz: f64,
    /// Last output per channel (empty before the first sample).
    value: Vec<f64>,
    /// Last smoothed speed per channel (units/s).
    speed: Vec<f64>,
}

impl OneEuroBank {
    /// A bank at `rate_hz` samples per second, empty until its first sample.
    pub fn new(params: OneEuroParams, rate_hz: f64) -> Self {
        Self {
            params,
            rate_hz,
            value: Vec::new(),
            speed: Vec::new(),
        }
    }

    /// Filter one sample of every channel in place.
    pub fn step(&mut self, x: &mut [f64]) {
        if self.value.len() != x.len() {
            self.value = x.to_vec();
            self.speed = vec![0.0; x.len()];
            return;
        }
        let p = self.params;
        let a_d = alpha(p.derivative_cutoff_hz, self.rate_hz);
        for ((xi, v), s) in x.iter_mut().zip(&mut self.value).zip(&mut self.speed) {
            let raw_speed = (*xi - *v) * self.rate_hz;
            *s += a_d * (raw_speed - *s);
            let cutoff = p.min_cutoff_hz + p.beta * s.abs();
            *v += alpha(cutoff, self.rate_hz) * (*xi - *v);
            *xi = *v;
        }
    }

    /// The state as numbers (values, then speeds; empty before a sample).
    pub fn state(&self) -> Vec<f64> {
        self.value.iter().chain(&self.speed).copied().collect()
    }

    /// Restore [`Self::state`]; `None` when its length is odd.
    pub fn with_state(mut self, state: &[f64]) -> Option<Self> {
        if !state.len().is_multiple_of(2) {
            return None;
        }
        let (v, s) = state.split_at(state.len() / 2);
        self.value = v.to_vec();
        self.speed = s.to_vec();
        Some(self)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const PARAMS: OneEuroParams = OneEuroParams {
        min_cutoff_hz: 1.0,
        beta: 0.5,
        derivative_cutoff_hz: 1.0,
    };

    #[test]
    fn a_constant_passes_unchanged_and_noise_shrinks() {
        let mut bank = OneEuroBank::new(PARAMS, 50.0);
        let mut x = [2.0];
        for _ in 0..10 {
            bank.step(&mut x);
            assert_eq!(x[0], 2.0);
        }
        let mut bank = OneEuroBank::new(PARAMS, 50.0);
        let mut out = Vec::new();
        for t in 0..400 {
            let mut x = [if t % 2 == 0 { 0.01 } else { -0.01 }];
            bank.step(&mut x);
            out.push(x[0]);
        }
        let late = out[300..].iter().map(|v| v.abs()).fold(0.0, f64::max);
        assert!(late < 0.002, "alternating noise left at {late}");
    }

    #[test]
    fn state_round_trips_exactly() {
        let mut a = OneEuroBank::new(PARAMS, 50.0);
        for t in 0..20 {
            a.step(&mut [t as f64 * 0.1, (t as f64).sin()]);
        }
        let mut b = OneEuroBank::new(PARAMS, 50.0)
            .with_state(&a.state())
            .unwrap();
        for t in 20..40 {
            let mut xa = [t as f64 * 0.1, (t as f64).sin()];
            let mut xb = xa;
            a.step(&mut xa);
            b.step(&mut xb);
            assert_eq!(xa, xb);
        }
    }
}

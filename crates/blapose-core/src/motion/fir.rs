//! A learned causal filter: each output is a fixed weighted sum of the
//! last [`FIR_TAPS`] inputs of its channel (a finite impulse response), the
//! weights fitted by least squares on the training subjects so that the
//! filtered lifter directions come close to the true ones *and* move like
//! them ([`FirFit`]).
//!
//! Why: a hand-tuned low-pass or Kalman filter trades accuracy for calm,
//! because its model of the signal (white noise on a constant-velocity
//! path) is not the lifter's. The best causal linear filter for the
//! lifter's actual errors is a least-squares problem in the weights,
//! including the velocity and acceleration terms (each is linear in the
//! weights too), so it is solved exactly, no gradient descent, from the
//! same data any choice is made on. Its state is the last inputs, so a
//! session token carries it bit for bit.

use nalgebra::{DMatrix, DVector};

/// Inputs each output reads (this one and the 23 before it: 0.48 s at
/// 50 Hz).
pub const FIR_TAPS: usize = 24;

/// The weights: `taps[k]` multiplies the input `k` frames ago.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FirTaps(pub [f64; FIR_TAPS]);

/// FIR filters over channels sampled together.
#[derive(Debug, Clone, PartialEq)]
pub struct FirBank {
    taps: FirTaps,
    /// Per channel, the last [`FIR_TAPS`] inputs, newest first (empty before
    /// the first sample).
    history: Vec<f64>,
}

impl FirBank {
    /// A bank with no history (the first sample fills it).
    pub fn new(taps: FirTaps) -> Self {
        Self {
            taps,
            history: Vec::new(),
        }
    }

    /// Filter one sample of every channel in place.
    pub fn step(&mut self, x: &mut [f64]) {
        if self.history.len() != x.len() * FIR_TAPS {
            // Before any past: as if the first sample had always been there.
            self.history = x.iter().flat_map(|&v| [v; FIR_TAPS]).collect();
        }
        for (c, v) in x.iter_mut().enumerate() {
            let h = &mut self.history[c * FIR_TAPS..(c + 1) * FIR_TAPS];
            h.copy_within(0..FIR_TAPS - 1, 1);
            h[0] = *v;
            *v = h.iter().zip(&self.taps.0).map(|(a, b)| a * b).sum();
        }
    }

    /// The state as numbers (every channel's history).
    pub fn state(&self) -> Vec<f64> {
        self.history.clone()
    }

    /// Restore [`Self::state`]; `None` unless it is whole histories.
    pub fn with_state(mut self, state: &[f64]) -> Option<Self> {
        if !state.len().is_multiple_of(FIR_TAPS) {
            return None;
        }
        self.history = state.to_vec();
        Some(self)
    }
}

/// Least-squares fit of [`FirTaps`]: minimise over the training series
/// `Σ |y - g|² + λ_v Σ |Δy - Δg|² + λ_a Σ |Δ²y - Δ²g|²`, where `y` is the
/// filtered input and `g` the truth. The three terms are accumulated apart
/// so that weights can be tried without a second pass over the data.
#[derive(Debug, Clone)]
pub struct FirFit {
    normal: [DMatrix<f64>; 3],
    rhs: [DVector<f64>; 3],
}

impl Default for FirFit {
    fn default() -> Self {
        Self {
            normal: std::array::from_fn(|_| DMatrix::zeros(FIR_TAPS, FIR_TAPS)),
            rhs: std::array::from_fn(|_| DVector::zeros(FIR_TAPS)),
        }
    }
}

impl FirFit {
    /// Add one recording: `input` and `target` are `frames x channels`,
    /// frame-major. Frames before the first read it, as [`FirBank`] does.
    pub fn add(&mut self, input: &[f64], target: &[f64], channels: usize) {
        let frames = input.len() / channels.max(1);
        if frames < 3 || target.len() != input.len() {
            return;
        }
        let at = |t: isize, c: usize| input[(t.max(0) as usize) * channels + c];
        let mut rows = [[0.0f64; FIR_TAPS]; 3];
        for c in 0..channels {
            for t in 2..frames {
                let t = t as isize;
                for k in 0..FIR_TAPS {
                    let k = k as isize;
                    let (x0, x1, x2) = (at(t - k, c), at(t - k - 1, c), at(t - k - 2, c));
                    rows[0][k as usize] = x0;
                    rows[1][k as usize] = x0 - x1;
                    rows[2][k as usize] = x0 - 2.0 * x1 + x2;
                }
                let g = |s: isize| target[s as usize * channels + c];
                let goals = [g(t), g(t) - g(t - 1), g(t) - 2.0 * g(t - 1) + g(t - 2)];
                for term in 0..3 {
                    let r = &rows[term];
                    let n = &mut self.normal[term];
                    for i in 0..FIR_TAPS {
                        self.rhs[term][i] += r[i] * goals[term];
                        for j in 0..FIR_TAPS {
                            n[(i, j)] += r[i] * r[j];
                        }
                    }
                }
            }
        }
    }

    /// The taps for velocity and acceleration weights `λ_v`, `λ_a`; `None`
    /// without data.
    pub fn solve(&self, velocity_weight: f64, accel_weight: f64) -> Option<FirTaps> {
        let w = [1.0, velocity_weight, accel_weight];
        let a = (0..3).fold(DMatrix::zeros(FIR_TAPS, FIR_TAPS), |m, i| {
            m + &self.normal[i] * w[i]
        });
        let b = (0..3).fold(DVector::zeros(FIR_TAPS), |v, i| v + &self.rhs[i] * w[i]);
        let x = a.cholesky()?.solve(&b);
        Some(FirTaps(std::array::from_fn(|k| x[k])))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_fit_recovers_a_known_filter_and_the_bank_applies_it() {
        // Target = a 3-tap moving average of the input.
        let input: Vec<f64> = (0..400)
            .map(|t| ((t * 37 % 101) as f64 / 50.0 - 1.0) + 0.01 * t as f64)
            .collect();
        let mut target = input.clone();
        for t in 0..input.len() {
            let x = |s: usize| input[t.saturating_sub(s)];
            target[t] = (x(0) + x(1) + x(2)) / 3.0;
        }
        let mut fit = FirFit::default();
        fit.add(&input, &target, 1);
        let taps = fit.solve(0.0, 0.0).unwrap();
        for (k, &v) in taps.0.iter().enumerate() {
            let want = if k < 3 { 1.0 / 3.0 } else { 0.0 };
            assert!((v - want).abs() < 1e-6, "tap {k}: {v}");
        }
        let mut bank = FirBank::new(taps);
        for (t, (&x, &g)) in input.iter().zip(&target).enumerate() {
            let mut v = [x];
            bank.step(&mut v);
            assert!((v[0] - g).abs() < 1e-6, "frame {t}");
        }
    }

    #[test]
    fn state_round_trips_exactly() {
        let taps = FirTaps(std::array::from_fn(|k| 1.0 / (k + 2) as f64));
        let mut a = FirBank::new(taps);
        for t in 0..30 {
            a.step(&mut [t as f64, (t as f64).cos()]);
        }
        let mut b = FirBank::new(taps).with_state(&a.state()).unwrap();
        for t in 30..50 {
            let mut xa = [t as f64, 0.5];
            let mut xb = xa;
            a.step(&mut xa);
            b.step(&mut xb);
            assert_eq!(xa, xb);
        }
    }
}

//! A constant-velocity Kalman filter per channel, and its Rauch-Tung-Striebel
//! smoother (the forward-backward, zero-lag offline counterpart).
//!
//! Why a model of motion: a plain low-pass (One Euro, a Butterworth run
//! forwards) answers a moving signal late, so a causal stage that only
//! smooths trades accuracy for calm. A filter that also tracks each
//! channel's velocity predicts where a steadily moving joint goes next and
//! answers without that lag; only changes of velocity (accelerations, the
//! white process noise `q`) are smoothed.
//!
//! The model, per channel and sampled every `dt` seconds: state `[x, v]`,
//! `x' = x + v dt`, `v' = v + w` with continuous white acceleration noise of
//! spectral density `q` (units²/s³), and a measurement `z = x + n` with
//! variance `r` (units²). Every channel of a bank shares `q`, `r` and the
//! clock, so one 2x2 covariance serves them all. The state is plain
//! numbers, so a session token carries it bit for bit.

/// Noise settings of the constant-velocity model.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct KalmanParams {
    /// Spectral density of the white acceleration (units²/s³): larger
    /// follows quicker changes, smooths less.
    pub process_noise: f64,
    /// Variance of one measurement (units²).
    pub measurement_noise: f64,
}

/// Symmetric 2x2 covariance `[[xx, xv], [xv, vv]]`.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Covariance {
    xx: f64,
    xv: f64,
    vv: f64,
}

impl Covariance {
    /// `F P F^T + Q` for the step `dt`.
    fn predicted(self, p: KalmanParams, dt: f64) -> Self {
        let q = p.process_noise;
        Self {
            xx: self.xx + 2.0 * dt * self.xv + dt * dt * self.vv + q * dt * dt * dt / 3.0,
            xv: self.xv + dt * self.vv + q * dt * dt / 2.0,
            vv: self.vv + q * dt,
        }
    }

    /// The gain for a measurement of `x` and the covariance after it.
    fn updated(self, p: KalmanParams) -> ([f64; 2], Self) {
        let s = self.xx + p.measurement_noise;
        let k = [self.xx / s, self.xv / s];
        let updated = Self {
            xx: (1.0 - k[0]) * self.xx,
            xv: (1.0 - k[0]) * self.xv,
            vv: self.vv - k[1] * self.xv,
        };
        (k, updated)
    }

    /// The covariance a channel starts with after its first measurement:
    /// the measurement's variance for `x`, and for `v` the variance of the
    /// velocity two such measurements one step apart would give.
    fn initial(p: KalmanParams, dt: f64) -> Self {
        Self {
            xx: p.measurement_noise,
            xv: 0.0,
            vv: 2.0 * p.measurement_noise / (dt * dt),
        }
    }
}

/// Constant-velocity Kalman filters over channels sampled together.
#[derive(Debug, Clone, PartialEq)]
pub struct KalmanBank {
    params: KalmanParams,
    dt: f64,
    cov: Covariance,
    /// Position estimate per channel (empty before the first sample).
    x: Vec<f64>,
    /// Velocity estimate per channel (units/s).
    v: Vec<f64>,
}

impl KalmanBank {
    /// A bank sampled at `rate_hz`, empty until its first sample.
    pub fn new(params: KalmanParams, rate_hz: f64) -> Self {
        let dt = 1.0 / rate_hz;
        Self {
            params,
            dt,
            cov: Covariance::initial(params, dt),
            x: Vec::new(),
            v: Vec::new(),
        }
    }

    /// Filter one sample of every channel in place (the filtered position
    /// replaces the measurement).
    pub fn step(&mut self, z: &mut [f64]) {
        if self.x.len() != z.len() {
            self.x = z.to_vec();
            self.v = vec![0.0; z.len()];
            self.cov = Covariance::initial(self.params, self.dt);
            return;
        }
        let (k, cov) = self
            .cov
            .predicted(self.params, self.dt)
            .updated(self.params);
        self.cov = cov;
        for ((zi, x), v) in z.iter_mut().zip(&mut self.x).zip(&mut self.v) {
            let predicted = *x + self.dt * *v;
            let innovation = *zi - predicted;
            *x = predicted + k[0] * innovation;
            *v += k[1] * innovation;
            *zi = *x;
        }
    }

    /// Where every channel is expected one step from now (no measurement).
    pub fn predict(&self) -> Vec<f64> {
        self.x
            .iter()
            .zip(&self.v)
            .map(|(x, v)| x + self.dt * v)
            .collect()
    }

    /// The state as numbers: the covariance (3), then positions, then
    /// velocities (just the covariance before the first sample).
    pub fn state(&self) -> Vec<f64> {
        [self.cov.xx, self.cov.xv, self.cov.vv]
            .into_iter()
            .chain(self.x.iter().copied())
            .chain(self.v.iter().copied())
            .collect()
    }

    /// Restore [`Self::state`]; `None` when it has the wrong shape.
    pub fn with_state(mut self, state: &[f64]) -> Option<Self> {
        let (cov, rest) = state.split_first_chunk::<3>()?;
        if rest.len() % 2 != 0 {
            return None;
        }
        self.cov = Covariance {
            xx: cov[0],
            xv: cov[1],
            vv: cov[2],
        };
        let (x, v) = rest.split_at(rest.len() / 2);
        self.x = x.to_vec();
        self.v = v.to_vec();
        Some(self)
    }
}

/// The Rauch-Tung-Striebel smoother of [`KalmanBank`]'s model over a whole
/// recording: `frames` samples of `channels` channels, frame-major, smoothed
/// in place. Every output reads the whole recording (zero lag).
pub fn rts_smooth(values: &mut [f64], channels: usize, params: KalmanParams, rate_hz: f64) {
    if channels == 0 || values.len() < 2 * channels {
        return;
    }
    let frames = values.len() / channels;
    let dt = 1.0 / rate_hz;
    // Forward pass: filtered states and the covariances before and after
    // each update (shared by every channel).
    let mut xs = vec![0.0; values.len()];
    let mut vs = vec![0.0; values.len()];
    let mut filtered = Vec::with_capacity(frames);
    let mut predicted = Vec::with_capacity(frames);
    let mut cov = Covariance::initial(params, dt);
    xs[..channels].copy_from_slice(&values[..channels]);
    filtered.push(cov);
    predicted.push(cov);
    for t in 1..frames {
        let prior = cov.predicted(params, dt);
        let (k, post) = prior.updated(params);
        predicted.push(prior);
        filtered.push(post);
        cov = post;
        for c in 0..channels {
            let (i, j) = (t * channels + c, (t - 1) * channels + c);
            let x_pred = xs[j] + dt * vs[j];
            let innovation = values[i] - x_pred;
            xs[i] = x_pred + k[0] * innovation;
            vs[i] = vs[j] + k[1] * innovation;
        }
    }
    // Backward pass: C = P_f F^T P_pred(t+1)^-1, one gain for all channels.
    let mut sx: Vec<f64> = xs[(frames - 1) * channels..].to_vec();
    let mut sv: Vec<f64> = vs[(frames - 1) * channels..].to_vec();
    values[(frames - 1) * channels..].copy_from_slice(&sx);
    for t in (0..frames - 1).rev() {
        let pf = filtered[t];
        let pp = predicted[t + 1];
        // P_f F^T with F = [[1, dt], [0, 1]].
        let a = [[pf.xx + dt * pf.xv, pf.xv], [pf.xv + dt * pf.vv, pf.vv]];
        let det = pp.xx * pp.vv - pp.xv * pp.xv;
        let inv = [[pp.vv / det, -pp.xv / det], [-pp.xv / det, pp.xx / det]];
        let gain = [
            [
                a[0][0] * inv[0][0] + a[0][1] * inv[1][0],
                a[0][0] * inv[0][1] + a[0][1] * inv[1][1],
            ],
            [
                a[1][0] * inv[0][0] + a[1][1] * inv[1][0],
                a[1][0] * inv[0][1] + a[1][1] * inv[1][1],
            ],
        ];
        for c in 0..channels {
            let i = t * channels + c;
            let dx = sx[c] - (xs[i] + dt * vs[i]);
            let dv = sv[c] - vs[i];
            sx[c] = xs[i] + gain[0][0] * dx + gain[0][1] * dv;
            sv[c] = vs[i] + gain[1][0] * dx + gain[1][1] * dv;
            values[i] = sx[c];
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const PARAMS: KalmanParams = KalmanParams {
        process_noise: 1.0,
        measurement_noise: 1e-4,
    };

    #[test]
    fn a_steady_ramp_is_followed_without_lag() {
        let mut bank = KalmanBank::new(PARAMS, 50.0);
        let mut last = 0.0;
        for t in 0..200 {
            let mut z = [0.01 * t as f64];
            bank.step(&mut z);
            last = z[0] - 0.01 * t as f64;
        }
        assert!(last.abs() < 1e-6, "lag {last}");
    }

    #[test]
    fn the_smoother_removes_more_noise_than_the_filter() {
        let truth: Vec<f64> = (0..300).map(|t| (t as f64 * 0.05).sin()).collect();
        let noisy: Vec<f64> = truth
            .iter()
            .enumerate()
            .map(|(t, v)| v + 0.02 * ((t * 7919 % 13) as f64 / 6.0 - 1.0))
            .collect();
        // The sine accelerates by up to 6.25 units/s²: q must allow it.
        let params = KalmanParams {
            process_noise: 50.0,
            measurement_noise: 4e-4,
        };
        let mut filtered = noisy.clone();
        let mut bank = KalmanBank::new(params, 50.0);
        for v in &mut filtered {
            let mut z = [*v];
            bank.step(&mut z);
            *v = z[0];
        }
        let mut smoothed = noisy.clone();
        rts_smooth(&mut smoothed, 1, params, 50.0);
        let err = |s: &[f64]| -> f64 {
            s.iter()
                .zip(&truth)
                .skip(20)
                .map(|(a, b)| (a - b).abs())
                .sum::<f64>()
                / 280.0
        };
        let (raw, f, s) = (err(&noisy), err(&filtered), err(&smoothed));
        assert!(f < raw && s < f, "raw {raw} filtered {f} smoothed {s}");
    }

    #[test]
    fn state_round_trips_exactly() {
        let mut a = KalmanBank::new(PARAMS, 30.0);
        for t in 0..15 {
            a.step(&mut [t as f64, -(t as f64).sqrt()]);
        }
        let mut b = KalmanBank::new(PARAMS, 30.0)
            .with_state(&a.state())
            .unwrap();
        for t in 15..30 {
            let mut za = [t as f64, 1.0];
            let mut zb = za;
            a.step(&mut za);
            b.step(&mut zb);
            assert_eq!(za, zb);
        }
    }
}

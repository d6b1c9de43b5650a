//! Adam over a flat parameter vector, with state that a checkpoint can
//! carry.
//!
//! candle-nn's `AdamW` keeps its moment estimates private, so a checkpoint
//! could not hold them and `--resume` would restart the optimizer cold; and
//! the training network ([`crate::fastnet`]) keeps its parameters in one
//! `Vec<f32>` anyway. This is plain Adam (Kingma & Ba, bias-corrected, no
//! weight decay — what the reference trains with) with optional
//! global-norm gradient clipping.

/// Adam hyper-parameters.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AdamConfig {
    /// Learning rate (the schedule sets it per step).
    pub lr: f64,
    /// First-moment decay.
    pub beta1: f64,
    /// Second-moment decay.
    pub beta2: f64,
    /// Denominator epsilon.
    pub eps: f64,
    /// Clip the global gradient norm to this (`None`: no clipping).
    pub clip_norm: Option<f64>,
}

impl Default for AdamConfig {
    fn default() -> Self {
        Self {
            lr: 1e-4,
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-8,
            clip_norm: Some(5.0),
        }
    }
}

/// Optimizer state: first and second moments and the update count.
#[derive(Debug, Clone, PartialEq)]
pub struct Adam {
    /// Hyper-parameters.
    pub config: AdamConfig,
    /// Learning-rate multipliers for parameter ranges, sorted by start
    /// (the rest: 1). Not optimizer state: rebuilt from the training
    /// config on resume ([`Adam::set_lr_groups`]).
    lr_groups: Vec<(std::ops::Range<usize>, f32)>,
    /// First moments.
    pub m: Vec<f32>,
    /// Second moments.
    pub v: Vec<f32>,
    /// Updates applied so far.
    pub t: u64,
}

impl Adam {
    /// Fresh state for `n` parameters.
    pub fn new(n: usize, config: AdamConfig) -> Self {
        Self {
            config,
            lr_groups: Vec::new(),
            m: vec![0.0; n],
            v: vec![0.0; n],
            t: 0,
        }
    }

    /// Apply one update to `params` from `grad`; returns the global gradient
    /// norm before clipping, or `None` (and changes nothing) when the
    /// gradient is not finite.
    /// Run the parameters in each range at `multiplier` times the rate
    /// (ranges must not overlap).
    pub fn set_lr_groups(&mut self, mut groups: Vec<(std::ops::Range<usize>, f32)>) {
        groups.sort_by_key(|(r, _)| r.start);
        self.lr_groups = groups;
    }

    pub fn step(&mut self, params: &mut [f32], grad: &[f32]) -> Option<f64> {
        assert_eq!(params.len(), self.m.len(), "parameter count changed");
        assert_eq!(grad.len(), self.m.len(), "gradient size mismatch");
        let norm = grad
            .iter()
            .map(|&g| f64::from(g) * f64::from(g))
            .sum::<f64>()
            .sqrt();
        if !norm.is_finite() {
            return None;
        }
        let scale = match self.config.clip_norm {
            Some(c) if norm > c => (c / norm) as f32,
            _ => 1.0,
        };
        self.t += 1;
        let c = self.config;
        let t = self.t as i32;
        let lr_t = (c.lr * (1.0 - c.beta2.powi(t)).sqrt() / (1.0 - c.beta1.powi(t))) as f32;
        let (b1, b2, eps) = (c.beta1 as f32, c.beta2 as f32, c.eps as f32);
        // Ranges between (and around) the groups run at the base rate.
        let Self {
            lr_groups,
            m: m_all,
            v: v_all,
            ..
        } = self;
        let n = params.len();
        let mut update = |range: std::ops::Range<usize>, lr: f32| {
            for i in range {
                let g = grad[i] * scale;
                let m = b1 * m_all[i] + (1.0 - b1) * g;
                let v = b2 * v_all[i] + (1.0 - b2) * g * g;
                m_all[i] = m;
                v_all[i] = v;
                params[i] -= lr * m / (v.sqrt() + eps);
            }
        };
        let mut next = 0;
        for (range, mult) in lr_groups.iter() {
            update(next..range.start, lr_t);
            update(range.clone(), lr_t * mult);
            next = range.end;
        }
        update(next..n, lr_t);
        Some(norm)
    }
}

/// An exponential moving average of the parameters (Polyak averaging):
/// Adam's steps make the weights jitter around a minimum by about the
/// learning rate per weight, which the output layer's 1,024 coherent inputs
/// amplify into millimetres; the average sits near the centre.
#[derive(Debug, Clone, PartialEq)]
pub struct ParamEma {
    /// Weight of the old average per update.
    pub decay: f32,
    /// The averaged parameters.
    pub values: Vec<f32>,
}

impl ParamEma {
    /// Start at `params`.
    pub fn new(params: &[f32], decay: f32) -> Self {
        Self {
            decay,
            values: params.to_vec(),
        }
    }

    /// Fold in the parameters after one optimizer step.
    pub fn update(&mut self, params: &[f32]) {
        assert_eq!(params.len(), self.values.len(), "parameter count changed");
        // `e += (1 - d)(p - e)`: exact when nothing moved.
        let rate = 1.0 - self.decay;
        for (e, &p) in self.values.iter_mut().zip(params) {
            *e += rate * (p - *e);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lr_groups_scale_only_their_range() {
        let grad = vec![1.0f32; 6];
        let mut plain = Adam::new(6, AdamConfig::default());
        let mut grouped = plain.clone();
        grouped.set_lr_groups(vec![(2..4, 0.1)]);
        let mut a = vec![0.0f32; 6];
        let mut b = vec![0.0f32; 6];
        plain.step(&mut a, &grad).unwrap();
        grouped.step(&mut b, &grad).unwrap();
        for i in 0..6 {
            let want = if (2..4).contains(&i) {
                0.1 * a[i]
            } else {
                a[i]
            };
            assert!((b[i] - want).abs() < 1e-9, "param {i}: {} vs {want}", b[i]);
        }
        assert_eq!(plain.m, grouped.m, "moments do not depend on the rate");
    }

    #[test]
    fn ema_tracks_the_average_of_jittering_params() {
        let mut ema = ParamEma::new(&[0.0], 0.99);
        for i in 0..5000 {
            let p = if i % 2 == 0 { 1.0 } else { -1.0 };
            ema.update(&[0.5 + p]);
        }
        assert!((ema.values[0] - 0.5).abs() < 0.02, "{}", ema.values[0]);
    }

    #[test]
    fn minimizes_a_quadratic() {
        let mut x = vec![3.0f32, -2.0];
        let mut opt = Adam::new(
            2,
            AdamConfig {
                lr: 0.1,
                clip_norm: None,
                ..Default::default()
            },
        );
        for _ in 0..300 {
            let g: Vec<f32> = x.iter().map(|v| 2.0 * v).collect();
            opt.step(&mut x, &g).unwrap();
        }
        assert!(x.iter().all(|a| a.abs() < 0.05), "{x:?}");
        assert_eq!(opt.t, 300);
    }

    #[test]
    fn clipping_and_non_finite_gradients() {
        let mut x = vec![0.0f32];
        let mut opt = Adam::new(
            1,
            AdamConfig {
                lr: 1.0,
                clip_norm: Some(1.0),
                ..Default::default()
            },
        );
        let norm = opt.step(&mut x, &[1000.0]).unwrap();
        assert!((norm - 1000.0).abs() < 1e-3);
        assert!((x[0] + 1.0).abs() < 1e-3, "{x:?}");
        assert!(opt.step(&mut x, &[f32::NAN]).is_none());
        assert_eq!(opt.t, 1, "a non-finite gradient is not applied");
    }
}

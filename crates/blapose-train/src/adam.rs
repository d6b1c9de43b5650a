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
            m: vec![0.0; n],
            v: vec![0.0; n],
            t: 0,
        }
    }

    /// Apply one update to `params` from `grad`; returns the global gradient
    /// norm before clipping, or `None` (and changes nothing) when the
    /// gradient is not finite.
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
        for i in 0..params.len() {
            let g = grad[i] * scale;
            let m = b1 * self.m[i] + (1.0 - b1) * g;
            let v = b2 * self.v[i] + (1.0 - b2) * g * g;
            self.m[i] = m;
            self.v[i] = v;
            params[i] -= lr_t * m / (v.sqrt() + eps);
        }
        Some(norm)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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

//! Adam with state that can be saved and restored.
//!
//! candle-nn's `AdamW` keeps its moment estimates private, so a checkpoint
//! could not carry them and `--resume` would restart the optimizer cold.
//! This is plain Adam (Kingma & Ba, bias-corrected, no weight decay — what
//! the reference trains with), with global-norm gradient clipping, over
//! named variables so the state can be written next to the weights.

use std::collections::BTreeMap;

use candle_core::backprop::GradStore;
use candle_core::{Tensor, Var};

use crate::error::TrainError;

/// Adam hyper-parameters.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AdamConfig {
    /// Learning rate (set per step by the schedule).
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
        Self { lr: 1e-4, beta1: 0.9, beta2: 0.999, eps: 1e-8, clip_norm: Some(5.0) }
    }
}

/// The optimizer: named variables and their moment estimates.
pub struct Adam {
    /// Hyper-parameters.
    pub config: AdamConfig,
    vars: Vec<(String, Var)>,
    m: Vec<Tensor>,
    v: Vec<Tensor>,
    t: u64,
}

impl Adam {
    /// An optimizer over `vars` (sorted by name for a stable state layout).
    pub fn new(mut vars: Vec<(String, Var)>, config: AdamConfig) -> Result<Self, TrainError> {
        vars.sort_by(|a, b| a.0.cmp(&b.0));
        let m = vars.iter().map(|(_, v)| v.as_tensor().zeros_like()).collect::<Result<Vec<_>, _>>()?;
        let v = vars.iter().map(|(_, v)| v.as_tensor().zeros_like()).collect::<Result<Vec<_>, _>>()?;
        Ok(Self { config, vars, m, v, t: 0 })
    }

    /// Updates applied so far.
    pub fn steps(&self) -> u64 {
        self.t
    }

    /// Apply one update from `grads`; returns the global gradient norm
    /// before clipping.
    pub fn step(&mut self, grads: &GradStore) -> Result<f64, TrainError> {
        let mut sq = 0.0f64;
        for (_, var) in &self.vars {
            if let Some(g) = grads.get(var.as_tensor()) {
                sq += f64::from(g.sqr()?.sum_all()?.to_scalar::<f32>()?);
            }
        }
        let norm = sq.sqrt();
        if !norm.is_finite() {
            return Err(TrainError::Data(format!("non-finite gradient norm {norm}")));
        }
        let scale = match self.config.clip_norm {
            Some(c) if norm > c => c / norm,
            _ => 1.0,
        };
        self.t += 1;
        let c = self.config;
        let t = self.t as i32;
        let lr_t = c.lr * (1.0 - c.beta2.powi(t)).sqrt() / (1.0 - c.beta1.powi(t));
        for (i, (_, var)) in self.vars.iter().enumerate() {
            let Some(g) = grads.get(var.as_tensor()) else { continue };
            let g = if scale != 1.0 { (g * scale)? } else { g.clone() };
            let m = ((&self.m[i] * c.beta1)? + (&g * (1.0 - c.beta1))?)?;
            let v = ((&self.v[i] * c.beta2)? + (g.sqr()? * (1.0 - c.beta2))?)?;
            let update = (&m / (v.sqrt()? + c.eps)?)?;
            var.set(&var.as_tensor().sub(&(update * lr_t)?)?)?;
            self.m[i] = m;
            self.v[i] = v;
        }
        Ok(norm)
    }

    /// The state as named tensors (`adam.m.<var>`, `adam.v.<var>`) and the
    /// update count.
    pub fn state(&self) -> (BTreeMap<String, Tensor>, u64) {
        let mut out = BTreeMap::new();
        for (i, (name, _)) in self.vars.iter().enumerate() {
            out.insert(format!("adam.m.{name}"), self.m[i].clone());
            out.insert(format!("adam.v.{name}"), self.v[i].clone());
        }
        (out, self.t)
    }

    /// Restore a state written by [`Adam::state`]; every variable's moments
    /// must be present with the right shape.
    pub fn restore(&mut self, tensors: &BTreeMap<String, Tensor>, t: u64) -> Result<(), String> {
        for (i, (name, var)) in self.vars.iter().enumerate() {
            for (key, slot) in [(format!("adam.m.{name}"), &mut self.m[i]), (format!("adam.v.{name}"), &mut self.v[i])] {
                let tensor = tensors.get(&key).ok_or_else(|| format!("missing optimizer tensor {key}"))?;
                if tensor.dims() != var.as_tensor().dims() {
                    return Err(format!("optimizer tensor {key} has shape {:?}", tensor.dims()));
                }
                *slot = tensor.clone();
            }
        }
        self.t = t;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;

    #[test]
    fn minimizes_a_quadratic_and_round_trips_state() {
        let x = Var::from_tensor(&Tensor::new(&[3.0f32, -2.0], &Device::Cpu).unwrap()).unwrap();
        let mut opt = Adam::new(vec![("x".into(), x.clone())], AdamConfig { lr: 0.1, clip_norm: None, ..Default::default() })
            .unwrap();
        for _ in 0..300 {
            let loss = x.as_tensor().sqr().unwrap().sum_all().unwrap();
            opt.step(&loss.backward().unwrap()).unwrap();
        }
        let v: Vec<f32> = x.as_tensor().to_vec1().unwrap();
        assert!(v.iter().all(|a| a.abs() < 0.05), "{v:?}");
        let (state, t) = opt.state();
        assert_eq!(t, 300);
        let mut other = Adam::new(vec![("x".into(), x.clone())], AdamConfig::default()).unwrap();
        other.restore(&state, t).unwrap();
        assert_eq!(other.steps(), 300);
        assert!(other.restore(&BTreeMap::new(), 1).is_err());
    }

    #[test]
    fn clipping_bounds_the_step() {
        let x = Var::from_tensor(&Tensor::new(&[0.0f32], &Device::Cpu).unwrap()).unwrap();
        let mut opt =
            Adam::new(vec![("x".into(), x.clone())], AdamConfig { lr: 1.0, clip_norm: Some(1.0), ..Default::default() })
                .unwrap();
        let loss = (x.as_tensor() * 1000.0).unwrap().sum_all().unwrap();
        let norm = opt.step(&loss.backward().unwrap()).unwrap();
        assert!((norm - 1000.0).abs() < 1e-3);
        // Adam's first step is ~lr in magnitude regardless of scale.
        let v: Vec<f32> = x.as_tensor().to_vec1().unwrap();
        assert!((v[0] + 1.0).abs() < 1e-3, "{v:?}");
    }
}

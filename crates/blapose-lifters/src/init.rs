//! Fast, reproducible random weights for timing and tests.
//!
//! Benchmarks need the reference architectures with *some* weights, and the
//! tests build a 59 M-parameter model: candle's own initializers draw from a
//! thread RNG element by element, which is slow and not reproducible. This
//! backend plugs into `VarBuilder` instead and honours the same [`Init`]
//! hints the constructors pass (PyTorch's defaults: `U(±1/sqrt(fan_in))`
//! for convolutions and linear layers, ones and zeros for normalization
//! layers), drawing from a SplitMix64 stream seeded by the tensor's *name*,
//! so a tensor's values do not depend on construction order.
//!
//! [`RandomInit::perturbed`] also randomizes the constant-initialized
//! tensors (batch-norm statistics, norm scales, positional embeddings)
//! around their defaults, so tests can tell a model that uses them from one
//! that silently ignores them.

use std::collections::HashMap;
use std::sync::{Arc, Mutex, PoisonError};

use candle_core::{DType, Device, Shape, Tensor};
use candle_nn::var_builder::SimpleBackend;
use candle_nn::{Init, VarBuilder};

/// A `VarBuilder` backend that creates every requested tensor from its
/// initialization hint and a seed.
#[derive(Debug, Clone, Copy)]
pub struct RandomInit {
    seed: u64,
    perturb_constants: bool,
}

impl RandomInit {
    /// Weights as PyTorch would initialize them (constants stay constant).
    pub fn new(seed: u64) -> Self {
        Self {
            seed,
            perturb_constants: false,
        }
    }

    /// Like [`RandomInit::new`], but constant hints `c` become
    /// `U(c - 0.25, c + 0.25)`: batch-norm variances stay positive
    /// (`[0.75, 1.25]`), means, biases and embeddings become non-zero.
    pub fn perturbed(seed: u64) -> Self {
        Self {
            seed,
            perturb_constants: true,
        }
    }

    /// A `VarBuilder` over this backend (f32, CPU).
    pub fn var_builder(self) -> VarBuilder<'static> {
        VarBuilder::from_backend(Box::new(self), DType::F32, Device::Cpu)
    }

    fn values(&self, shape: &Shape, name: &str, hint: Init) -> Vec<f32> {
        let n = shape.elem_count();
        let mut rng = SplitMix64::new(self.seed ^ fnv1a(name));
        match hint {
            Init::Const(c) if !self.perturb_constants => vec![c as f32; n],
            Init::Const(c) => (0..n).map(|_| rng.uniform(c - 0.25, c + 0.25)).collect(),
            Init::Uniform { lo, up } => (0..n).map(|_| rng.uniform(lo, up)).collect(),
            Init::Randn { mean, stdev } => (0..n).map(|_| rng.normal(mean, stdev)).collect(),
            Init::Kaiming {
                dist,
                fan,
                non_linearity,
            } => {
                let std = non_linearity.gain() / (fan.for_shape(shape).max(1) as f64).sqrt();
                match dist {
                    candle_nn::init::NormalOrUniform::Uniform => {
                        let b = 3f64.sqrt() * std;
                        (0..n).map(|_| rng.uniform(-b, b)).collect()
                    }
                    candle_nn::init::NormalOrUniform::Normal => {
                        (0..n).map(|_| rng.normal(0.0, std)).collect()
                    }
                }
            }
        }
    }
}

impl SimpleBackend for RandomInit {
    fn get(
        &self,
        s: Shape,
        name: &str,
        h: Init,
        dtype: DType,
        dev: &Device,
    ) -> candle_core::Result<Tensor> {
        let values = self.values(&s, name, h);
        Tensor::from_vec(values, s, &Device::Cpu)?
            .to_dtype(dtype)?
            .to_device(dev)
    }

    fn get_unchecked(&self, name: &str, _: DType, _: &Device) -> candle_core::Result<Tensor> {
        candle_core::bail!("RandomInit cannot create `{name}` without a shape")
    }

    fn contains_tensor(&self, _name: &str) -> bool {
        true
    }
}

/// PyTorch's default initializer for the weight or bias of a layer with
/// `fan_in` inputs: `U(-1/sqrt(fan_in), 1/sqrt(fan_in))`.
pub(crate) fn torch_default(fan_in: usize) -> Init {
    let b = 1.0 / (fan_in.max(1) as f64).sqrt();
    Init::Uniform { lo: -b, up: b }
}

fn fnv1a(s: &str) -> u64 {
    s.bytes().fold(0xcbf2_9ce4_8422_2325, |h, b| {
        (h ^ b as u64).wrapping_mul(0x0100_0000_01b3)
    })
}

/// SplitMix64: tiny, fast and good enough for initial weights.
struct SplitMix64(u64);

impl SplitMix64 {
    fn new(seed: u64) -> Self {
        Self(seed)
    }

    fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    /// Uniform in `[0, 1)` with 53 random bits.
    fn unit(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }

    fn uniform(&mut self, lo: f64, up: f64) -> f32 {
        (lo + (up - lo) * self.unit()) as f32
    }

    /// Box–Muller (one of the pair is discarded; speed is irrelevant here).
    fn normal(&mut self, mean: f64, std: f64) -> f32 {
        let u1 = 1.0 - self.unit();
        let u2 = self.unit();
        (mean + std * (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()) as f32
    }
}

/// Build a model on [`RandomInit::perturbed`] weights and return it with
/// every tensor it asked for, by name (what a weights file of it would
/// hold). For tests, benchmarks and synthetic weights files.
pub fn record_random<M>(
    seed: u64,
    build: impl FnOnce(VarBuilder<'static>) -> crate::Result<M>,
) -> crate::Result<(M, HashMap<String, Tensor>)> {
    let seen = Arc::new(Mutex::new(HashMap::new()));
    let recorder = Recorder {
        inner: RandomInit::perturbed(seed),
        seen: Arc::clone(&seen),
    };
    let model = build(VarBuilder::from_backend(
        Box::new(recorder),
        DType::F32,
        Device::Cpu,
    ))?;
    let tensors = std::mem::take(&mut *seen.lock().unwrap_or_else(PoisonError::into_inner));
    Ok((model, tensors))
}

/// A `VarBuilder` backend that keeps every tensor it hands out.
struct Recorder {
    inner: RandomInit,
    seen: Arc<Mutex<HashMap<String, Tensor>>>,
}

impl SimpleBackend for Recorder {
    fn get(
        &self,
        s: Shape,
        name: &str,
        h: Init,
        dtype: DType,
        dev: &Device,
    ) -> candle_core::Result<Tensor> {
        let t = self.inner.get(s, name, h, dtype, dev)?;
        self.seen
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .insert(name.to_string(), t.clone());
        Ok(t)
    }

    fn get_unchecked(&self, name: &str, dtype: DType, dev: &Device) -> candle_core::Result<Tensor> {
        self.inner.get_unchecked(name, dtype, dev)
    }

    fn contains_tensor(&self, name: &str) -> bool {
        self.inner.contains_tensor(name)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn draw(init: RandomInit, name: &str, hint: Init) -> Vec<f32> {
        init.values(&Shape::from((1000,)), name, hint)
    }

    #[test]
    fn values_follow_hints_and_names() {
        let r = RandomInit::new(1);
        let u = Init::Uniform { lo: -0.5, up: 0.5 };
        let a = draw(r, "a.weight", u);
        assert_eq!(a, draw(r, "a.weight", u), "same name, same values");
        assert_ne!(a, draw(r, "b.weight", u), "names seed the stream");
        assert_ne!(a, draw(RandomInit::new(2), "a.weight", u), "seed matters");
        assert!(a.iter().all(|v| (-0.5..0.5).contains(v)));
        assert!(a.iter().any(|v| *v > 0.4) && a.iter().any(|v| *v < -0.4));
        assert!(draw(r, "bn.running_var", Init::Const(1.0))
            .iter()
            .all(|v| *v == 1.0));
        let p = draw(RandomInit::perturbed(1), "bn.running_var", Init::Const(1.0));
        assert!(p.iter().all(|v| (0.75..1.25).contains(v)));
        assert!(p.iter().any(|v| *v != 1.0));
        let n = draw(
            r,
            "pos",
            Init::Randn {
                mean: 0.0,
                stdev: 2.0,
            },
        );
        let mean = n.iter().sum::<f32>() / n.len() as f32;
        let var = n.iter().map(|v| (v - mean).powi(2)).sum::<f32>() / n.len() as f32;
        assert!(
            mean.abs() < 0.3 && (var.sqrt() - 2.0).abs() < 0.3,
            "mean {mean} var {var}"
        );
    }
}

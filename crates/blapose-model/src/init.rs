//! Initial weights, drawn as PyTorch draws them.
//!
//! Training starts from PyTorch's defaults so that the reference recipe's
//! hyper-parameters (Adam, lr 1e-4) behave as in the paper: `nn.Linear`
//! weights and biases `U(-1/sqrt(fan_in), 1/sqrt(fan_in))`, every `nn.GRU`
//! tensor `U(-1/sqrt(hidden), 1/sqrt(hidden))`. Benchmarks and tests use the
//! same distributions with a fixed seed, so "random weights" have realistic
//! magnitudes.

use std::collections::HashMap;

use candle_core::{Device, Tensor};
use rand::{rngs::StdRng, Rng, SeedableRng};

use crate::names::{tensor_specs, EMBED_BIAS, EMBED_WEIGHT, FC_WEIGHT};
use crate::{ModelError, ModelKind, FEATURES, HIDDEN, INPUT_DIM};

/// Half-width of the uniform distribution PyTorch initializes tensor `name` from.
pub fn uniform_bound(name: &str) -> f64 {
    let fan_in = match name {
        EMBED_WEIGHT | EMBED_BIAS => INPUT_DIM,
        FC_WEIGHT => FEATURES,
        _ => HIDDEN, // every GRU tensor
    };
    1.0 / (fan_in as f64).sqrt()
}

/// candle initializer for tensor `name` (for `VarBuilder::get_with_hints`).
pub fn init_for(name: &str) -> candle_nn::Init {
    let b = uniform_bound(name);
    candle_nn::Init::Uniform { lo: -b, up: b }
}

/// A full set of freshly initialized tensors for `kind`, reproducible from `seed`.
pub fn random_tensors(kind: ModelKind, seed: u64) -> Result<HashMap<String, Tensor>, ModelError> {
    let mut rng = StdRng::seed_from_u64(seed);
    let mut out = HashMap::new();
    for (name, shape) in tensor_specs(kind) {
        let b = uniform_bound(&name) as f32;
        let n: usize = shape.iter().product();
        let data: Vec<f32> = (0..n).map(|_| rng.random_range(-b..b)).collect();
        let t = Tensor::from_vec(data, shape, &Device::Cpu)?;
        out.insert(name, t);
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn random_tensors_respect_bounds_and_seed() {
        let a = random_tensors(ModelKind::Gru, 7).unwrap();
        let b = random_tensors(ModelKind::Gru, 7).unwrap();
        let c = random_tensors(ModelKind::Gru, 8).unwrap();
        let fc = |m: &HashMap<String, Tensor>| -> Vec<f32> {
            m[FC_WEIGHT].flatten_all().unwrap().to_vec1().unwrap()
        };
        assert_eq!(fc(&a), fc(&b));
        assert_ne!(fc(&a), fc(&c));
        let bound = uniform_bound(FC_WEIGHT) as f32;
        assert!(fc(&a).iter().all(|v| v.abs() <= bound));
        assert!(fc(&a).iter().any(|v| v.abs() > 0.5 * bound));
    }
}

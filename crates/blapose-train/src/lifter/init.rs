//! Seeded initial weights and dropout masks shared by the trained lifters.
//!
//! candle's CPU initializers draw from an unseeded generator, so a run
//! would not be a function of its seed; every lifter is therefore built
//! with placeholder values and then re-drawn here from the run's seed.

use candle_core::{Device, Tensor};
use candle_nn::VarMap;
use rand::{Rng, RngCore};
use rand_distr::{Distribution, Normal};

use crate::error::TrainError;
use crate::synth::sample_rng;

/// Seed offset of the initial weights.
const INIT_SEED_SALT: u64 = 0x11F7_E541;
/// The output layer starts at this fraction of its Kaiming scale, so the
/// first predictions are tens of centimetres, not metres: with batch-normed
/// hidden units of unit scale a full-scale output layer starts the MPJPE
/// near 3 m and the first few hundred steps only shrink it.
pub const OUTPUT_INIT_SCALE: f64 = 0.1;

fn lock(
    varmap: &VarMap,
) -> Result<
    std::sync::MutexGuard<'_, std::collections::HashMap<String, candle_core::Var>>,
    TrainError,
> {
    varmap
        .data()
        .lock()
        .map_err(|_| TrainError::InvalidArgument("variable map lock poisoned".into()))
}

/// Re-draw every weight of rank 2 or more in `varmap` (linear `(out, in)`
/// and convolution `(out, in, k)`) from `seed`: Kaiming normal (`std =
/// sqrt(2 / fan_in)`, `fan_in` = the product of all but the first
/// dimension) and the matching `.bias`, if any, `U(-1/sqrt(fan_in),
/// 1/sqrt(fan_in))`. Weights are visited in name order, each with its own
/// generator, so the result does not depend on hash-map order.
/// `output_weight` (the last layer) is then scaled by [`OUTPUT_INIT_SCALE`].
pub fn seed_weights(varmap: &VarMap, seed: u64, output_weight: &str) -> Result<(), TrainError> {
    let data = lock(varmap)?;
    let mut weights: Vec<&String> = data
        .keys()
        .filter(|k| k.ends_with(".weight") && data[*k].as_tensor().rank() >= 2)
        .collect();
    weights.sort();
    for (i, name) in weights.into_iter().enumerate() {
        let w = &data[name];
        let shape = w.as_tensor().shape().clone();
        let out = shape.dims()[0];
        let fan_in = shape.elem_count() / out;
        let mut rng = sample_rng(seed ^ INIT_SEED_SALT, i as u64, 0);
        let normal = Normal::new(0.0f32, (2.0 / fan_in as f32).sqrt())
            .map_err(|e| TrainError::InvalidArgument(e.to_string()))?;
        let scale = if name == output_weight {
            OUTPUT_INIT_SCALE as f32
        } else {
            1.0
        };
        let wv: Vec<f32> = (0..shape.elem_count())
            .map(|_| scale * normal.sample(&mut rng))
            .collect();
        w.set(&Tensor::from_vec(wv, shape, &Device::Cpu)?)?;
        let bias_name = format!("{}.bias", name.trim_end_matches(".weight"));
        if let Some(b) = data.get(&bias_name) {
            let bound = 1.0 / (fan_in as f32).sqrt();
            let bv: Vec<f32> = (0..out).map(|_| rng.random_range(-bound..bound)).collect();
            b.set(&Tensor::from_vec(bv, out, &Device::Cpu)?)?;
        }
    }
    Ok(())
}

/// Build a network on a fresh [`VarMap`] and draw its weights from `seed`
/// ([`seed_weights`], `output_weight` scaled down).
pub fn seeded<M>(
    seed: u64,
    output_weight: &str,
    build: impl FnOnce(candle_nn::VarBuilder) -> Result<M, TrainError>,
) -> Result<(M, VarMap), TrainError> {
    let varmap = VarMap::new();
    let vb = candle_nn::VarBuilder::from_varmap(&varmap, candle_core::DType::F32, &Device::Cpu);
    let model = build(vb)?;
    seed_weights(&varmap, seed, output_weight)?;
    Ok((model, varmap))
}

/// Set the first `rows` entries along dimension 0 of each named variable
/// to zero.
pub fn zero_leading_rows(varmap: &VarMap, names: &[&str], rows: usize) -> Result<(), TrainError> {
    let data = lock(varmap)?;
    for name in names {
        let v = data
            .get(*name)
            .ok_or_else(|| TrainError::InvalidArgument(format!("no variable {name}")))?;
        let t = v.as_tensor();
        let n = t.dim(0)?;
        let kept = t.narrow(0, rows, n - rows)?;
        let zeros = kept.narrow(0, 0, rows)?.zeros_like()?;
        v.set(&Tensor::cat(&[&zeros, &kept], 0)?)?;
    }
    Ok(())
}

/// Inverted dropout with a mask drawn from `rng` (kept units scaled by
/// `1 / (1 - p)`).
pub fn apply_dropout(x: &Tensor, p: f32, rng: &mut dyn RngCore) -> Result<Tensor, TrainError> {
    let keep = 1.0 / (1.0 - p);
    let mask: Vec<f32> = (0..x.elem_count())
        .map(|_| if rng.random::<f32>() < p { 0.0 } else { keep })
        .collect();
    Ok(x.mul(&Tensor::from_vec(mask, x.shape(), x.device())?)?)
}

/// `x` after dropout `p` in training mode (`train` is `Some`: the mask is
/// drawn from its generator, [`apply_dropout`]); `x` itself in evaluation
/// mode or when `p` is 0.
pub fn dropout(
    x: Tensor,
    p: f32,
    train: &mut Option<&mut dyn RngCore>,
) -> Result<Tensor, TrainError> {
    match train {
        Some(rng) if p > 0.0 => apply_dropout(&x, p, &mut **rng),
        _ => Ok(x),
    }
}

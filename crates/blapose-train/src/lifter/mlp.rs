//! The single-frame baseline of Martinez et al. 2017 ("A simple yet
//! effective baseline for 3d human pose estimation"): a residual MLP on one
//! frame's 2D joints.
//!
//! `Linear(34 -> h)`, BatchNorm, ReLU, Dropout, then `blocks` residual
//! blocks of `[Linear(h -> h), BatchNorm, ReLU, Dropout] x 2` with the
//! block input added to its output, then `Linear(h -> 48)`: the 16 non-root
//! joints, root-relative, metres (the root is fixed at the origin, as in the
//! paper, which predicts 16 joints). The paper's size is `h = 1024`,
//! `blocks = 2`, dropout 0.5 (about 4.3 M parameters). Unlike the paper the
//! inputs and targets are not z-scored: the inputs are already normalized
//! screen coordinates in about [-1, 1] and the metre targets are of order
//! one, and a per-coordinate z-score would break the exact mirror symmetry
//! that flip augmentation relies on.
//!
//! Built in candle-nn on a [`VarMap`] so candle autograd trains it. The
//! initial weights are drawn from a seeded generator ([`MlpLifter::init`]:
//! Kaiming-normal weights, PyTorch-default uniform biases, the output layer
//! scaled by [`OUTPUT_INIT_SCALE`]), not from
//! candle's unseeded CPU generator, and dropout masks come from the caller's
//! generator, so a run is a function of its seed.

use blapose_core::Keypoints2d;
use candle_core::{DType, Device, Tensor};
use candle_nn::{BatchNorm, Linear, Module, ModuleT, VarBuilder, VarMap};
use rand::{Rng, RngCore};
use rand_distr::{Distribution, Normal};
use serde::{Deserialize, Serialize};

use super::{LifterKind, LifterNet, OUTPUT_DIM};
use crate::error::TrainError;
use crate::synth::{sample_rng, FRAME_DIM};

/// Seed offset of the initial weights.
const INIT_SEED_SALT: u64 = 0x11F7_E541;
/// The output layer starts at this fraction of its Kaiming scale, so the
/// first predictions are tens of centimetres, not metres: with batch-normed
/// hidden units of unit scale a full-scale output layer starts the MPJPE
/// near 3 m and the first few hundred steps only shrink it.
pub const OUTPUT_INIT_SCALE: f64 = 0.1;

/// Size of the MLP.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct MlpConfig {
    /// Hidden width.
    pub hidden: usize,
    /// Residual blocks.
    pub blocks: usize,
    /// Dropout probability (training only).
    pub dropout: f32,
}

impl Default for MlpConfig {
    /// The paper's size.
    fn default() -> Self {
        Self {
            hidden: 1024,
            blocks: 2,
            dropout: 0.5,
        }
    }
}

/// Linear + batch norm (+ ReLU + dropout in `forward`).
struct Layer {
    linear: Linear,
    bn: BatchNorm,
}

impl Layer {
    fn new(input: usize, output: usize, vb: VarBuilder) -> Result<Self, TrainError> {
        Ok(Self {
            linear: candle_nn::linear(input, output, vb.pp("linear"))?,
            bn: candle_nn::batch_norm(output, candle_nn::BatchNormConfig::default(), vb.pp("bn"))?,
        })
    }

    fn forward(
        &self,
        x: &Tensor,
        dropout: f32,
        train: &mut Option<&mut dyn RngCore>,
    ) -> Result<Tensor, TrainError> {
        let y = self.linear.forward(x)?;
        let y = self.bn.forward_t(&y, train.is_some())?.relu()?;
        match train {
            Some(rng) if dropout > 0.0 => apply_dropout(&y, dropout, &mut **rng),
            _ => Ok(y),
        }
    }
}

/// Inverted dropout with a mask drawn from `rng` (kept units scaled by
/// `1 / (1 - p)`).
fn apply_dropout(x: &Tensor, p: f32, rng: &mut dyn RngCore) -> Result<Tensor, TrainError> {
    let keep = 1.0 / (1.0 - p);
    let mask: Vec<f32> = (0..x.elem_count())
        .map(|_| if rng.random::<f32>() < p { 0.0 } else { keep })
        .collect();
    Ok(x.mul(&Tensor::from_vec(mask, x.shape(), x.device())?)?)
}

/// The residual MLP lifter.
pub struct MlpLifter {
    config: MlpConfig,
    input: Layer,
    blocks: Vec<[Layer; 2]>,
    output: Linear,
}

impl MlpLifter {
    /// Build on `vb` (tensor names `input.*`, `blocks.{i}.{0,1}.*`,
    /// `output.*`).
    pub fn new(config: MlpConfig, vb: VarBuilder) -> Result<Self, TrainError> {
        if config.hidden == 0 || !(0.0..1.0).contains(&config.dropout) {
            return Err(TrainError::InvalidArgument(format!(
                "MLP needs hidden > 0 and dropout in [0, 1), got {config:?}"
            )));
        }
        let h = config.hidden;
        let input = Layer::new(FRAME_DIM, h, vb.pp("input"))?;
        let blocks = (0..config.blocks)
            .map(|i| {
                let vb = vb.pp(format!("blocks.{i}"));
                Ok([Layer::new(h, h, vb.pp("0"))?, Layer::new(h, h, vb.pp("1"))?])
            })
            .collect::<Result<_, TrainError>>()?;
        let output = candle_nn::linear(h, OUTPUT_DIM, vb.pp("output"))?;
        Ok(Self {
            config,
            input,
            blocks,
            output,
        })
    }

    /// A fresh model in a new [`VarMap`], initialized from `seed`.
    pub fn init(config: MlpConfig, seed: u64) -> Result<(Self, VarMap), TrainError> {
        let varmap = VarMap::new();
        let vb = VarBuilder::from_varmap(&varmap, DType::F32, &Device::Cpu);
        let model = Self::new(config, vb)?;
        seed_linear_layers(&varmap, seed)?;
        if let Some(w) = varmap
            .data()
            .lock()
            .map_err(|_| TrainError::InvalidArgument("variable map lock poisoned".into()))?
            .get("output.weight")
        {
            w.set(&(w.as_tensor() * OUTPUT_INIT_SCALE)?)?;
        }
        Ok((model, varmap))
    }

    /// The size.
    pub fn config(&self) -> MlpConfig {
        self.config
    }

    /// Lift single frames (evaluation mode), for callers without tensors.
    pub fn lift(&self, frames: &[Keypoints2d]) -> Result<Vec<blapose_core::Pose>, TrainError> {
        let flat: Vec<f32> = frames.iter().flatten().flatten().copied().collect();
        let x = Tensor::from_vec(flat, (frames.len(), FRAME_DIM), &Device::Cpu)?;
        let y = self.forward(&x, None)?.flatten_all()?.to_vec1::<f32>()?;
        Ok(super::data::outputs_to_poses(&y))
    }
}

/// Re-draw every linear layer of `varmap` from `seed`: weights Kaiming
/// normal (`std = sqrt(2 / fan_in)`), biases `U(-1/sqrt(fan_in),
/// 1/sqrt(fan_in))`. Layers are visited in name order, each with its own
/// generator, so the result does not depend on hash-map order.
fn seed_linear_layers(varmap: &VarMap, seed: u64) -> Result<(), TrainError> {
    let data = varmap
        .data()
        .lock()
        .map_err(|_| TrainError::InvalidArgument("variable map lock poisoned".into()))?;
    let mut weights: Vec<&String> = data
        .keys()
        .filter(|k| k.ends_with(".weight") && data[*k].as_tensor().rank() == 2)
        .collect();
    weights.sort();
    for (i, name) in weights.into_iter().enumerate() {
        let w = &data[name];
        let (out, fan_in) = w.as_tensor().dims2()?;
        let mut rng = sample_rng(seed ^ INIT_SEED_SALT, i as u64, 0);
        let normal = Normal::new(0.0f32, (2.0 / fan_in as f32).sqrt())
            .map_err(|e| TrainError::InvalidArgument(e.to_string()))?;
        let wv: Vec<f32> = (0..out * fan_in).map(|_| normal.sample(&mut rng)).collect();
        w.set(&Tensor::from_vec(wv, (out, fan_in), &Device::Cpu)?)?;
        let bias_name = format!("{}.bias", name.trim_end_matches(".weight"));
        if let Some(b) = data.get(&bias_name) {
            let bound = 1.0 / (fan_in as f32).sqrt();
            let bv: Vec<f32> = (0..out).map(|_| rng.random_range(-bound..bound)).collect();
            b.set(&Tensor::from_vec(bv, out, &Device::Cpu)?)?;
        }
    }
    Ok(())
}

impl LifterNet for MlpLifter {
    fn kind(&self) -> LifterKind {
        LifterKind::Mlp
    }

    fn receptive_field(&self) -> usize {
        1
    }

    fn forward(
        &self,
        x: &Tensor,
        mut train: Option<&mut dyn RngCore>,
    ) -> Result<Tensor, TrainError> {
        let p = self.config.dropout;
        let mut h = self.input.forward(x, p, &mut train)?;
        for [a, b] in &self.blocks {
            let y = a.forward(&h, p, &mut train)?;
            let y = b.forward(&y, p, &mut train)?;
            h = (h + y)?;
        }
        Ok(self.output.forward(&h)?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn paper_size_and_seeded_init() {
        let (m, vars) = MlpLifter::init(MlpConfig::default(), 7).unwrap();
        let trainable: usize = vars
            .data()
            .lock()
            .unwrap()
            .iter()
            .filter(|(k, _)| !k.contains("running_"))
            .map(|(_, v)| v.as_tensor().elem_count())
            .sum();
        // 34*1024+1024 + 4*(1024*1024+1024) + 1024*48+48 + 5*2*1024 (BN).
        assert_eq!(trainable, 4_293_680);
        let x = Tensor::ones((3, FRAME_DIM), DType::F32, &Device::Cpu).unwrap();
        let a = m.forward(&x, None).unwrap().to_vec2::<f32>().unwrap();
        let (m2, _) = MlpLifter::init(MlpConfig::default(), 7).unwrap();
        let b = m2.forward(&x, None).unwrap().to_vec2::<f32>().unwrap();
        assert_eq!(a, b, "same seed, same network");
        let (m3, _) = MlpLifter::init(MlpConfig::default(), 8).unwrap();
        let c = m3.forward(&x, None).unwrap().to_vec2::<f32>().unwrap();
        assert_ne!(a, c);
        assert_eq!(a[0].len(), OUTPUT_DIM);
    }
}

//! The single-frame baseline of Martinez et al. 2017 ("A simple yet
//! effective baseline for 3d human pose estimation"): a residual MLP on one
//! frame's 2D joints, trained here as the paper's single-frame lifter to
//! measure the adjustment on.
//!
//! `Linear(34 -> h)`, BatchNorm, ReLU, Dropout, then `blocks` residual
//! blocks of `[Linear(h -> h), BatchNorm, ReLU, Dropout] x 2` with the
//! block input added to its output, then `Linear(h -> 48)`: the 16 non-root
//! joints, root-relative, metres (the root is fixed at the origin, as in the
//! paper, which predicts 16 joints). Its size is an [`MlpArch`]; the
//! paper's, the default, is `h = 1024`, `blocks = 2`, dropout 0.5 (about
//! 4.3 M parameters). Unlike the paper the inputs and targets are not
//! z-scored: the inputs are already normalized screen coordinates in about
//! [-1, 1] and the metre targets are of order one, and a per-coordinate
//! z-score would break the exact mirror symmetry that flip augmentation
//! relies on.
//!
//! Built in candle-nn on a [`VarMap`] so candle autograd trains it. The
//! initial weights are drawn from a seeded generator ([`MlpLifter::init`]:
//! Kaiming-normal weights, PyTorch-default uniform biases, the output layer
//! scaled by [`super::init::OUTPUT_INIT_SCALE`]), not from
//! candle's unseeded CPU generator, and dropout masks come from the caller's
//! generator, so a run is a function of its seed.

use blapose_core::Keypoints2d;
use candle_core::{Device, Tensor};
use candle_nn::{BatchNorm, Linear, Module, ModuleT, VarBuilder, VarMap};
use rand::RngCore;

use super::data::Window;
use super::init::seeded;
use super::{LifterKind, LifterNet, MlpArch, OUTPUT_DIM};
use crate::error::TrainError;
use crate::synth::FRAME_DIM;

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
        super::init::dropout(y, dropout, train)
    }
}

/// The residual MLP lifter.
pub struct MlpLifter {
    config: MlpArch,
    input: Layer,
    blocks: Vec<[Layer; 2]>,
    output: Linear,
}

impl MlpLifter {
    /// Build on `vb` (tensor names `input.*`, `blocks.{i}.{0,1}.*`,
    /// `output.*`).
    pub fn new(config: MlpArch, vb: VarBuilder) -> Result<Self, TrainError> {
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
    pub fn init(config: MlpArch, seed: u64) -> Result<(Self, VarMap), TrainError> {
        seeded(seed, "output.weight", |vb| Self::new(config, vb))
    }

    /// The size.
    pub fn config(&self) -> MlpArch {
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

impl LifterNet for MlpLifter {
    fn kind(&self) -> LifterKind {
        LifterKind::Mlp
    }

    fn window(&self) -> Window {
        Window::SINGLE_FRAME
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
    use candle_core::DType;

    #[test]
    fn paper_size_and_seeded_init() {
        let (m, vars) = MlpLifter::init(MlpArch::default(), 7).unwrap();
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
        let (m2, _) = MlpLifter::init(MlpArch::default(), 7).unwrap();
        let b = m2.forward(&x, None).unwrap().to_vec2::<f32>().unwrap();
        assert_eq!(a, b, "same seed, same network");
        let (m3, _) = MlpLifter::init(MlpArch::default(), 8).unwrap();
        let c = m3.forward(&x, None).unwrap().to_vec2::<f32>().unwrap();
        assert_ne!(a, c);
        assert_eq!(a[0].len(), OUTPUT_DIM);
    }
}

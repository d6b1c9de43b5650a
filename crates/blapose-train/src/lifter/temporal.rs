//! A VideoPose3D-style temporal lifter (Pavllo et al., CVPR 2019) that this
//! crate trains: dilated temporal convolutions over a window of 2D frames,
//! trained — as the reference does — in the *optimized single-frame* form
//! (every convolution with stride = its width on exactly one receptive
//! field, one output frame per window).
//!
//! Why not reuse `blapose_lifters::VideoPose3d`: that one is inference only
//! (batch norm folded into packed weights, no autograd). This module builds
//! the same network in candle-nn on a [`VarMap`] under the reference tensor
//! names (`expand_conv`, `expand_bn`, `layers_conv.{i}`, `layers_bn.{i}`,
//! `shrink`) and shapes (`Conv1d` weights `(out, in, k)`), so a weights file
//! written here loads unchanged into `blapose_lifters::VideoPose3d` — the
//! fast online path the server runs ([`VideoPoseArch::config`]; a test
//! checks both give the same poses). Its size is the [`VideoPoseArch`] the
//! weights file records.
//!
//! The reference predicts all 17 joints and is trained towards a pelvis at
//! the origin; here the three pelvis rows of `shrink` start at zero and,
//! being cut from the output before the loss, never receive a gradient, so
//! they stay zero and the pelvis is exactly 0 in both implementations.
//!
//! The *causal* variant aligns each residual with the last tap of its
//! window, so the output belongs to the window's last frame and depends on
//! past frames only — the variant for online use.

use candle_core::Tensor;
use candle_nn::{BatchNorm, ModuleT, VarBuilder, VarMap};
use rand::RngCore;

use super::data::Window;
use super::init::{seeded, zero_leading_rows};
use super::{LifterKind, LifterNet, VideoPoseArch, OUTPUT_DIM};
use crate::error::TrainError;
use crate::synth::FRAME_DIM;

/// Outputs of `shrink`: all 17 joints, as in the reference.
const SHRINK_OUTPUTS: usize = OUTPUT_DIM + 3;

/// Largest receptive field trained here (frames).
const MAX_RECEPTIVE_FIELD: usize = 729;

/// The input window of `arch` if this crate can train it: an odd filter
/// width, channels, dropout in `[0, 1)` and at most
/// [`MAX_RECEPTIVE_FIELD`] frames.
pub fn window(arch: &VideoPoseArch) -> Result<Window, TrainError> {
    let frames = arch
        .receptive_field()
        .filter(|&rf| rf <= MAX_RECEPTIVE_FIELD);
    match frames {
        Some(frames)
            if arch.filter_width % 2 == 1
                && arch.channels > 0
                && (0.0..1.0).contains(&arch.dropout) =>
        {
            Ok(Window {
                frames,
                causal: arch.causal,
            })
        }
        _ => Err(TrainError::InvalidArgument(format!(
            "temporal lifter needs an odd filter width, channels > 0, dropout in [0, 1) and \
             a receptive field of at most {MAX_RECEPTIVE_FIELD} frames; got {arch:?}"
        ))),
    }
}

/// A temporal convolution as a trainable `(out, in, k)` weight, applied in
/// the strided form on time-major `(B, T, in)` tensors.
struct StridedConv {
    weight: Tensor,
    kernel: usize,
}

impl StridedConv {
    fn new(c_in: usize, c_out: usize, kernel: usize, vb: VarBuilder) -> Result<Self, TrainError> {
        let weight = vb.get_with_hints((c_out, c_in, kernel), "weight", candle_nn::init::ZERO)?;
        Ok(Self { weight, kernel })
    }

    /// `(B, T, in)` -> `(B, T / k, out)`: `(B, T, in)` reshaped to
    /// `(B·T/k, k·in)` is the im2col matrix of a stride-`k` convolution;
    /// the weight is laid out to match (row `j·in + c` = tap `j`, channel `c`).
    fn forward(&self, x: &Tensor) -> Result<Tensor, TrainError> {
        let (b, t, c_in) = x.dims3()?;
        let (c_out, _, k) = self.weight.dims3()?;
        let n = t / self.kernel;
        let cols = x.contiguous()?.reshape((b * n, k * c_in))?;
        let w = self.weight.permute((2, 1, 0))?.reshape((k * c_in, c_out))?;
        Ok(cols.matmul(&w)?.reshape((b, n, c_out))?)
    }
}

/// Convolution, batch norm, ReLU, dropout.
struct ConvLayer {
    conv: StridedConv,
    bn: BatchNorm,
}

impl ConvLayer {
    fn new(
        c_in: usize,
        c_out: usize,
        kernel: usize,
        conv_vb: VarBuilder,
        bn_vb: VarBuilder,
    ) -> Result<Self, TrainError> {
        Ok(Self {
            conv: StridedConv::new(c_in, c_out, kernel, conv_vb)?,
            bn: candle_nn::batch_norm(c_out, candle_nn::BatchNormConfig::default(), bn_vb)?,
        })
    }

    fn forward(
        &self,
        x: &Tensor,
        dropout: f32,
        train: &mut Option<&mut dyn RngCore>,
    ) -> Result<Tensor, TrainError> {
        let y = self.conv.forward(x)?;
        let (b, n, c) = y.dims3()?;
        // Batch norm over channels, statistics over batch and time, as
        // PyTorch's BatchNorm1d on (B, C, T).
        let y = self
            .bn
            .forward_t(&y.reshape((b * n, c))?, train.is_some())?
            .relu()?
            .reshape((b, n, c))?;
        super::init::dropout(y, dropout, train)
    }
}

/// The temporal lifter.
pub struct TemporalLifter {
    config: VideoPoseArch,
    window: Window,
    expand: ConvLayer,
    /// `(wide, pointwise)` per residual block.
    blocks: Vec<(ConvLayer, ConvLayer)>,
    shrink_weight: Tensor,
    shrink_bias: Tensor,
}

impl TemporalLifter {
    /// Build on `vb` under the reference names.
    pub fn new(config: VideoPoseArch, vb: VarBuilder) -> Result<Self, TrainError> {
        let window = window(&config)?;
        let (c, w) = (config.channels, config.filter_width);
        let expand = ConvLayer::new(FRAME_DIM, c, w, vb.pp("expand_conv"), vb.pp("expand_bn"))?;
        let (convs, bns) = (vb.pp("layers_conv"), vb.pp("layers_bn"));
        let blocks = (0..config.blocks)
            .map(|i| {
                let wide = ConvLayer::new(c, c, w, convs.pp(2 * i), bns.pp(2 * i))?;
                let point = ConvLayer::new(c, c, 1, convs.pp(2 * i + 1), bns.pp(2 * i + 1))?;
                Ok((wide, point))
            })
            .collect::<Result<_, TrainError>>()?;
        let shrink = vb.pp("shrink");
        let shrink_weight =
            shrink.get_with_hints((SHRINK_OUTPUTS, c, 1), "weight", candle_nn::init::ZERO)?;
        let shrink_bias = shrink.get_with_hints(SHRINK_OUTPUTS, "bias", candle_nn::init::ZERO)?;
        Ok(Self {
            config,
            window,
            expand,
            blocks,
            shrink_weight,
            shrink_bias,
        })
    }

    /// A fresh model in a new [`VarMap`], initialized from `seed` (as the
    /// MLP: Kaiming-normal weights, the output layer scaled down) with the
    /// pelvis rows of `shrink` at zero.
    pub fn init(config: VideoPoseArch, seed: u64) -> Result<(Self, VarMap), TrainError> {
        let (model, varmap) = seeded(seed, "shrink.weight", |vb| Self::new(config, vb))?;
        zero_leading_rows(&varmap, &["shrink.weight", "shrink.bias"], 3)?;
        Ok((model, varmap))
    }

    /// The size.
    pub fn config(&self) -> VideoPoseArch {
        self.config
    }
}

impl LifterNet for TemporalLifter {
    fn kind(&self) -> LifterKind {
        LifterKind::VideoPose
    }

    fn window(&self) -> Window {
        self.window
    }

    fn forward(
        &self,
        x: &Tensor,
        mut train: Option<&mut dyn RngCore>,
    ) -> Result<Tensor, TrainError> {
        let (b, width) = x.dims2()?;
        let rf = self.window.frames;
        if width != rf * FRAME_DIM {
            return Err(TrainError::InvalidArgument(format!(
                "temporal lifter input has {width} values per row, needs {rf} frames x {FRAME_DIM}"
            )));
        }
        let (p, w) = (self.config.dropout, self.config.filter_width);
        let tap = if self.config.causal { w - 1 } else { w / 2 };
        let mut h = self
            .expand
            .forward(&x.reshape((b, rf, FRAME_DIM))?, p, &mut train)?;
        for (wide, point) in &self.blocks {
            let (_, n, c) = h.dims3()?;
            let residual =
                h.reshape((b, n / w, w, c))?
                    .narrow(2, tap, 1)?
                    .reshape((b, n / w, c))?;
            let y = wide.forward(&h, p, &mut train)?;
            h = (residual + point.forward(&y, p, &mut train)?)?;
        }
        let c = self.config.channels;
        let out = h
            .reshape((b, c))?
            .matmul(&self.shrink_weight.reshape((SHRINK_OUTPUTS, c))?.t()?)?
            .broadcast_add(&self.shrink_bias)?;
        Ok(out.narrow(1, 3, OUTPUT_DIM)?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lifter::weights::named_tensors;
    use candle_core::{DType, Device};

    fn tensors_count(vars: &VarMap) -> usize {
        named_tensors(vars)
            .unwrap()
            .iter()
            .filter(|(k, _)| !k.contains("running_"))
            .map(|(_, v)| v.elem_count())
            .sum()
    }

    fn small(causal: bool) -> VideoPoseArch {
        VideoPoseArch {
            filter_width: 3,
            blocks: 2,
            channels: 16,
            dropout: 0.25,
            causal,
        }
    }

    #[test]
    fn reference_names_sizes_and_seeded_init() {
        let (m, vars) = TemporalLifter::init(VideoPoseArch::default(), 3).unwrap();
        assert_eq!(m.window().frames, 27);
        let t = named_tensors(&vars).unwrap();
        assert_eq!(t["expand_conv.weight"].dims(), &[512, 34, 3]);
        assert_eq!(t["layers_conv.3.weight"].dims(), &[512, 512, 1]);
        assert_eq!(t["shrink.weight"].dims(), &[51, 512, 1]);
        let trainable = tensors_count(&vars);
        // 512*34*3 + 2*(512*512*3 + 512*512) + 51*512 + 51 + 5*2*512 (BN).
        assert_eq!(trainable, 2_180_659);
        let x = Tensor::ones((2, 27 * FRAME_DIM), DType::F32, &Device::Cpu).unwrap();
        let a = m.forward(&x, None).unwrap().to_vec2::<f32>().unwrap();
        let (m2, _) = TemporalLifter::init(VideoPoseArch::default(), 3).unwrap();
        assert_eq!(a, m2.forward(&x, None).unwrap().to_vec2::<f32>().unwrap());
        assert_eq!(a[0].len(), OUTPUT_DIM);
        let pelvis = t["shrink.weight"].narrow(0, 0, 3).unwrap();
        assert_eq!(
            pelvis
                .abs()
                .unwrap()
                .sum_all()
                .unwrap()
                .to_scalar::<f32>()
                .unwrap(),
            0.0
        );
    }

    /// The trained network and the inference crate's VideoPose3D built
    /// from the same tensors give the same poses, centred and causal, with
    /// non-trivial batch-norm statistics.
    #[test]
    fn matches_the_inference_crate() {
        for causal in [false, true] {
            let (m, vars) = TemporalLifter::init(small(causal), 9).unwrap();
            let rf = m.window().frames;
            let x: Vec<f32> = (0..4 * rf * FRAME_DIM)
                .map(|i| (i as f32 * 0.37).sin())
                .collect();
            let x = Tensor::from_vec(x, (4, rf * FRAME_DIM), &Device::Cpu).unwrap();
            let mut rng = crate::synth::sample_rng(1, 2, 3);
            m.forward(&x, Some(&mut rng)).unwrap(); // updates the running statistics
            let ours = m.forward(&x, None).unwrap().to_vec2::<f32>().unwrap();

            let tensors: std::collections::HashMap<String, Tensor> =
                named_tensors(&vars).unwrap().into_iter().collect();
            let vb = VarBuilder::from_tensors(tensors, DType::F32, &Device::Cpu);
            let reference = blapose_lifters::VideoPose3d::new(m.config().config(), vb).unwrap();
            let trainable: usize = tensors_count(&vars);
            assert_eq!(blapose_lifters::Lifter::params(&reference), trainable);
            let theirs = reference
                .forward_window(&x.reshape((4, rf, 17, 2)).unwrap())
                .unwrap()
                .reshape((4, 51))
                .unwrap()
                .to_vec2::<f32>()
                .unwrap();
            for (a, b) in ours.iter().zip(&theirs) {
                assert_eq!(&b[..3], &[0.0; 3], "pelvis at the origin");
                for (u, v) in a.iter().zip(&b[3..]) {
                    assert!((u - v).abs() < 1e-4, "causal={causal}: {u} vs {v}");
                }
            }
        }
    }

    #[test]
    fn rejects_bad_sizes() {
        let mut c = small(false);
        c.filter_width = 2;
        assert!(TemporalLifter::init(c, 0).is_err());
        let (m, _) = TemporalLifter::init(small(false), 0).unwrap();
        let x = Tensor::ones((2, 5 * FRAME_DIM), DType::F32, &Device::Cpu).unwrap();
        assert!(m.forward(&x, None).is_err());
    }
}

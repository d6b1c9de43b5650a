//! The inference building blocks the three lifters share.
//!
//! Everything runs in a *time-major* layout `(B, T, C)`: a temporal
//! convolution then becomes one matrix product over gathered time steps,
//! and the strided "single-frame" form (stride = kernel width) needs no
//! gather at all — `(B, T, C)` reshaped to `(B, T/k, k·C)` *is* the im2col
//! matrix. Batch norm is folded into the preceding convolution or linear
//! layer when the model is built (inference only, so the running
//! statistics are constants), which leaves one product and one bias add per
//! layer.
//!
//! Weights are loaded under the reference PyTorch names (`weight`, `bias`,
//! `running_mean`, `running_var`) and shapes (`Conv1d`: `(out, in, k)`,
//! `Linear`: `(out, in)`), so converted checkpoints load unchanged.

use candle_core::{DType, Storage, Tensor, D};

use crate::error::{LifterError, Result};
use crate::init::torch_default;
use crate::kernel::PackedMatrix;
use crate::params::ParamLoader;

/// PyTorch's default `BatchNorm1d` epsilon.
pub(crate) const BN_EPS: f64 = 1e-5;

/// Raw weights of a PyTorch `Conv1d` (`weight`: `(out, in, k)`) or
/// `Linear` (`weight`: `(out, in)`, i.e. `k = 1` without the last axis).
pub(crate) struct RawAffine {
    weight: Tensor,
    bias: Option<Tensor>,
}

impl RawAffine {
    /// Load `Conv1d(c_in, c_out, k, bias)` under `l`.
    pub(crate) fn conv1d(
        l: &ParamLoader,
        c_in: usize,
        c_out: usize,
        k: usize,
        bias: bool,
    ) -> Result<Self> {
        let init = torch_default(c_in * k);
        let weight = l.param(&[c_out, c_in, k], "weight", init)?;
        let bias = if bias {
            Some(l.param(&[c_out], "bias", init)?)
        } else {
            None
        };
        Ok(Self { weight, bias })
    }

    /// Load `Linear(c_in, c_out, bias)` under `l`.
    pub(crate) fn linear(l: &ParamLoader, c_in: usize, c_out: usize, bias: bool) -> Result<Self> {
        let init = torch_default(c_in);
        let weight = l.param(&[c_out, c_in], "weight", init)?;
        let bias = if bias {
            Some(l.param(&[c_out], "bias", init)?)
        } else {
            None
        };
        Ok(Self {
            weight: weight.unsqueeze(2)?,
            bias,
        })
    }

    /// Fold a following batch norm into the weights.
    pub(crate) fn with_bn(self, bn: &BatchNorm) -> Result<Self> {
        let scale = bn.scale.reshape(((), 1, 1))?;
        let weight = self.weight.broadcast_mul(&scale)?;
        let bias = match &self.bias {
            Some(b) => b.mul(&bn.scale)?.add(&bn.shift)?,
            None => bn.shift.clone(),
        };
        Ok(Self {
            weight,
            bias: Some(bias),
        })
    }

    /// Build the temporal convolution this layer is.
    pub(crate) fn into_conv(self) -> Result<TemporalConv> {
        let (c_out, c_in, k) = self.weight.dims3()?;
        // (out, in, k) -> (k, in, out) -> (k·in, out): row `j·in + c` holds
        // tap `j` of input channel `c`, matching the time-major im2col.
        let w = self
            .weight
            .permute((2, 1, 0))?
            .flatten_all()?
            .to_vec1::<f32>()?;
        let b = match self.bias {
            Some(b) => Some(b.to_dtype(DType::F32)?.to_vec1::<f32>()?),
            None => None,
        };
        let w = PackedMatrix::new(&w, k * c_in, c_out);
        Ok(TemporalConv {
            kernel: k,
            dense: Dense { w, b },
        })
    }

    /// Build the dense layer this (kernel-1) layer is.
    pub(crate) fn into_dense(self) -> Result<Dense> {
        Ok(self.into_conv()?.dense)
    }
}

/// An inference-mode batch norm as `y = x * scale + shift`.
pub(crate) struct BatchNorm {
    scale: Tensor,
    shift: Tensor,
}

impl BatchNorm {
    /// Load `BatchNorm1d(c)` under `l` (weight and bias are parameters,
    /// the running statistics buffers).
    pub(crate) fn load(l: &ParamLoader, c: usize) -> Result<Self> {
        let gamma = l.param(&[c], "weight", candle_nn::init::ONE)?;
        let beta = l.param(&[c], "bias", candle_nn::init::ZERO)?;
        let mean = l.buffer(&[c], "running_mean", candle_nn::init::ZERO)?;
        let var = l.buffer(&[c], "running_var", candle_nn::init::ONE)?;
        let scale = gamma.div(&var.affine(1.0, BN_EPS)?.sqrt()?)?;
        let shift = beta.sub(&mean.mul(&scale)?)?;
        Ok(Self { scale, shift })
    }
}

/// `y = x W + b` over the last dimension, `W` packed for [`PackedMatrix`].
#[derive(Debug, Clone)]
pub(crate) struct Dense {
    w: PackedMatrix,
    b: Option<Vec<f32>>,
}

impl Dense {
    pub(crate) fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let (k, n) = (self.w.k(), self.w.n());
        let mut dims = x.dims().to_vec();
        if dims.last() != Some(&k) {
            return Err(LifterError::Shape {
                what: "dense input",
                expected: format!("(..., {k})"),
                got: dims,
            });
        }
        let x = x.to_dtype(DType::F32)?.contiguous()?;
        let y = {
            let (storage, layout) = x.storage_and_layout();
            let Storage::Cpu(cpu) = &*storage else {
                return Err(LifterError::Config(
                    "the lifters run on the CPU only".into(),
                ));
            };
            let start = layout.start_offset();
            let values = &cpu.as_slice::<f32>()?[start..start + x.elem_count()];
            self.w.matmul(values, self.b.as_deref())
        };
        if let Some(last) = dims.last_mut() {
            *last = n;
        }
        Ok(Tensor::from_vec(y, dims, x.device())?)
    }
}

/// A 1-D convolution over time on `(B, T, C)` tensors.
#[derive(Debug, Clone)]
pub(crate) struct TemporalConv {
    kernel: usize,
    dense: Dense,
}

impl TemporalConv {
    /// The convolution with stride = kernel width (and dilation 1): the
    /// "optimized single-frame" form. `T` must be a multiple of the kernel.
    pub(crate) fn strided(&self, x: &Tensor) -> Result<Tensor> {
        let (b, t, c) = x.dims3()?;
        if t % self.kernel != 0 {
            return Err(LifterError::Config(format!(
                "strided conv: {t} frames is not a multiple of the kernel {}",
                self.kernel
            )));
        }
        let cols = x
            .contiguous()?
            .reshape((b, t / self.kernel, self.kernel * c))?;
        self.dense.forward(&cols)
    }

    /// The convolution with stride 1 and `dilation`, no padding:
    /// `T - (k-1)·dilation` output frames.
    pub(crate) fn dilated(&self, x: &Tensor, dilation: usize) -> Result<Tensor> {
        let t = x.dim(1)?;
        let span = (self.kernel - 1) * dilation;
        if t <= span {
            return Err(LifterError::Config(format!(
                "dilated conv: {t} frames do not cover the span {}",
                span + 1
            )));
        }
        let out = t - span;
        if self.kernel == 1 {
            return self.dense.forward(x);
        }
        let taps: Vec<Tensor> = (0..self.kernel)
            .map(|j| x.narrow(1, j * dilation, out))
            .collect::<candle_core::Result<_>>()?;
        self.dense.forward(&Tensor::cat(&taps, D::Minus1)?)
    }
}

/// Frames `offset, offset + k, offset + 2k, ...` of a `(B, T, C)` tensor
/// (`T` a multiple of `k`): the residual that survives a strided layer.
pub(crate) fn every_kth(x: &Tensor, k: usize, offset: usize) -> Result<Tensor> {
    let (b, t, c) = x.dims3()?;
    Ok(x.reshape((b, t / k, k, c))?
        .narrow(2, offset, 1)?
        .squeeze(2)?)
}

/// The residual block of VideoPose3D (reused by Anatomy3D): a wide
/// convolution (`width` taps) and a pointwise one, each followed by batch
/// norm and ReLU, plus the input sliced to the frames the output stands for.
///
/// The slice is the reference's: the centre tap of every window, or its
/// last tap in the causal variant (so an output never depends on a frame
/// after the one it is aligned with). When the input is wider than the
/// output (Anatomy3D's concatenated features) the residual keeps the first
/// `c_out` channels.
pub(crate) struct ResidualBlock {
    wide: TemporalConv,
    point: Dense,
    width: usize,
    c_out: usize,
}

impl ResidualBlock {
    /// Load block `i` from the reference's flat lists: convolutions
    /// `convs.{2i}` (wide) and `convs.{2i+1}` (pointwise), batch norms
    /// `bns.{2i}` and `bns.{2i+1}`. Both convolutions have no bias.
    pub(crate) fn load(
        convs: &ParamLoader,
        bns: &ParamLoader,
        i: usize,
        c_in: usize,
        c_out: usize,
        width: usize,
    ) -> Result<Self> {
        let wide = RawAffine::conv1d(&convs.pp(2 * i), c_in, c_out, width, false)?
            .with_bn(&BatchNorm::load(&bns.pp(2 * i), c_out)?)?
            .into_conv()?;
        let point = RawAffine::conv1d(&convs.pp(2 * i + 1), c_out, c_out, 1, false)?
            .with_bn(&BatchNorm::load(&bns.pp(2 * i + 1), c_out)?)?
            .into_dense()?;
        Ok(Self {
            wide,
            point,
            width,
            c_out,
        })
    }

    /// Residual offset of the tap an output frame is aligned with, in
    /// units of the block's dilation.
    fn aligned_tap(&self, causal: bool) -> usize {
        if causal {
            self.width - 1
        } else {
            self.width / 2
        }
    }

    fn finish(&self, residual: Tensor, x: &Tensor) -> Result<Tensor> {
        let residual = if residual.dim(2)? > self.c_out {
            residual.narrow(2, 0, self.c_out)?
        } else {
            residual
        };
        Ok(residual.add(&self.point.forward(x)?.relu()?)?)
    }

    /// The strided (single-output-frame) form: `T` frames in, `T / width` out.
    pub(crate) fn strided(&self, x: &Tensor, causal: bool) -> Result<Tensor> {
        let residual = every_kth(x, self.width, self.aligned_tap(causal))?;
        let h = self.wide.strided(x)?.relu()?;
        self.finish(residual, &h)
    }

    /// The dilated (whole-sequence) form: `T` frames in,
    /// `T - (width-1)·dilation` out.
    pub(crate) fn dilated(&self, x: &Tensor, dilation: usize, causal: bool) -> Result<Tensor> {
        let h = self.wide.dilated(x, dilation)?.relu()?;
        let residual = x.narrow(1, self.aligned_tap(causal) * dilation, h.dim(1)?)?;
        self.finish(residual, &h)
    }
}

/// A PyTorch `LayerNorm` over the last dimension.
#[derive(Debug, Clone)]
pub(crate) struct LayerNorm {
    weight: Tensor,
    bias: Tensor,
    eps: f32,
}

impl LayerNorm {
    pub(crate) fn load(l: &ParamLoader, dim: usize, eps: f32) -> Result<Self> {
        let weight = l.param(&[dim], "weight", candle_nn::init::ONE)?;
        let bias = l.param(&[dim], "bias", candle_nn::init::ZERO)?;
        Ok(Self { weight, bias, eps })
    }

    pub(crate) fn forward(&self, x: &Tensor) -> Result<Tensor> {
        Ok(candle_nn::ops::layer_norm(
            &x.contiguous()?,
            &self.weight,
            &self.bias,
            self.eps,
        )?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::init::RandomInit;
    use candle_core::{DType, Device, IndexOp};

    fn input(b: usize, c: usize, t: usize) -> Tensor {
        Tensor::rand(-1f32, 1f32, (b, c, t), &Device::Cpu).unwrap()
    }

    fn max_diff(a: &Tensor, b: &Tensor) -> f32 {
        a.sub(b)
            .unwrap()
            .abs()
            .unwrap()
            .flatten_all()
            .unwrap()
            .max(0)
            .unwrap()
            .to_scalar()
            .unwrap()
    }

    /// Reference: candle's own conv1d in `(B, C, T)` layout, then the
    /// batch norm written out.
    fn reference(l: &ParamLoader, x_bct: &Tensor, stride: usize, dilation: usize) -> Tensor {
        use candle_nn::init::{ONE, ZERO};
        let conv = l.pp("conv");
        let w = conv.param(&[6, 4, 3], "weight", torch_default(12)).unwrap();
        let bias = conv.param(&[6], "bias", torch_default(12)).unwrap();
        let bn = l.pp("bn");
        let g = bn.param(&[6], "weight", ONE).unwrap();
        let beta = bn.param(&[6], "bias", ZERO).unwrap();
        let mean = bn.buffer(&[6], "running_mean", ZERO).unwrap();
        let var = bn.buffer(&[6], "running_var", ONE).unwrap();
        let col = |t: &Tensor| t.reshape((1, 6, 1)).unwrap();
        let y = x_bct
            .conv1d(&w, 0, stride, dilation, 1)
            .unwrap()
            .broadcast_add(&col(&bias))
            .unwrap();
        let y = y.broadcast_sub(&col(&mean)).unwrap();
        let y = y
            .broadcast_div(&col(&var.affine(1.0, BN_EPS).unwrap().sqrt().unwrap()))
            .unwrap();
        y.broadcast_mul(&col(&g))
            .unwrap()
            .broadcast_add(&col(&beta))
            .unwrap()
    }

    #[test]
    fn folded_conv_matches_candle_conv1d_then_batch_norm() {
        let l = ParamLoader::new(RandomInit::perturbed(3).var_builder());
        let conv = RawAffine::conv1d(&l.pp("conv"), 4, 6, 3, true)
            .unwrap()
            .with_bn(&BatchNorm::load(&l.pp("bn"), 6).unwrap())
            .unwrap()
            .into_conv()
            .unwrap();
        assert_eq!(
            l.total(),
            6 * 4 * 3 + 6 + 2 * 6,
            "running stats are not parameters"
        );
        let x = input(2, 4, 27);
        let x_btc = x.transpose(1, 2).unwrap().contiguous().unwrap();
        for dilation in [1, 3, 9] {
            let ours = conv
                .dilated(&x_btc, dilation)
                .unwrap()
                .transpose(1, 2)
                .unwrap();
            let theirs = reference(&l, &x, 1, dilation);
            assert_eq!(ours.dims(), theirs.dims());
            assert!(max_diff(&ours, &theirs) < 1e-5, "dilation {dilation}");
        }
        let ours = conv.strided(&x_btc).unwrap().transpose(1, 2).unwrap();
        let theirs = reference(&l, &x, 3, 1);
        assert_eq!(ours.dims(), &[2, 6, 9]);
        assert!(max_diff(&ours, &theirs) < 1e-5);
    }

    #[test]
    fn dense_matches_linear_and_every_kth_picks_frames() {
        let l = ParamLoader::new(RandomInit::new(5).var_builder());
        let dense = RawAffine::linear(&l, 5, 7, true)
            .unwrap()
            .into_dense()
            .unwrap();
        let w = l.param(&[7, 5], "weight", torch_default(5)).unwrap();
        let b = l.param(&[7], "bias", torch_default(5)).unwrap();
        let x = Tensor::rand(-1f32, 1f32, (2, 3, 5), &Device::Cpu).unwrap();
        let theirs = candle_nn::Linear::new(w, Some(b));
        let theirs = candle_nn::Module::forward(&theirs, &x).unwrap();
        assert!(max_diff(&dense.forward(&x).unwrap(), &theirs) < 1e-6);

        let x = Tensor::arange(0f32, 12.0, &Device::Cpu)
            .unwrap()
            .reshape((1, 6, 2))
            .unwrap();
        let picked = every_kth(&x, 3, 2).unwrap();
        assert_eq!(
            picked
                .i((0, .., 0))
                .unwrap()
                .to_dtype(DType::F32)
                .unwrap()
                .to_vec1::<f32>()
                .unwrap(),
            [4.0, 10.0]
        );
    }
}

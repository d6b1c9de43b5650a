//! 2D-to-3D lifters trained here, so that the bone-length adjustment can
//! be measured on lifters whose outputs we produce ourselves, end to end
//! from the real Stacked Hourglass detections.
//!
//! - [`data`]: per (sequence, camera) inputs (SH -> H36M-17 normalized
//!   screen coordinates, the same conversion the bone-length models read)
//!   and root-relative camera-space targets; frame subsampling; horizontal
//!   flip augmentation and test-time flip;
//! - [`mlp`]: the residual MLP of Martinez et al. 2017 in candle-nn;
//! - [`temporal`]: a VideoPose3D-style dilated temporal convolution model
//!   (centred or causal), under the reference tensor names so its weights
//!   also load into `blapose_lifters::VideoPose3d`;
//! - [`init`]: seeded initial weights and dropout masks;
//! - [`objective`]: the training objectives — MPJPE from scratch, and the
//!   paper's fine-tuning through the bone-length adjustment;
//! - [`train`]: the training loop (candle autograd, the crate's
//!   checkpointable [`crate::adam::Adam`]), checkpoints, resume, log;
//! - [`weights`]: the weights file (safetensors + metadata) and loading.
//!
//! What each network is and how large is a [`LifterArch`] (an [`MlpArch`] or
//! a [`VideoPoseArch`], selected by [`LifterKind`]): the type the weights
//! files record, defined in `blapose_lifters::arch` and used here as the
//! training configuration too, so a run writes exactly what the server
//! reads; [`build`] makes the network of one.
//!
//! Every lifter is a [`LifterNet`]: a [`data::Window`] of frames in, the 16
//! non-root joints of one frame out — the window's centre frame, or its
//! last for a causal model (the root is fixed at the origin: targets are
//! root-relative, so predicting it would only add a constant-zero output).
//! The single-frame MLP reads a window of 1.

pub mod data;
pub mod init;
pub mod mlp;
pub mod objective;
pub mod predict;
pub mod temporal;
pub mod train;
pub mod weights;

use blapose_core::{Pose, NUM_JOINTS};
use candle_core::Tensor;
use candle_nn::VarMap;
use rand::RngCore;

use crate::error::TrainError;
use data::Window;
use mlp::MlpLifter;
use temporal::TemporalLifter;

/// The architectures trained here, as the weights files record them:
/// defined once in the serving crate, which reads those files.
pub use blapose_lifters::arch::{LifterArch, LifterKind, MlpArch, VideoPoseArch};

/// Outputs of a lifter: the 16 non-root joints x (x, y, z), metres.
pub const OUTPUT_DIM: usize = (NUM_JOINTS - 1) * 3;

/// A fresh network of architecture `arch`, its variables initialized from
/// `seed`.
pub fn build(arch: &LifterArch, seed: u64) -> Result<(Box<dyn LifterNet>, VarMap), TrainError> {
    match *arch {
        LifterArch::Mlp(c) => {
            let (m, v) = MlpLifter::init(c, seed)?;
            Ok((Box::new(m), v))
        }
        LifterArch::VideoPose(c) => {
            let (m, v) = TemporalLifter::init(c, seed)?;
            Ok((Box::new(m), v))
        }
    }
}

/// A trainable lifting network.
pub trait LifterNet: Send + Sync {
    /// The architecture.
    fn kind(&self) -> LifterKind;
    /// The input frames of one output frame.
    fn window(&self) -> Window;
    /// `x`: `(B, window().values())` normalized screen coordinates ->
    /// `(B, OUTPUT_DIM)` root-relative joints 1..17 (metres). `train` is
    /// `Some(rng)` in training mode (dropout masks drawn from `rng`, batch
    /// statistics in batch norm, running statistics updated) and `None` in
    /// evaluation mode.
    fn forward(&self, x: &Tensor, train: Option<&mut dyn RngCore>) -> Result<Tensor, TrainError>;
}

/// A network output row (16 joints) as a pose with the root at the origin.
pub fn output_to_pose(row: &[f32]) -> Pose {
    let mut p = [[0.0f32; 3]; NUM_JOINTS];
    for j in 1..NUM_JOINTS {
        let k = 3 * (j - 1);
        p[j] = [row[k], row[k + 1], row[k + 2]];
    }
    p
}

/// The training target of a root-relative pose (joints 1..17, flattened).
pub fn pose_to_target(pose: &Pose) -> [f32; OUTPUT_DIM] {
    std::array::from_fn(|i| pose[1 + i / 3][i % 3])
}

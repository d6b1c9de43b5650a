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
use serde::{Deserialize, Serialize};

use crate::error::TrainError;
use data::Window;
use mlp::{MlpConfig, MlpLifter};
use temporal::{TemporalConfig, TemporalLifter};

/// Outputs of a lifter: the 16 non-root joints x (x, y, z), metres.
pub const OUTPUT_DIM: usize = (NUM_JOINTS - 1) * 3;

/// Which lifter architecture (`train-lifter --model`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, clap::ValueEnum)]
pub enum LifterKind {
    /// Martinez et al. 2017 residual MLP, single frame.
    Mlp,
    /// VideoPose3D-style temporal convolutions.
    #[value(name = "videopose")]
    Temporal,
}

impl LifterKind {
    /// Flag and metadata spelling.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Mlp => "mlp",
            Self::Temporal => "videopose",
        }
    }
}

impl std::fmt::Display for LifterKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

/// An architecture with its size: what a weights file needs to rebuild the
/// network (stored in its metadata).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "model", rename_all = "lowercase")]
pub enum LifterArch {
    /// [`MlpLifter`].
    Mlp(MlpConfig),
    /// [`TemporalLifter`].
    #[serde(rename = "videopose")]
    Temporal(TemporalConfig),
}

impl LifterArch {
    /// The default size of `kind`.
    pub fn default_for(kind: LifterKind) -> Self {
        match kind {
            LifterKind::Mlp => Self::Mlp(MlpConfig::default()),
            LifterKind::Temporal => Self::Temporal(TemporalConfig::default()),
        }
    }

    /// The architecture's kind.
    pub fn kind(&self) -> LifterKind {
        match self {
            Self::Mlp(_) => LifterKind::Mlp,
            Self::Temporal(_) => LifterKind::Temporal,
        }
    }

    /// A short name for tables: `mlp`, `videopose27`, `videopose27-causal`.
    pub fn name(&self) -> String {
        match self {
            Self::Mlp(_) => "mlp".into(),
            Self::Temporal(c) => c.served().name(),
        }
    }

    /// A fresh network, its variables initialized from `seed`.
    pub fn build(&self, seed: u64) -> Result<(Box<dyn LifterNet>, VarMap), TrainError> {
        match *self {
            Self::Mlp(c) => {
                let (m, v) = MlpLifter::init(c, seed)?;
                Ok((Box::new(m), v))
            }
            Self::Temporal(c) => {
                let (m, v) = TemporalLifter::init(c, seed)?;
                Ok((Box::new(m), v))
            }
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

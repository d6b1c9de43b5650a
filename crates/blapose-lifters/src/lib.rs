//! blapose-lifters: the 2D-to-3D lifting models BLAPose adjusts, in candle.
//!
//! The paper's efficiency table times three published lifters online, one
//! output frame per step, alone and followed by the bone-length
//! adjustment. To reproduce it (and, later, to fine-tune a lifter through
//! the adjustment) we need those lifters with their *exact* reference
//! architectures — the parameter counts are asserted by the tests:
//!
//! | model | frames | parameters |
//! |---|---|---|
//! | [`VideoPose3d`] (Pavllo et al. 2019) | 243 | 16,952,371 |
//! | [`PoseFormer`] (Zheng et al. 2021) | 81 | 9,602,885 |
//! | [`Anatomy3d`] (Chen et al. 2021) | 243 | 59,177,580 |
//! | its [`BoneLengthBranch`] | - | 8,557,219 |
//!
//! Every model is built from a `candle_nn::VarBuilder` whose tensor names
//! are those of the reference PyTorch state dict (a converted checkpoint
//! loads unchanged; a `VarMap` gives a future trainer the same names), or
//! with fast reproducible random weights ([`RandomInit`]) for timing.
//! (Checkpoints saved from `nn.DataParallel`, as Anatomy3D's are, prefix
//! every name with `module.`: pass `vb.pp("module")`.)
//! Inference only: batch norm is folded into the layers when a model is
//! built, dropout is the identity, and the dense products run in a CPU
//! kernel with weights packed once at construction (see `kernel.rs`; candle's
//! general matmul repacks the weights on every call, which dominates at the
//! few rows of online lifting). A trainer would build its own autograd
//! forward over the same tensor names.
//!
//! [`ReferenceLifter`] names those three reference architectures (random
//! weights for timing). Lifters trained by `blapose train-lifter` are
//! another concept: [`arch`] defines their architectures once
//! ([`LifterArch`], selected by [`LifterKind`]) for the trainer that builds
//! them and everyone who reads their weights files, and [`trained`] loads a
//! trained causal VideoPose3D as a [`TrainedLifter`], the online lifter
//! blapose-server can run for clients that send 2D keypoints only.
//!
//! Conventions: inputs are normalized 2D keypoints `(B, F, 17, 2)` in
//! Human3.6M joint order, outputs root-relative 3D poses `(B, 17, 3)` (in
//! whatever unit the weights were trained in; metres for the references).

pub mod anatomy;
pub mod arch;
mod error;
mod init;
mod kernel;
mod layers;
mod params;
pub mod poseformer;
pub mod trained;
pub mod videopose;
mod window;

pub use anatomy::{Anatomy3d, Anatomy3dConfig, BoneLengthBranch, OnlineBoneLengths};
pub use arch::{LifterArch, LifterKind, MlpArch, VideoPoseArch};
pub use error::{LifterError, Result};
pub use init::{record_random, RandomInit};
pub use poseformer::{PoseFormer, PoseFormerConfig};
pub use trained::{TrainedLifter, TrainedLifterError};
pub use videopose::{VideoPose3d, VideoPose3dConfig};
pub use window::{keypoints_tensor, poses_from_tensor, SlidingWindow};

use candle_core::Tensor;

/// Features per input joint: normalized `(x, y)`.
pub const INPUT_FEATURES: usize = 2;

/// A lifting model that turns a window of 2D keypoint frames into the 3D
/// pose of one frame.
pub trait Lifter: Send + Sync {
    /// Display name (e.g. `"VideoPose3D"`).
    fn name(&self) -> &'static str;

    /// Frames in one input window.
    fn receptive_field(&self) -> usize;

    /// Trainable parameters, counted as PyTorch's `model.parameters()`
    /// would (batch-norm running statistics excluded).
    fn params(&self) -> usize;

    /// One pose per window: `(B, receptive_field, 17, 2)` ->
    /// `(B, 17, 3)`. Which frame of the window the pose belongs to is the
    /// model's (the centre frame, or the last for causal variants).
    fn predict_frame(&self, window: &Tensor) -> Result<Tensor>;
}

/// The published reference lifters of the paper's efficiency table (not
/// the architectures the trainer trains: those are [`LifterKind`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum ReferenceLifter {
    /// VideoPose3D, 243 frames.
    VideoPose3d,
    /// PoseFormer, 81 frames.
    PoseFormer,
    /// Anatomy3D, 243 frames.
    Anatomy3d,
}

impl ReferenceLifter {
    /// All of them, in the order of the paper's table.
    pub const ALL: [ReferenceLifter; 3] = [
        ReferenceLifter::VideoPose3d,
        ReferenceLifter::Anatomy3d,
        ReferenceLifter::PoseFormer,
    ];

    /// The reference model with random weights. `causal` selects the
    /// causal variant where the model has one (VideoPose3D, Anatomy3D);
    /// PoseFormer has none and always outputs the centre frame.
    pub fn random(self, causal: bool, seed: u64) -> Result<Box<dyn Lifter>> {
        Ok(match self {
            ReferenceLifter::VideoPose3d => Box::new(VideoPose3d::random(
                VideoPose3dConfig::receptive_field_243().with_causal(causal),
                seed,
            )?),
            ReferenceLifter::PoseFormer => {
                Box::new(PoseFormer::random(PoseFormerConfig::frames_81(), seed)?)
            }
            ReferenceLifter::Anatomy3d => Box::new(Anatomy3d::random(
                Anatomy3dConfig::receptive_field_243().with_causal(causal),
                seed,
            )?),
        })
    }
}

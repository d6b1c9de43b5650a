//! blapose-model: the BLAPose bone-length networks and the kernels that serve them.
//!
//! The paper's length predictor is small (2,390,784 parameters) but it runs on
//! every frame of every stream, so this crate has two faces:
//!
//! * [`mod@reference`]: the networks in candle, exactly as the paper's reference
//!   code defines them and trainable with candle autograd. They are the
//!   ground truth every other path is tested against.
//! * [`fast`]: hand-written CPU kernels for serving — one batched online GRU
//!   step ([`fast::OnlineGruEngine`]) and a whole-sequence Bi-GRU
//!   ([`fast::OfflineBiGruEngine`]).
//!
//! Both read the same safetensors files ([`weights`]), whose tensor names are
//! those of the reference PyTorch module ([`names`]), so a converted reference
//! checkpoint loads unchanged.

pub mod averaging;
pub mod error;
pub mod fast;
pub mod init;
pub mod input;
pub mod names;
pub mod reference;
pub mod stature;
pub mod symmetry;
pub mod weights;

pub use averaging::RunningMean;
pub use error::ModelError;
pub use fast::{
    Bf16Unit, CpuFeatures, EngineOptions, Isa, OfflineBiGruEngine, OnlineGruEngine, Precision,
    PrecisionChoice, StepScratch,
};
pub use input::{Framing, ModelInput};
pub use reference::{BoneLengthBiGru, BoneLengthGru};
pub use weights::{LoadedWeights, WeightsMetadata};

use blapose_core::skeleton::NUM_BONES;

/// Values per input frame: 17 joints x 2 normalized screen coordinates.
pub const INPUT_DIM: usize = blapose_core::pose::KEYPOINT_VALUES;
/// Width of the per-frame embedding (`Linear(34 -> 256)`).
pub const EMBED_DIM: usize = 256;
/// Hidden size of every GRU direction.
pub const HIDDEN: usize = 512;
/// Width of the gate pre-activations of one GRU direction (r, z, n).
pub const GATES: usize = 3 * HIDDEN;
/// Width of the concatenated final states fed to the output layer.
pub const FEATURES: usize = 2 * HIDDEN;
/// Number of predicted bone lengths.
pub const OUTPUT_DIM: usize = NUM_BONES;
/// Dropout probability after the embedding during training (reference code).
pub const DROPOUT: f32 = 0.25;
/// Trainable parameters of either model kind.
pub const PARAMS: usize = 2_390_784;

/// Floats of recurrent state one online session carries (two GRUs x 512).
pub const STATE_DIM: usize = 2 * HIDDEN;

pub use blapose_core::ModelKind;

/// `Ok` if the weights found are of the `expected` kind, else
/// [`ModelError::WrongKind`]: what loading a file and building an engine
/// both check.
pub fn expect_kind(expected: ModelKind, found: ModelKind) -> Result<(), ModelError> {
    if found == expected {
        Ok(())
    } else {
        Err(ModelError::WrongKind { expected, found })
    }
}

/// A zeroed recurrent state for one online session (`STATE_DIM` floats),
/// the state every stream starts from.
pub fn initial_hidden() -> Vec<f32> {
    vec![0.0; STATE_DIM]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_kind_found_must_be_the_kind_expected() {
        assert!(expect_kind(ModelKind::Gru, ModelKind::Gru).is_ok());
        assert!(matches!(
            expect_kind(ModelKind::Gru, ModelKind::BiGru),
            Err(ModelError::WrongKind { .. })
        ));
    }

    #[test]
    fn initial_hidden_is_zero_state() {
        let h = initial_hidden();
        assert_eq!(h.len(), STATE_DIM);
        assert!(h.iter().all(|&v| v == 0.0));
    }
}

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
pub mod names;
pub mod reference;
pub mod stature;
pub mod symmetry;
pub mod weights;

pub use averaging::RunningMean;
pub use error::ModelError;
pub use fast::{
    Bf16Unit, EngineOptions, Isa, OfflineBiGruEngine, OnlineGruEngine, Precision, StepScratch,
};
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

/// Which of the paper's two bone-length models.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ModelKind {
    /// Online model: two unidirectional GRUs fed the same stream.
    Gru,
    /// Offline model: one bidirectional GRU over the whole sequence.
    BiGru,
}

impl ModelKind {
    /// The name used on command lines and in weights metadata.
    pub const fn as_str(self) -> &'static str {
        match self {
            ModelKind::Gru => "gru",
            ModelKind::BiGru => "bigru",
        }
    }

    /// `Ok` if `found` is this kind, else [`ModelError::WrongKind`]: what
    /// loading a file and building an engine both check.
    pub fn expect(self, found: ModelKind) -> Result<(), ModelError> {
        if found == self {
            Ok(())
        } else {
            Err(ModelError::WrongKind {
                expected: self,
                found,
            })
        }
    }
}

impl std::fmt::Display for ModelKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

impl std::str::FromStr for ModelKind {
    type Err = ModelError;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.trim().to_ascii_lowercase().as_str() {
            "gru" => Ok(ModelKind::Gru),
            "bigru" | "bi-gru" => Ok(ModelKind::BiGru),
            _ => Err(ModelError::UnknownKind(s.to_string())),
        }
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
    fn kind_round_trips_through_strings() {
        for kind in [ModelKind::Gru, ModelKind::BiGru] {
            assert_eq!(kind.to_string().parse::<ModelKind>().unwrap(), kind);
        }
        assert_eq!("BiGRU".parse::<ModelKind>().unwrap(), ModelKind::BiGru);
        assert!(matches!(
            "lstm".parse::<ModelKind>(),
            Err(ModelError::UnknownKind(_))
        ));
    }

    #[test]
    fn initial_hidden_is_zero_state() {
        let h = initial_hidden();
        assert_eq!(h.len(), STATE_DIM);
        assert!(h.iter().all(|&v| v == 0.0));
    }
}

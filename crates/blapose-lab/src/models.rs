//! The models a lab benchmark scores: which shipped weights, which
//! keypoints each reads, and the input contract it is fed through. Shared
//! by the many-bodies benchmark ([`crate::bodies`]) and the real-detection
//! check beside it ([`crate::real_check`]).

use blapose_model::input::ModelInput;
use blapose_model::{LoadedWeights, ModelKind};
use blapose_train::TrainError;
use serde::Serialize;

/// Which keypoints a benchmark model reads (its rows' `input`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum BenchInput {
    /// Normalized keypoints, no calibration (the default pair).
    None,
    /// Keypoints prepared with the camera's calibration (the camera-aware
    /// pair).
    Calibration,
}

/// The shipped models the benchmark scores, in row order: each model kind
/// with the input it reads and its weights file under `models/`.
pub const SHIPPED_MODELS: [(ModelKind, BenchInput, &str); 4] = [
    (
        ModelKind::Gru,
        BenchInput::None,
        "bone_length_gru.safetensors",
    ),
    (
        ModelKind::BiGru,
        BenchInput::None,
        "bone_length_bigru.safetensors",
    ),
    (
        ModelKind::Gru,
        BenchInput::Calibration,
        "bone_length_gru_rectified.safetensors",
    ),
    (
        ModelKind::BiGru,
        BenchInput::Calibration,
        "bone_length_bigru_rectified.safetensors",
    ),
];

/// A model to score: its kind, which keypoints it reads, its weights.
pub struct BenchModel<'a> {
    /// Online GRU or offline Bi-GRU.
    pub kind: ModelKind,
    /// Which keypoints.
    pub input: BenchInput,
    /// The weights.
    pub weights: &'a LoadedWeights,
    /// Where they came from (for the report).
    pub path: String,
}

impl BenchModel<'_> {
    /// What the model reads: its weights' input contract (weights that
    /// record none read as `input` says: screen coordinates, or plain
    /// rectified keypoints with a calibration). Weights whose contract
    /// does not read what `input` gives are refused.
    pub fn contract(&self) -> Result<ModelInput, TrainError> {
        let calibrated = self.input == BenchInput::Calibration;
        let contract = self.weights.meta.input_contract(calibrated);
        if contract.framing.needs_calibration() != calibrated {
            return Err(TrainError::InvalidArgument(format!(
                "{}: its weights read {:?} keypoints, but the benchmark gives them input {:?}",
                self.path, contract.framing, self.input
            )));
        }
        Ok(contract)
    }
}

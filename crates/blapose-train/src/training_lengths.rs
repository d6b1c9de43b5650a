//! The training subjects' bone-length statistics: what every length
//! strategy ([`crate::lengths`]) and the ANSUR II population's calibration
//! ([`crate::ansur`]) are built from, and the one place they are computed.
//!
//! **No test statistics.** [`TrainingLengthStats::from_training`] sees only
//! the lengths handed to it, and the data loader only ever hands it the
//! training subjects ([`crate::dataset::TRAIN_SUBJECTS`]).

use blapose_core::bones::average_symmetric_pairs;
use blapose_core::skeleton::NUM_BONES;
use blapose_core::BoneLengths;

use crate::error::TrainError;

/// Below this standard deviation (metres) a bone is treated as fixed across
/// the training subjects (Human3.6M's head bone is 0.115 m for everyone).
pub const FIXED_BONE_STD: f32 = 5e-4;

/// Per-bone statistics of the training subjects' lengths (metres).
#[derive(Debug, Clone, PartialEq)]
pub struct TrainingLengthStats {
    /// Mean over subjects.
    pub mean: BoneLengths,
    /// Population standard deviation over subjects.
    pub std: BoneLengths,
    /// Number of subjects.
    pub count: usize,
}

impl TrainingLengthStats {
    /// Statistics of the training subjects' lengths (one entry per subject).
    /// Callers pass the training subjects only; see the module docs.
    pub fn from_training(subject_lengths: &[BoneLengths]) -> Result<Self, TrainError> {
        if subject_lengths.is_empty() {
            return Err(TrainError::InvalidArgument(
                "no training subjects' lengths".into(),
            ));
        }
        let n = subject_lengths.len() as f64;
        let mut mean = [0.0f32; NUM_BONES];
        let mut std = [0.0f32; NUM_BONES];
        for b in 0..NUM_BONES {
            let m = subject_lengths.iter().map(|l| f64::from(l[b])).sum::<f64>() / n;
            let v = subject_lengths
                .iter()
                .map(|l| (f64::from(l[b]) - m).powi(2))
                .sum::<f64>()
                / n;
            if !m.is_finite() || m <= 0.0 {
                return Err(TrainError::InvalidArgument(format!(
                    "training mean of bone {b} is {m}"
                )));
            }
            mean[b] = m as f32;
            std[b] = v.sqrt() as f32;
        }
        // Human3.6M's left and right bones agree to float rounding; make
        // them exactly equal so every strategy is exactly symmetric.
        average_symmetric_pairs(&mut mean);
        average_symmetric_pairs(&mut std);
        Ok(Self {
            mean,
            std,
            count: subject_lengths.len(),
        })
    }

    /// True when the training subjects all share this bone's length.
    pub fn is_fixed(&self, bone: usize) -> bool {
        self.std[bone] < FIXED_BONE_STD
    }
}

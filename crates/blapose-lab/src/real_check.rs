//! The many-bodies benchmark's real-detection check: each model scored on
//! the *training* subjects' own Stacked Hourglass detections, beside its
//! synthetic row.
//!
//! Why: the benchmark's 2D is synthetic (each body's true joints projected,
//! plus a residual track of another person's real detections drawn
//! independently of the body). Three readings tried on it (a proportion
//! reader given the height, the same without it through the calibration,
//! and the camera-aware GRU restarted every few frames) moved the
//! synthetic rows and real detections in opposite directions
//! (models/README.md). The training subjects' own detections with their
//! true lengths are real data that selection may use (they are training
//! data, never S9/S11), so the benchmark reports them beside every row: a
//! change that helps only one of the two columns is one to distrust.
//!
//! Camera-aware models read the trials as their weights' input contract
//! says with each view's calibration, as the server does for a calibrated
//! session ([`blapose_train::eval::calibrate`]). The stature
//! regression reads each subject's *matched* stature
//! ([`crate::stature_proxy::matched_stature`]: the stature whose regression
//! lengths sum to the subject's true summed length), which reads the truth
//! and so scores the regression's proportions alone.

use blapose_core::camera::Camera;
use blapose_core::BoneLengths;
use blapose_model::stature::StatureLines;
use blapose_model::Precision;
use serde::Serialize;

use blapose_train::dataset::EvalSequence;
use blapose_train::eval::run::network_estimator;
use blapose_train::eval::{calibrate, trial_error_mm, LengthEstimator};
use blapose_train::TrainError;

use crate::models::{BenchInput, BenchModel};
use crate::stature_proxy::matched_lengths;

/// The training subjects' real trials, and how to find their cameras.
pub struct RealCheck<'a> {
    /// Normalized SH keypoints, each with its subject's true lengths.
    pub trials: Vec<EvalSequence>,
    /// Each trial's calibration, by subject and camera id.
    pub camera: &'a (dyn Fn(&str, &str) -> Option<&'a Camera> + Sync),
}

/// What the check ran on, for the report.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct RealCheckInfo {
    /// Subjects.
    pub subjects: Vec<String>,
    /// Trials (subject, action, camera).
    pub trials: usize,
    /// Frames over all trials.
    pub frames: usize,
}

/// Mean over trials of the mean absolute bone error, mm.
fn mean_error(pred: &[BoneLengths], trials: &[EvalSequence]) -> Result<f64, TrainError> {
    if pred.len() != trials.len() || trials.is_empty() {
        return Err(TrainError::InvalidArgument(format!(
            "{} predictions for {} real-check trials",
            pred.len(),
            trials.len()
        )));
    }
    Ok(pred
        .iter()
        .zip(trials)
        .map(|(p, t)| trial_error_mm(p, &t.gt))
        .sum::<f64>()
        / trials.len() as f64)
}

impl RealCheck<'_> {
    /// A benchmark model's error on the trials, mm.
    pub fn model_error(&self, model: &BenchModel<'_>) -> Result<f64, TrainError> {
        let estimator = network_estimator(model.kind, model.weights, Precision::F32)?;
        let est = if model.input == BenchInput::Calibration {
            let mut trials = self.trials.clone();
            calibrate(model.weights, &mut trials, self.camera)?;
            estimator.estimate(&trials)?
        } else {
            estimator.estimate(&self.trials)?
        };
        let pred: Vec<BoneLengths> = est.into_iter().map(|e| e.lengths).collect();
        mean_error(&pred, &self.trials)
    }

    /// The stature regression's error with each subject's matched stature
    /// on its pooled `lines`, mm.
    pub fn matched_stature_error(&self, lines: &StatureLines) -> Result<f64, TrainError> {
        let pred = self
            .trials
            .iter()
            .map(|t| {
                matched_lengths(lines, &t.gt).ok_or_else(|| {
                    TrainError::Data("the stature regression's summed slope is not positive".into())
                })
            })
            .collect::<Result<Vec<_>, TrainError>>()?;
        mean_error(&pred, &self.trials)
    }

    /// A constant answer's error on the trials, mm.
    pub fn constant_error(&self, lengths: &BoneLengths) -> Result<f64, TrainError> {
        mean_error(&vec![*lengths; self.trials.len()], &self.trials)
    }

    /// What the check ran on.
    pub fn info(&self) -> RealCheckInfo {
        let mut subjects: Vec<String> = self.trials.iter().map(|t| t.subject.clone()).collect();
        subjects.dedup();
        RealCheckInfo {
            subjects,
            trials: self.trials.len(),
            frames: self.trials.iter().map(EvalSequence::frames).sum(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use blapose_core::skeleton::NUM_BONES;

    fn trial(subject: &str, gt: f32) -> EvalSequence {
        EvalSequence {
            subject: subject.into(),
            sequence: "Walking".into(),
            camera: "c".into(),
            input: vec![0.1; 2 * 34],
            gt: [gt; NUM_BONES],
        }
    }

    #[test]
    fn the_matched_regression_scores_only_proportions_and_the_mean_is_in_sample() {
        let lines = |slope: f64| StatureLines {
            intercept: vec![0.0; NUM_BONES],
            slope: vec![slope; NUM_BONES],
            people: 2,
        };
        let pooled = lines(0.15);
        let no_camera = |_: &str, _: &str| -> Option<&Camera> { None };
        let check = RealCheck {
            trials: vec![trial("S1", 0.25), trial("S1", 0.25), trial("S5", 0.2)],
            camera: &no_camera,
        };
        // Equal bones: the regression's proportions are exact once the
        // summed length is matched.
        assert!(check.matched_stature_error(&pooled).unwrap() < 1e-3);
        let info = check.info();
        assert_eq!(info.subjects, vec!["S1", "S5"]);
        assert_eq!((info.trials, info.frames), (3, 6));
        // 0, 0 and 50 mm.
        let training_mean_mm = check.constant_error(&[0.25; NUM_BONES]).unwrap();
        assert!((training_mean_mm - 50.0 / 3.0).abs() < 1e-3);
        assert!(mean_error(&[], &check.trials).is_err());
    }
}

//! Bone-length evaluation on the standard protocol: one implementation of
//! it, so every number in the model card, the shipped-weights test and a
//! new run's report is computed the same way.
//!
//! Every (sequence, camera) of the evaluated subjects is one *trial*: the
//! model reads the whole 2D stream and gives one estimate of the subject's
//! 16 lengths; the trial's error is the mean absolute error over the 16
//! bones (mm).
//!
//! * **Offline Bi-GRU**: one pass over the whole sequence
//!   ([`blapose_model::OfflineBiGruEngine`]).
//! * **Online GRU**: the serving estimate, i.e. the running mean of the
//!   per-frame predictions over all frames seen
//!   ([`blapose_model::OnlineGruEngine`], trials stepped in lockstep
//!   batches; the mean is the server's own [`blapose_model::RunningMean`],
//!   so the two cannot drift apart); its error after the whole sequence is
//!   the headline, and the error after `n` frames for `n` in
//!   [`CURVE_FRAMES`] is the curve (a trial shorter than `n` contributes
//!   its final estimate).
//!
//! **Aggregation** (the headline `mean_bone_error_mm`): trials are averaged
//! within each action (take number dropped, e.g. "Walking 1" and "Walking"
//! are both "Walking"; both subjects, all cameras, each trial weighted
//! equally), then the per-action means are averaged over actions — the
//! Human3.6M tables' "Avg" ([`blapose_core::metrics::ActionAggregator`]).
//! The plain mean over trials, per subject and per bone are reported too.
//! The naive baselines (predict the training subjects' mean for everyone;
//! the mean of all seven subjects, test subjects included) are aggregated
//! the same way.
//!
//! The protocol is [`evaluate`] over any [`LengthEstimator`]; the
//! networks' estimators are in [`estimators`], the report and its
//! aggregation in [`report`], and one evaluation run on Human3.6M (which
//! trials, which model, where the report goes) in [`run`], which `blapose
//! eval` and `blapose-lab diagnose` share.

pub mod estimators;
pub mod report;
pub mod run;

use std::collections::BTreeMap;

use blapose_core::skeleton::BONE_NAMES;
use blapose_core::BoneLengths;

pub use estimators::{calibrate, BiGruEstimator, FlipAveraged, GruEstimator, StateRestarts};
pub use report::{
    markdown, subject_spread, summarize, trial_error_mm, CurvePoint, EvalReport, SubjectMean,
    SubjectSpread, Summary, TrialPrediction,
};

use crate::dataset::EvalSequence;
use crate::error::TrainError;
use report::{per_bone_bias_mm, per_subject_mean, per_view_mean};

/// Frames-seen points of the online error curve.
pub const CURVE_FRAMES: [usize; 9] = [1, 2, 5, 10, 20, 50, 100, 200, 500];

/// One trial's estimate.
#[derive(Debug, Clone, PartialEq)]
pub struct Estimate {
    /// After the whole sequence.
    pub lengths: BoneLengths,
    /// Online only: the running estimate after `CURVE_FRAMES[i]` frames.
    pub curve: Vec<BoneLengths>,
}

/// Anything that estimates lengths for a batch of trials.
pub trait LengthEstimator: Sync {
    /// One estimate per trial, in order.
    fn estimate(&self, trials: &[EvalSequence]) -> Result<Vec<Estimate>, TrainError>;
}

impl<E: LengthEstimator + ?Sized> LengthEstimator for Box<E> {
    fn estimate(&self, trials: &[EvalSequence]) -> Result<Vec<Estimate>, TrainError> {
        (**self).estimate(trials)
    }
}

/// Evaluate `estimator` on `trials`; `baselines` are `(name, lengths)`
/// predicted for every trial.
#[allow(clippy::too_many_arguments)]
pub fn evaluate(
    estimator: &dyn LengthEstimator,
    trials: &[EvalSequence],
    baselines: &[(&str, BoneLengths)],
    model: &str,
    input: &str,
    weights: &str,
    subjects: &[String],
) -> Result<EvalReport, TrainError> {
    let t0 = std::time::Instant::now();
    let est = estimator.estimate(trials)?;
    let seconds = t0.elapsed().as_secs_f64();
    let pred: Vec<BoneLengths> = est.iter().map(|e| e.lengths).collect();
    let summary = summarize(trials, &pred)?;
    let per_subject_mean_prediction = per_subject_mean(trials, &pred);
    let mut base = BTreeMap::new();
    for (name, l) in baselines {
        base.insert(
            name.to_string(),
            summarize(trials, &vec![*l; trials.len()])?,
        );
    }
    let mut curve = Vec::new();
    if est.iter().all(|e| e.curve.len() == CURVE_FRAMES.len()) && !est.is_empty() {
        for (k, &n) in CURVE_FRAMES.iter().enumerate() {
            let p: Vec<BoneLengths> = est.iter().map(|e| e.curve[k]).collect();
            let s = summarize(trials, &p)?;
            curve.push(CurvePoint {
                frames: n,
                mean_bone_error_mm: s.mean_bone_error_mm,
                mean_over_trials_mm: s.mean_over_trials_mm,
            });
        }
    }
    Ok(EvalReport {
        model: model.into(),
        input: input.into(),
        weights: weights.into(),
        subjects: subjects.to_vec(),
        aggregation: "mean over actions of the mean error of each action's trials (sequence x camera, \
                      both subjects, each trial weighted equally); per trial: mean |pred - true| over 16 bones"
            .into(),
        trials: trials.len(),
        frames: trials.iter().map(|t| t.frames()).sum(),
        mean_bone_error_mm: summary.mean_bone_error_mm,
        per_bone_mm: summary.per_bone_mm.clone(),
        bone_names: BONE_NAMES.iter().map(|s| s.to_string()).collect(),
        per_action_mm: summary.per_action_mm.clone(),
        per_bone_bias_mm: per_bone_bias_mm(trials, &pred),
        subject_spread: subject_spread(&per_subject_mean_prediction),
        per_subject_mean_prediction,
        per_view_mean_prediction: per_view_mean(trials, &pred),
        trial_predictions: trials
            .iter()
            .zip(&pred)
            .map(|(t, p)| TrialPrediction {
                subject: t.subject.clone(),
                sequence: t.sequence.clone(),
                camera: t.camera.clone(),
                frames: t.frames(),
                predicted_m: p.to_vec(),
                true_m: t.gt.to_vec(),
            })
            .collect(),
        summary,
        baselines: base,
        curve,
        seconds,
    })
}

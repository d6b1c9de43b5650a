//! The eval diagnostics of `blapose-lab diagnose`: the product's
//! evaluation run ([`blapose_train::eval::run`]) with its trials read
//! otherwise (joined mid-way: [`skipped`]; rectified with their camera
//! whatever the weights record: [`rectified`]), the online GRU's state
//! restarted every so many frames ([`state_frames`]),
//! joints lost ([`crate::joint_dropout`]), or the stature regression
//! scored in a model's place ([`crate::stature_proxy`]).
//!
//! Why in the lab: each answers a research question about the shipped
//! models (does the online curve depend on the state's age or on how the
//! recordings begin? what does a lost joint cost?); none is what a user
//! evaluating a model needs, and each is measured through the product's
//! own run, so its numbers compare with the product's.

use blapose_model::input::ModelInput;
use blapose_train::dataset::{prepare_streams, EvalSequence};
use blapose_train::eval::run::EvalData;
use blapose_train::eval::{EvalReport, GruEstimator};
use blapose_train::synth::FRAME_DIM;
use blapose_train::TrainError;
use serde::Serialize;

use crate::joint_dropout::DropJointsReport;

/// `estimator` restarting its hidden state every `frames` frames (`None`
/// or 0: never), the running mean of its predictions carrying on: does
/// the online curve depend on the state's age (`--state-frames`)?
pub fn state_frames(estimator: GruEstimator, frames: Option<usize>) -> GruEstimator {
    match frames.filter(|&k| k > 0) {
        Some(k) => estimator.with_state_restarts(std::sync::Arc::new(move |t: usize| {
            t > 0 && t.is_multiple_of(k)
        })),
        None => estimator,
    }
}

/// The trial joined `skip` frames in: what a model sees when a client
/// starts streaming in the middle of a recording. A trial no longer than
/// `skip` keeps its last frame, so it still has one.
pub fn skipped(trial: &EvalSequence, skip: usize) -> EvalSequence {
    let first = skip.min(trial.frames().saturating_sub(1));
    EvalSequence {
        subject: trial.subject.clone(),
        sequence: trial.sequence.clone(),
        camera: trial.camera.clone(),
        input: trial.input[first * FRAME_DIM..].to_vec(),
        gt: trial.gt,
    }
}

/// Every trial rectified with its camera's calibration
/// ([`ModelInput::level`]: no lens undistortion, no floor scaling), for
/// weights trained with `train --rectify` alone, whatever they record.
pub fn rectified(trials: &mut [EvalSequence], data: &EvalData) -> Result<(), TrainError> {
    prepare_streams(trials, &ModelInput::level(), &|s: &str, id: &str| {
        data.camera(s, id)
    })
}

/// The report of a diagnosed run (`--json`): the evaluation report, and
/// with `--drop-joints` the comparison with the clean trials beside it.
#[derive(Debug, Serialize)]
pub struct DiagnoseReport<'a> {
    /// The evaluation report (its fields at the top level, as `blapose
    /// eval` writes them).
    #[serde(flatten)]
    pub report: &'a EvalReport,
    /// With `--drop-joints`: the headline is the model reading the trials
    /// with lost joints held (confidence honoured); this compares it with
    /// the clean trials and with the garbage fed as is.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub drop_joints: Option<&'a DropJointsReport>,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn skipping_starts_later_and_keeps_at_least_one_frame() {
        // Ten frames, every value of frame f is f.
        let s = EvalSequence {
            subject: "S9".into(),
            sequence: "Walking 1".into(),
            camera: "54138969".into(),
            input: (0..10 * FRAME_DIM)
                .map(|i| (i / FRAME_DIM) as f32)
                .collect(),
            gt: [0.2; 16],
        };
        let late = skipped(&s, 4);
        assert_eq!(late.frames(), 6);
        assert_eq!(late.input[0], 4.0);
        assert_eq!(late.gt, s.gt);
        assert_eq!(skipped(&s, 0), s);
        let last = skipped(&s, 50);
        assert_eq!(last.frames(), 1);
        assert_eq!(last.input[0], 9.0);
        let empty = EvalSequence {
            input: Vec::new(),
            ..s
        };
        assert_eq!(skipped(&empty, 3).frames(), 0);
    }
}

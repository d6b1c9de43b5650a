//! Evaluation arithmetic on a hand-made fixture, and the online estimator
//! against an independent implementation of the same network.

#![allow(clippy::needless_range_loop)]

use blapose_core::BoneLengths;
use blapose_model::{LoadedWeights, ModelKind};
use blapose_test_support::trials::random_trials;
use blapose_train::dataset::EvalSequence;
use blapose_train::eval::{
    evaluate, summarize, Estimate, GruEstimator, LengthEstimator, CURVE_FRAMES,
};
use blapose_train::fastnet::FastNet;
use blapose_train::TrainError;

fn trial(subject: &str, sequence: &str, gt: f32, frames: usize, marker: f32) -> EvalSequence {
    let mut input = vec![0.0f32; frames * 34];
    input[0] = marker;
    EvalSequence {
        subject: subject.into(),
        sequence: sequence.into(),
        camera: "c".into(),
        input,
        gt: [gt; 16],
    }
}

/// Predicts `marker` (the first input value) for every bone.
struct MarkerEstimator;
impl LengthEstimator for MarkerEstimator {
    fn estimate(&self, trials: &[EvalSequence]) -> Result<Vec<Estimate>, TrainError> {
        Ok(trials
            .iter()
            .map(|t| Estimate {
                lengths: [t.input[0]; 16],
                curve: Vec::new(),
            })
            .collect())
    }
}

#[test]
fn aggregation_matches_hand_computation() {
    // Errors per trial (mm): Walking 1 -> 10, Walking 2 -> 30, Eating 1 -> 20 (S9);
    // Walking 1 -> 40 (S11). Walking = (10 + 30 + 40) / 3 = 26.667, Eating = 20,
    // headline = (26.667 + 20) / 2 = 23.333; over trials (10+30+20+40)/4 = 25.
    let trials = vec![
        trial("S9", "Walking 1", 0.20, 5, 0.21),
        trial("S9", "Walking 2", 0.20, 5, 0.17),
        trial("S9", "Eating 1", 0.20, 5, 0.22),
        trial("S11", "Walking 1", 0.30, 5, 0.34),
    ];
    let base: BoneLengths = [0.25; 16];
    let subjects = vec!["S9".to_string(), "S11".to_string()];
    let r = evaluate(
        &MarkerEstimator,
        &trials,
        &[("flat", base)],
        "bigru",
        "sh",
        "w",
        &subjects,
    )
    .unwrap();
    assert!(
        (r.mean_bone_error_mm - 70.0 / 3.0).abs() < 1e-3,
        "{}",
        r.mean_bone_error_mm
    );
    assert!((r.summary.mean_over_trials_mm - 25.0).abs() < 1e-3);
    assert!((r.per_action_mm["Walking"] - 80.0 / 3.0).abs() < 1e-3);
    assert!((r.per_action_mm["Eating"] - 20.0).abs() < 1e-3);
    assert!((r.summary.per_subject_mm["S9"] - 20.0).abs() < 1e-3);
    assert!((r.summary.per_subject_mm["S11"] - 40.0).abs() < 1e-3);
    assert!(r.per_bone_mm.iter().all(|&b| (b - 25.0).abs() < 1e-3));
    // Signed: +10, -30, +20, +40 mm -> bias +10 mm on every bone.
    assert!(r.per_bone_bias_mm.iter().all(|&b| (b - 10.0).abs() < 1e-3));
    assert_eq!(r.trial_predictions.len(), 4);
    assert!((r.trial_predictions[1].predicted_m[3] - 0.17).abs() < 1e-6);
    assert_eq!(r.trial_predictions[3].true_m, vec![0.30; 16]);
    // Baseline 0.25 everywhere: S9 trials 50 mm, S11 50 mm.
    assert!((r.baselines["flat"].mean_bone_error_mm - 50.0).abs() < 1e-3);
    assert_eq!(r.frames, 20);
    assert!(r.curve.is_empty());
    let json = serde_json::to_value(&r).unwrap();
    assert!(
        json["mean_bone_error_mm"].is_f64()
            && json["per_bone_mm"].is_array()
            && json["per_action_mm"].is_object()
    );
    assert!(
        summarize(&trials, &[base]).is_err(),
        "length mismatch is an error"
    );
}

#[test]
fn online_estimate_is_the_running_mean_of_the_reference_network() {
    let w = LoadedWeights::random(ModelKind::Gru, 3).unwrap();
    let net = FastNet::from_tensors(ModelKind::Gru, w.tensors()).unwrap();
    let est = GruEstimator::new(&w).unwrap();
    let trials = random_trials(1, &[7, 3, 12]);
    let out = est.estimate(&trials).unwrap();
    for (t, e) in trials.iter().zip(&out) {
        let n = t.frames();
        let per = net.predict_per_frame(&t.input, 1, n);
        let mean = |k: usize| -> Vec<f32> {
            (0..16)
                .map(|j| (0..k).map(|f| per[f * 16 + j]).sum::<f32>() / k as f32)
                .collect()
        };
        let full = mean(n);
        for j in 0..16 {
            assert!(
                (e.lengths[j] - full[j]).abs() < 1e-4,
                "final estimate differs"
            );
        }
        assert_eq!(e.curve.len(), CURVE_FRAMES.len());
        for (k, &f) in CURVE_FRAMES.iter().enumerate() {
            let m = mean(f.min(n));
            for j in 0..16 {
                assert!((e.curve[k][j] - m[j]).abs() < 1e-4, "curve at {f} frames");
            }
        }
    }
}

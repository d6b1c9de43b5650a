//! `blapose-lab diagnose --drop-joints P`: how much a lost joint costs.
//!
//! Why: real detectors lose joints and say so with a low confidence; the
//! coordinates they report for a lost joint are anywhere. This simulates
//! it on the evaluation trials: each joint of each frame is lost with
//! probability `P` (seeded), its coordinates replaced by garbage drawn
//! uniformly over the picture (normalized screen coordinates in [-1, 1]).
//! Two inputs come out:
//!
//! * *without confidence*: the garbage fed to the model as is (a client
//!   that does not send confidences, or a model that ignores them);
//! * *with confidence*: every lost joint held at its last detection
//!   ([`blapose_core::missing::hold_fill_sequence`]), what a model that
//!   honours confidence 0 reads.
//!
//! The evaluation scores both beside the clean trials
//! ([`score_with_lost_joints`], [`DropJointsReport`]).

use blapose_core::missing::hold_fill_sequence;
use blapose_core::NUM_JOINTS;
use blapose_train::dataset::EvalSequence;
use blapose_train::eval::EvalReport;
use blapose_train::TrainError;
use rand::{Rng, SeedableRng};
use serde::Serialize;

/// The trials with joints lost.
#[derive(Debug, Clone)]
pub struct DroppedJoints {
    /// Lost joints' coordinates replaced by garbage.
    pub garbage: Vec<EvalSequence>,
    /// Lost joints held at their last detection.
    pub held: Vec<EvalSequence>,
    /// Joints lost, all trials together.
    pub lost: usize,
    /// Joints in all trials.
    pub joints: usize,
    /// Frames that lost every joint.
    pub empty_frames: usize,
}

/// Lose each joint of each frame of `trials` with `probability` (seeded:
/// trial `i` draws from `seed` and `i`).
pub fn drop_joints(
    trials: &[EvalSequence],
    probability: f64,
    seed: u64,
) -> Result<DroppedJoints, TrainError> {
    if !(0.0..1.0).contains(&probability) {
        return Err(TrainError::InvalidArgument(format!(
            "--drop-joints must be in [0, 1), got {probability}"
        )));
    }
    let mut out = DroppedJoints {
        garbage: Vec::with_capacity(trials.len()),
        held: Vec::with_capacity(trials.len()),
        lost: 0,
        joints: 0,
        empty_frames: 0,
    };
    for (i, trial) in trials.iter().enumerate() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(
            seed ^ (i as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15),
        );
        let frames = trial.frames();
        let mut present = vec![true; frames * NUM_JOINTS];
        let mut garbage = trial.input.clone();
        for (k, p) in present.iter_mut().enumerate() {
            if rng.random::<f64>() < probability {
                *p = false;
                garbage[2 * k] = rng.random_range(-1.0..1.0);
                garbage[2 * k + 1] = rng.random_range(-1.0..1.0);
            }
        }
        out.lost += present.iter().filter(|p| !**p).count();
        out.joints += present.len();
        let mut held = garbage.clone();
        out.empty_frames += hold_fill_sequence(&mut held, &present);
        out.garbage.push(EvalSequence {
            input: garbage,
            ..trial.clone()
        });
        out.held.push(EvalSequence {
            input: held,
            ..trial.clone()
        });
    }
    Ok(out)
}

/// The `drop_joints` part of the evaluation report.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct DropJointsReport {
    /// Probability of losing each joint of each frame.
    pub probability: f64,
    /// The seed.
    pub seed: u64,
    /// Share of joints actually lost.
    pub lost_share: f64,
    /// Frames that lost every joint.
    pub empty_frames: usize,
    /// The same model on the clean trials, mm.
    pub clean_mm: f64,
    /// With confidence (lost joints held): the report's headline, mm.
    pub with_confidence_mm: f64,
    /// Without confidence (garbage fed as is), mm.
    pub without_confidence_mm: f64,
    /// `with_confidence_mm - clean_mm`.
    pub rise_mm: f64,
    /// `without_confidence_mm - clean_mm`.
    pub rise_without_confidence_mm: f64,
}

/// `score` (a model scored on a set of trials by the protocol) on
/// `trials` with joints lost ([`drop_joints`]): the report of the trials
/// with lost joints held (confidence honoured), beside the comparison
/// with the clean trials and with the garbage fed as is.
pub fn score_with_lost_joints(
    trials: Vec<EvalSequence>,
    probability: f64,
    seed: u64,
    mut score: impl FnMut(Vec<EvalSequence>) -> Result<EvalReport, TrainError>,
) -> Result<(EvalReport, DropJointsReport), TrainError> {
    let dropped = drop_joints(&trials, probability, seed)?;
    let clean = score(trials)?.mean_bone_error_mm;
    let without = score(dropped.garbage)?.mean_bone_error_mm;
    let report = score(dropped.held)?;
    let with = report.mean_bone_error_mm;
    let lost = DropJointsReport {
        probability,
        seed,
        lost_share: dropped.lost as f64 / dropped.joints.max(1) as f64,
        empty_frames: dropped.empty_frames,
        clean_mm: clean,
        with_confidence_mm: with,
        without_confidence_mm: without,
        rise_mm: with - clean,
        rise_without_confidence_mm: without - clean,
    };
    Ok((report, lost))
}

impl DropJointsReport {
    /// What a run prints about it.
    pub fn summary(&self) -> String {
        format!(
            "joints lost: {:.1} % (p = {}, seed {}), {} frames lost every joint\n\
             clean {:.2} mm | lost joints held (confidence honoured) {:.2} mm ({:+.2}) | \
             garbage fed as is {:.2} mm ({:+.2})",
            100.0 * self.lost_share,
            self.probability,
            self.seed,
            self.empty_frames,
            self.clean_mm,
            self.with_confidence_mm,
            self.rise_mm,
            self.without_confidence_mm,
            self.rise_without_confidence_mm
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn trial(frames: usize) -> EvalSequence {
        EvalSequence {
            subject: "S9".into(),
            sequence: "Walking".into(),
            camera: "1".into(),
            input: (0..frames * NUM_JOINTS * 2)
                .map(|i| (i % 7) as f32 * 0.1)
                .collect(),
            gt: [0.3; 16],
        }
    }

    #[test]
    fn joints_are_lost_at_the_rate_asked_and_seeded() {
        let trials = vec![trial(400), trial(300)];
        let a = drop_joints(&trials, 0.2, 1).unwrap();
        let share = a.lost as f64 / a.joints as f64;
        assert!((share - 0.2).abs() < 0.02, "{share}");
        let b = drop_joints(&trials, 0.2, 1).unwrap();
        assert_eq!(a.garbage[0].input, b.garbage[0].input, "seeded");
        let c = drop_joints(&trials, 0.2, 2).unwrap();
        assert_ne!(a.garbage[0].input, c.garbage[0].input);
        // Held inputs differ from the clean ones only where joints were
        // lost, and never hold garbage outside the clean values.
        let clean = &trials[0].input;
        let held = &a.held[0].input;
        assert!(held.iter().all(|v| clean.contains(v)));
        assert_ne!(&a.garbage[0].input, clean);
        assert!(drop_joints(&trials, 1.0, 1).is_err());
        let none = drop_joints(&trials, 0.0, 1).unwrap();
        assert_eq!(none.lost, 0);
        assert_eq!(&none.held[0].input, clean);
    }
}

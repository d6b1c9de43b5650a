//! Which motion stage to serve: every candidate filter scored the way
//! `blapose eval-adjust` scores the served one, on subjects the choice may
//! be made on (the training subjects; never S9/S11).
//!
//! The lifter runs once per trial (and once more per 2D pre-filter); every
//! candidate is then one more [`evaluate_lifter`] over the cached poses,
//! read from its `gru_motion` row (causal candidates) or `bigru_motion`
//! row (offline ones). The rows beside them (`gru`, `bigru`, `before`,
//! `ground_truth_lengths`) are the baselines every choice is read against.
//!
//! Candidates:
//! * causal, on bone directions: none, One Euro (5 settings), constant-
//!   velocity Kalman (a grid of process and measurement noise);
//! * causal, on the 2D keypoints before lifting (One Euro, Kalman), then
//!   the plain GRU adjustment;
//! * causal root filters (Kalman) and joint sets for the root solve;
//! * offline, on bone directions: Butterworth (cutoffs), Savitzky-Golay
//!   (windows, degrees), RTS smoother; offline root filters; feet held or
//!   not.

use std::collections::HashMap;

use blapose_core::motion::fir::FirFit;
use blapose_core::motion::kalman::KalmanParams;
use blapose_core::motion::one_euro::OneEuroParams;
use blapose_core::motion::{
    direction_values, served_causal, served_offline, CausalMotionConfig, CausalSmoothing,
    ChannelFilter, OfflineMotionConfig, OfflineSmoothing, DIRECTION_CHANNELS,
};
use blapose_core::skeleton::NUM_JOINTS;
use blapose_core::Pose;
use blapose_train::eval_adjust::{evaluate_lifter, Adjusters, MethodReport, MotionSetup};
use blapose_train::lifter::data::LifterSequence;
use blapose_train::motion_eval::{Scene, H36M_RATE_HZ};
use blapose_train::synth::FRAME_DIM;
use blapose_train::TrainError;
use serde::Serialize;

/// One scored candidate.
#[derive(Debug, Clone, Serialize)]
pub struct Row {
    /// What was scored.
    pub candidate: String,
    /// Its metrics.
    pub report: MethodReport,
}

fn kalman(q: f64, r: f64) -> CausalSmoothing {
    CausalSmoothing::Kalman(KalmanParams {
        process_noise: q,
        measurement_noise: r,
    })
}

fn one_euro(min_cutoff_hz: f64, beta: f64) -> CausalSmoothing {
    CausalSmoothing::OneEuro(OneEuroParams {
        min_cutoff_hz,
        beta,
        derivative_cutoff_hz: 1.0,
    })
}

/// The causal direction filters measured, by name.
pub fn causal_direction_candidates() -> Vec<(String, Option<CausalSmoothing>)> {
    let mut v: Vec<(String, Option<CausalSmoothing>)> = vec![("none".into(), None)];
    for (mc, beta) in [(0.5, 0.5), (1.0, 0.5), (1.0, 2.0), (2.0, 1.0), (3.0, 2.0)] {
        v.push((
            format!("one-euro min {mc} Hz beta {beta}"),
            Some(one_euro(mc, beta)),
        ));
    }
    for q in [0.3, 1.0, 3.0, 10.0] {
        for r in [1e-4, 4e-4, 1.6e-3] {
            v.push((format!("kalman q {q} r {r:e}"), Some(kalman(q, r))));
        }
    }
    v
}

/// The causal root filters measured.
pub fn causal_root_candidates() -> Vec<(String, Option<CausalSmoothing>)> {
    let mut v: Vec<(String, Option<CausalSmoothing>)> = vec![("none".into(), None)];
    for q in [0.1, 1.0, 10.0] {
        for r in [0.01, 0.04] {
            v.push((format!("kalman q {q} r {r}"), Some(kalman(q, r))));
        }
    }
    v
}

/// The offline stages measured (directions, root, feet).
pub fn offline_candidates() -> Vec<(String, OfflineMotionConfig)> {
    let base = served_offline(H36M_RATE_HZ);
    let mut v = Vec::new();
    let dirs = |d: Option<OfflineSmoothing>| OfflineMotionConfig {
        directions: d,
        ..base
    };
    v.push(("directions none".into(), dirs(None)));
    for cutoff_hz in [1.5, 2.0, 3.0, 4.0, 6.0] {
        v.push((
            format!("directions butterworth 4 {cutoff_hz} Hz"),
            dirs(Some(OfflineSmoothing::Butterworth {
                order: 4,
                cutoff_hz,
            })),
        ));
    }
    for window_s in [0.3, 0.5, 0.7] {
        for degree in [2, 3] {
            v.push((
                format!("directions savgol {window_s} s degree {degree}"),
                dirs(Some(OfflineSmoothing::SavitzkyGolay { window_s, degree })),
            ));
        }
    }
    for q in [0.3, 1.0, 3.0] {
        v.push((
            format!("directions rts q {q} r 4e-4"),
            dirs(Some(OfflineSmoothing::Rts(KalmanParams {
                process_noise: q,
                measurement_noise: 4e-4,
            }))),
        ));
    }
    for (name, root) in [
        ("root none", None),
        (
            "root butterworth 4 0.5 Hz",
            Some(OfflineSmoothing::Butterworth {
                order: 4,
                cutoff_hz: 0.5,
            }),
        ),
        (
            "root butterworth 4 2 Hz",
            Some(OfflineSmoothing::Butterworth {
                order: 4,
                cutoff_hz: 2.0,
            }),
        ),
    ] {
        v.push((name.into(), OfflineMotionConfig { root, ..base }));
    }
    v.push((
        "feet not held".into(),
        OfflineMotionConfig { feet: None, ..base },
    ));
    v
}

/// Joint sets for the root solve: weight 1 for the listed joints.
pub fn root_joint_sets() -> Vec<(&'static str, [f64; NUM_JOINTS])> {
    let only = |joints: &[usize]| -> [f64; NUM_JOINTS] {
        std::array::from_fn(|j| if joints.contains(&j) { 1.0 } else { 0.0 })
    };
    vec![
        ("all joints", [1.0; NUM_JOINTS]),
        (
            "limbs and hips",
            only(&[1, 2, 3, 4, 5, 6, 11, 12, 13, 14, 15, 16]),
        ),
        ("legs and shoulders", only(&[1, 2, 3, 4, 5, 6, 11, 14])),
        (
            "no head",
            only(&[0, 1, 2, 3, 4, 5, 6, 7, 8, 11, 12, 13, 14, 15, 16]),
        ),
    ]
}

/// `input` (`frames * 34`) through a causal filter, frame by frame.
pub fn prefiltered(input: &[f32], smoothing: CausalSmoothing) -> Vec<f32> {
    let mut bank = ChannelFilter::new(smoothing, H36M_RATE_HZ);
    input
        .chunks_exact(FRAME_DIM)
        .flat_map(|frame| {
            let mut v: Vec<f64> = frame.iter().map(|&x| x as f64).collect();
            bank.step(&mut v);
            v.into_iter().map(|x| x as f32).collect::<Vec<_>>()
        })
        .collect()
}

/// The normal equations of the learned causal filter
/// ([`blapose_core::motion::fir`]) over `trials`: the lifter's poses
/// (`lifted`) adjusted with `lengths` (per trial and frame), against the
/// true directions.
pub fn fir_fit(
    trials: &[LifterSequence],
    lifted: &Lifted,
    lengths: &[Vec<blapose_core::BoneLengths>],
) -> Result<FirFit, TrainError> {
    use blapose_core::bones::{adjust_sequence_per_frame, ZeroBonePolicy};
    let mut fit = FirFit::default();
    for (t, l) in trials.iter().zip(lengths) {
        let pred = lifted
            .get(&key(t))
            .ok_or_else(|| TrainError::Data("trial not lifted".into()))?;
        let adjusted = adjust_sequence_per_frame(pred, l, ZeroBonePolicy::KeepInput)?;
        let mut input = Vec::new();
        let mut target = Vec::new();
        for (p, g) in adjusted.iter().zip(&t.target) {
            if let (Some(x), Some(y)) = (direction_values(p), direction_values(g)) {
                input.extend(x);
                target.extend(y);
            }
        }
        fit.add(&input, &target, DIRECTION_CHANNELS);
    }
    Ok(fit)
}

/// Everything the sweep reuses across candidates.
pub struct Sweep<'a> {
    /// The trials.
    pub trials: &'a [LifterSequence],
    /// Lengths to adjust with.
    pub adjusters: Adjusters<'a>,
}

/// Lifted poses by trial.
pub type Lifted = HashMap<(String, String, String), Vec<Pose>>;

/// A trial's key in [`Lifted`].
pub fn key(t: &LifterSequence) -> (String, String, String) {
    (
        t.trial.subject.clone(),
        t.trial.sequence.clone(),
        t.trial.camera.clone(),
    )
}

/// Every trial of `trials` lifted by `lift`, cached.
pub fn lift_all(
    trials: &[LifterSequence],
    lift: &(dyn Fn(&LifterSequence) -> Result<Vec<Pose>, TrainError> + Sync),
) -> Result<Lifted, TrainError> {
    use rayon::prelude::*;
    trials.par_iter().map(|t| Ok((key(t), lift(t)?))).collect()
}

impl Sweep<'_> {
    /// One evaluation over cached poses with these stages and scenes.
    pub fn evaluate(
        &self,
        lifted: &Lifted,
        scenes: &[Scene],
        causal: CausalMotionConfig,
        offline: OfflineMotionConfig,
    ) -> Result<blapose_train::eval_adjust::LifterReport, TrainError> {
        let lift = |t: &LifterSequence| -> Result<Vec<Pose>, TrainError> {
            lifted
                .get(&key(t))
                .cloned()
                .ok_or_else(|| TrainError::Data("trial not lifted".into()))
        };
        let adjusters = Adjusters {
            motion: Some(MotionSetup {
                scenes,
                causal,
                offline,
            }),
            ..self.adjusters
        };
        evaluate_lifter(self.trials, &lift, adjusters)
    }

    /// The served stages at Human3.6M's rate.
    pub fn served() -> (CausalMotionConfig, OfflineMotionConfig) {
        (served_causal(H36M_RATE_HZ), served_offline(H36M_RATE_HZ))
    }
}

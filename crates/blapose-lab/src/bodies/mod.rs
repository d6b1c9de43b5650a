//! The many-bodies cross-camera benchmark (`blapose-lab bodies`): does a
//! model read *this* person's bone lengths, or output one body for
//! everyone?
//!
//! Why: on Human3.6M's two test subjects a constant body already scores
//! well, and the four test cameras stand where the training cameras stood.
//! Here every individual of the held-out ANSUR II split
//! ([`blapose_train::ansur_split`], never drawn by training) is one trial
//! ([`trials`]):
//!
//! 1. its 16 lengths come from the ANSUR mapping, calibrated exactly as the
//!    training population ([`blapose_train::ansur`]; the survey's own
//!    spread, not a training run's `--ansur-spread`);
//! 2. it performs a clip of [`BodiesConfig::frames`] 50 Hz frames of one
//!    S9/S11 sequence (sequence and start drawn by the seed): directions
//!    and root trajectory from the mocap, lengths from the body, the
//!    lowest joint kept at its recorded height
//!    ([`blapose_train::synth::rebuild_on_floor`]: feet on the floor);
//! 3. a camera is drawn from the wide distribution
//!    ([`blapose_train::camera_range`]) until the whole clip is in the
//!    picture;
//! 4. the clip is projected (no distortion) and given real-detector noise:
//!    a random residual track of the training subjects' Stacked Hourglass
//!    detections ([`blapose_train::noise::ResidualBank`]), from a random
//!    start, rescaled to the person's depth;
//! 5. each model reads it as its weights' input contract says
//!    ([`blapose_model::input`], what the server does for a session): the
//!    calibration-free pair the normalized keypoints (input `none`), the
//!    camera-aware pair the keypoints prepared with the drawn camera's
//!    calibration (input `calibration`: rectified to the level camera and
//!    scaled to the floor). The online GRU's estimate is its running mean
//!    at the last frame.
//!
//! Scores per row ([`score`]): the mean over individuals of the mean
//! absolute error over the 16 bones; the same for the *prior*, the
//! population-mean body of the population training draws from (the
//! answer of a model that knows nothing about the person); their ratio; and
//! the *size slope*, the least-squares slope of the predicted against the
//! true sum of the 16 lengths over the individuals (1: reads sizes, 0: one
//! body for all); and the error *at the prior's size*, every estimate
//! rescaled to the prior's summed length, which scores its proportions
//! alone. Beside the models ([`references`]), rows `stature-regression`
//! with inputs `height` and `height+sex` ([`blapose_train::stature`],
//! fitted on the training split) answer from each individual's measured
//! ANSUR stature (and sex) alone: the bar a height-conditioned model has
//! to beat. Two *size oracles* (input `true size`) are given each
//! individual's true summed length: what reading size perfectly, and
//! proportion not at all, would score; a ratio below theirs needs
//! proportions read from the 2D. Everything is seeded: the same seed gives
//! the same individuals, clips, cameras and noise. The report and its
//! table are [`report`].

pub mod references;
pub mod report;
pub mod score;
pub mod trials;

use std::sync::Arc;
use std::time::Instant;

use blapose_core::bones::summed_length;
use blapose_core::BoneLengths;
use blapose_data::ansur::Sex;
use blapose_model::stature::StatureLines;
use blapose_train::ansur_split::{is_held_out, Person};
use blapose_train::camera_range::{wide_cameras, CameraRange};
use blapose_train::dataset::{decompose_sequence, subject_lengths};
use blapose_train::noise::ResidualBank;
use blapose_train::stature::StatureRegression;
use blapose_train::synth::MotionSequence;
use blapose_train::TrainError;

pub use report::{markdown, BodiesReport, TrialInfo};
pub use score::{mean_body, Baseline, BaselineName, Row, RowInput, RowModel};
pub use trials::{build_trials, Trial};

pub use crate::models::{BenchInput, BenchModel, SHIPPED_MODELS};
use crate::real_check::RealCheck;
use references::{fused_row, size_oracle_rows, stature_rows, FusionData};
use score::{baseline, row};
use trials::{estimate, statures};

/// Default seed of `blapose-lab bodies`.
pub const DEFAULT_SEED: u64 = 2026;
/// Default clip length (50 Hz frames: 10 s).
pub const DEFAULT_FRAMES: usize = 500;

/// What the benchmark runs on.
#[derive(Debug, Clone, PartialEq)]
pub struct BodiesConfig {
    /// Master seed.
    pub seed: u64,
    /// Frames per clip (50 Hz).
    pub frames: usize,
    /// Use only the first this many held-out individuals (`None`: all).
    pub limit: Option<usize>,
    /// The camera distribution.
    pub cameras: CameraRange,
}

impl Default for BodiesConfig {
    fn default() -> Self {
        Self {
            seed: DEFAULT_SEED,
            frames: DEFAULT_FRAMES,
            limit: None,
            cameras: wide_cameras(),
        }
    }
}

/// Everything the benchmark needs besides the models.
pub struct BodiesInput<'a> {
    /// Held-out people.
    pub people: Vec<&'a Person>,
    /// Test subjects' motion.
    pub motions: Vec<MotionSequence>,
    /// Training subjects' detector residuals.
    pub residuals: &'a ResidualBank,
    /// The prior body.
    pub prior: BoneLengths,
    /// The training subjects' mean lengths.
    pub training_mean: BoneLengths,
    /// The stature regression fitted on the training split
    /// ([`StatureRegression::fit_training`]): rows `stature-regression`
    /// (`height`, `height+sex`) after the models' (`None`: no such rows).
    pub stature: Option<&'a StatureRegression>,
    /// Training data to fit each model's height fusion
    /// ([`crate::height_fusion`]) on: rows
    /// `height` and `calibration+height` (`None`: no such rows).
    pub fit_set: Option<FitSet<'a>>,
    /// The training subjects' own real detections, to score the models and
    /// the stature regression on beside their synthetic rows (`None`: not
    /// checked).
    pub real_check: Option<RealCheck<'a>>,
}

/// What the height-fusion rows are fitted on: built like the benchmark,
/// but from training data only, so the held-out individuals and the test
/// subjects never enter the fit.
pub struct FitSet<'a> {
    /// ANSUR training-split people (never the held-out split).
    pub people: Vec<&'a Person>,
    /// The training subjects' motion (never S9/S11).
    pub motions: Vec<MotionSequence>,
    /// Seed of the fit trials (not the benchmark's).
    pub seed: u64,
}

/// Every `k`-th ANSUR training-split person of `everyone`, `n` at most,
/// for [`FitSet::people`]: never one of the held-out split, both sexes as
/// the survey has them.
pub fn fit_people(everyone: &[Person], n: usize) -> Vec<&Person> {
    let training: Vec<&Person> = everyone
        .iter()
        .filter(|p| !is_held_out(p.subject_id, p.sex))
        .collect();
    let step = (training.len() / n.max(1)).max(1);
    training.into_iter().step_by(step).take(n).collect()
}

/// Run the benchmark: build the trials, score every model and the
/// baselines.
pub fn run(
    input: &BodiesInput<'_>,
    models: &[BenchModel<'_>],
    cfg: &BodiesConfig,
) -> Result<BodiesReport, TrainError> {
    let t0 = Instant::now();
    let trials = build_trials(&input.people, &input.motions, input.residuals, cfg)?;
    let truth: Vec<BoneLengths> = trials.iter().map(|t| t.lengths).collect();
    let fusion = match &input.fit_set {
        Some(f) => {
            let fit_cfg = BodiesConfig {
                seed: f.seed,
                limit: None,
                ..cfg.clone()
            };
            let fit_trials = build_trials(&f.people, &f.motions, input.residuals, &fit_cfg)?;
            Some(FusionData {
                fit_statures: statures(&f.people, &fit_trials)?,
                fit_trials,
                test_statures: statures(&input.people, &trials)?,
            })
        }
        None => None,
    };
    let mut rows = Vec::with_capacity(models.len());
    let mut fused_rows = Vec::new();
    for m in models {
        let t = Instant::now();
        let pred = estimate(m, &trials)?;
        let mut r = row(m.kind.into(), m.input.into(), &pred, &truth, &input.prior)?;
        r.weights = m.path.clone();
        r.seconds = t.elapsed().as_secs_f64();
        if let Some(check) = &input.real_check {
            r.real_check_mm = Some(check.model_error(m)?);
        }
        rows.push(r);
        if let Some(data) = &fusion {
            fused_rows.push(fused_row(m, data, &pred, &truth, &input.prior)?);
        }
    }
    rows.extend(fused_rows);
    if let Some(reg) = input.stature {
        let pooled = StatureLines::from(&reg.pooled);
        let mut stature = stature_rows(reg, &input.people, &trials, &input.prior)?;
        if let Some(check) = &input.real_check {
            let error = check.matched_stature_error(&pooled)?;
            for r in stature.iter_mut().filter(|r| r.input == RowInput::Height) {
                r.real_check_mm = Some(error);
            }
        }
        rows.extend(stature);
        rows.extend(size_oracle_rows(&pooled, &truth, &input.prior)?);
    }
    let mut training_mean = baseline(
        BaselineName::TrainingMean,
        &input.training_mean,
        &truth,
        &input.prior,
    )?;
    if let Some(check) = &input.real_check {
        // In-sample there: these are the checked subjects' own mean.
        training_mean.real_check_mm = Some(check.constant_error(&input.training_mean)?);
    }
    let baselines = vec![
        baseline(BaselineName::Prior, &input.prior, &truth, &input.prior)?,
        training_mean,
    ];
    let used: Vec<&&Person> = input.people.iter().take(trials.len()).collect();
    let male = used.iter().filter(|p| p.sex == Sex::Male).count();
    Ok(BodiesReport {
        rows,
        baselines,
        individuals: trials.len(),
        male,
        female: trials.len() - male,
        frames_per_individual: cfg.frames,
        frames: trials.len() * cfg.frames,
        seed: cfg.seed,
        camera_distribution: cfg.cameras.clone(),
        prior_m: input.prior.to_vec(),
        protocol: "held-out ANSUR II individuals (ansur_split), lengths from the calibrated ANSUR \
                   mapping, retargeted onto an S9/S11 clip (feet on the floor), one camera each from \
                   camera_distribution (whole clip in frame), real-detector residual noise; error per \
                   individual = mean |pred - true| over 16 bones, averaged over individuals; GRU: \
                   running mean at the last frame; stature-regression: per-bone least squares on \
                   measured ANSUR stature (height+sex: one line per sex) over the ANSUR people \
                   outside the split, applied to each individual's measured stature; size_slope: \
                   least squares of predicted vs true sum of the 16 lengths"
            .into(),
        seconds: t0.elapsed().as_secs_f64(),
        real_check: input.real_check.as_ref().map(RealCheck::info),
        trials: trials
            .iter()
            .map(|t| TrialInfo {
                subject_id: t.subject_id,
                motion: t.motion.clone(),
                start: t.start,
                true_total_m: summed_length(&t.lengths),
                camera: t.camera.clone(),
            })
            .collect(),
    })
}

/// Decomposed test-subject sequences for [`BodiesInput::motions`].
pub fn test_motions(
    h36m: &blapose_data::h36m::H36m,
    subjects: &[&str],
) -> Result<Vec<MotionSequence>, TrainError> {
    let lengths = subject_lengths(h36m);
    let mut out = Vec::new();
    for (s, a, poses) in h36m.sequences() {
        if !subjects.contains(&s) || poses.len() < 2 {
            continue;
        }
        let l = *lengths
            .get(s)
            .ok_or_else(|| TrainError::Data(format!("no lengths for {s}")))?;
        out.push(decompose_sequence(s, a, poses, l, Arc::new(Vec::new()))?);
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use blapose_core::skeleton::NUM_BONES;

    #[test]
    fn the_fit_set_never_holds_a_held_out_person() {
        let everyone: Vec<Person> = (0..2000u64)
            .map(|i| Person {
                subject_id: i,
                sex: if i % 3 == 0 { Sex::Female } else { Sex::Male },
                stature_m: 1.7,
                lengths: [0.3; NUM_BONES],
            })
            .collect();
        let held_out = everyone
            .iter()
            .filter(|p| is_held_out(p.subject_id, p.sex))
            .count();
        assert!(held_out > 0, "the split holds some of them out");
        let fit = fit_people(&everyone, 500);
        assert_eq!(fit.len(), 500);
        assert!(fit.iter().all(|p| !is_held_out(p.subject_id, p.sex)));
        assert!(fit.iter().any(|p| p.sex == Sex::Female));
        assert!(fit.iter().any(|p| p.sex == Sex::Male));
    }

    #[test]
    fn inputs_keep_their_json_spelling() {
        assert_eq!(
            serde_json::to_value(BenchInput::None).unwrap(),
            serde_json::json!("none")
        );
        assert_eq!(
            RowInput::from(BenchInput::Calibration).name(),
            "calibration"
        );
    }
}

//! The many-bodies cross-camera benchmark (`blapose eval --benchmark
//! bodies`): does a model read *this* person's bone lengths, or output one
//! body for everyone?
//!
//! Why: on Human3.6M's two test subjects a constant body already scores
//! well, and the four test cameras stand where the training cameras stood.
//! Here every individual of the held-out ANSUR II split
//! ([`crate::ansur_split`], never drawn by training) is one trial:
//!
//! 1. its 16 lengths come from the ANSUR mapping, calibrated exactly as the
//!    training population ([`crate::ansur`]; the survey's own spread, not
//!    a training run's `--ansur-spread`);
//! 2. it performs a clip of [`BodiesConfig::frames`] 50 Hz frames of one
//!    S9/S11 sequence (sequence and start drawn by the seed): directions
//!    and root trajectory from the mocap, lengths from the body, the
//!    lowest joint kept at its recorded height
//!    ([`crate::synth::rebuild_on_floor`]: feet on the floor);
//! 3. a camera is drawn from the wide distribution
//!    ([`crate::bench_camera`]) until the whole clip is in the picture;
//! 4. the clip is projected (no distortion) and given real-detector noise:
//!    a random residual track of the training subjects' Stacked Hourglass
//!    detections ([`crate::noise::ResidualBank`]), from a random start,
//!    rescaled to the person's depth;
//! 5. each model reads it: the calibration-free pair the normalized
//!    keypoints (input `none`), the camera-aware pair the keypoints
//!    rectified with the drawn camera's calibration
//!    ([`blapose_core::level::LevelCamera::from_camera`], what the server
//!    does for a calibrated session; estimates scaled by the camera height
//!    when the weights are height-normalized, as the server does). The
//!    online GRU's estimate is its running mean at the last frame.
//!
//! Scores per row ([`row`], [`score`]): the mean over individuals of the mean
//! absolute error over the 16 bones; the same for the *prior*, the
//! population-mean body of the population training draws from (the
//! answer of a model that knows nothing about the person); their ratio; and
//! the *size slope*, the least-squares slope of the predicted against the
//! true sum of the 16 lengths over the individuals (1: reads sizes, 0: one
//! body for all); and the error *at the prior's size*, every estimate
//! rescaled to the prior's summed length, which scores its proportions
//! alone. Beside the models, rows `stature-regression` with
//! inputs `height` and `height+sex` ([`crate::stature`], fitted on the
//! training split) answer from each individual's measured ANSUR stature
//! (and sex) alone: the bar a height-conditioned model has to beat. Two
//! *size oracles* ([`size_oracle_rows`], input `true size`) are given each
//! individual's true summed length: what reading size perfectly, and
//! proportion not at all, would score; a ratio below theirs needs
//! proportions read from the 2D.
//! Everything is seeded: the same seed gives the same
//! individuals, clips, cameras and noise.

use std::sync::Arc;
use std::time::Instant;

use blapose_core::bones::summed_length;
use blapose_core::level::{height_scale, LevelCamera};
use blapose_core::skeleton::NUM_BONES;
use blapose_core::{BoneLengths, Keypoints2d, Pose};
use blapose_model::{LoadedWeights, ModelKind};
use rand::Rng;
use serde::Serialize;

use crate::ansur_split::Person;
use crate::bench_camera::{draw_camera_seeing, CameraRange, DrawnCamera};
use crate::dataset::EvalSequence;
use crate::error::TrainError;
use crate::eval::{trial_error_mm, BiGruEstimator, GruEstimator, LengthEstimator};
use crate::height_fusion::HeightFusion;
use crate::noise::{apply_residual, residual_at, ResidualBank};
use crate::real_check::{RealCheck, RealCheckInfo};
use crate::stature::{matched_lengths, StatureInput, StatureRegression};
use crate::synth::{rebuild_on_floor, sample_rng, MotionSequence};
use crate::train::trained_config;
use blapose_model::stature::StatureLines;

/// Default seed of `--benchmark bodies`.
pub const DEFAULT_SEED: u64 = 2026;
/// Default clip length (50 Hz frames: 10 s).
pub const DEFAULT_FRAMES: usize = 500;
/// Camera draws per clip before another clip is drawn.
const CAMERA_TRIES: usize = 200;
/// Clips drawn per individual before giving up.
const CLIP_TRIES: usize = 20;

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
            cameras: crate::bench_camera::wide_cameras(),
        }
    }
}

/// Which keypoints a model reads (`input` in the JSON rows).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum BenchInput {
    /// Normalized keypoints, no calibration (the default pair).
    None,
    /// Keypoints rectified with the camera's calibration (camera-aware pair).
    Calibration,
}

impl BenchInput {
    /// The JSON spelling.
    pub fn name(self) -> &'static str {
        match self {
            Self::None => "none",
            Self::Calibration => "calibration",
        }
    }
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

/// One individual's trial: truth, clip, camera and both inputs.
#[derive(Debug, Clone)]
pub struct Trial {
    /// The survey id.
    pub subject_id: u64,
    /// True lengths (metres).
    pub lengths: BoneLengths,
    /// Motion: `"S9/Walking 1"`.
    pub motion: String,
    /// First frame of the clip.
    pub start: usize,
    /// The camera.
    pub camera: DrawnCamera,
    /// Normalized keypoints (`frames * 34`).
    pub plain: Vec<f32>,
    /// The same, rectified with the camera's calibration.
    pub rectified: Vec<f32>,
}

/// Build every individual's trial (see the module docs). `motions` are the
/// test subjects' decomposed sequences (their own lengths in
/// [`MotionSequence::lengths`]); `residuals` the training subjects' noise.
pub fn build_trials(
    people: &[&Person],
    motions: &[MotionSequence],
    residuals: &ResidualBank,
    cfg: &BodiesConfig,
) -> Result<Vec<Trial>, TrainError> {
    cfg.cameras.validate()?;
    if cfg.frames == 0 {
        return Err(TrainError::InvalidArgument(
            "clip length must be positive".into(),
        ));
    }
    let usable: Vec<&MotionSequence> = motions.iter().filter(|m| m.len() >= cfg.frames).collect();
    if usable.is_empty() {
        return Err(TrainError::Data(format!(
            "no test sequence has {} frames",
            cfg.frames
        )));
    }
    if residuals.frames() == 0 {
        return Err(TrainError::Data("the residual bank is empty".into()));
    }
    let n = cfg.limit.map_or(people.len(), |l| l.min(people.len()));
    use rayon::prelude::*;
    people[..n]
        .par_iter()
        .enumerate()
        .map(|(i, p)| trial(p, &usable, residuals, cfg, i as u64))
        .collect()
}

fn trial(
    person: &Person,
    motions: &[&MotionSequence],
    residuals: &ResidualBank,
    cfg: &BodiesConfig,
    index: u64,
) -> Result<Trial, TrainError> {
    let mut rng = sample_rng(cfg.seed, 0, index);
    for _ in 0..CLIP_TRIES {
        let m = motions[rng.random_range(0..motions.len())];
        let start = rng.random_range(0..=m.len() - cfg.frames);
        let world: Vec<Pose> = (start..start + cfg.frames)
            .map(|f| rebuild_on_floor(m.roots[f], &m.dirs[f], &person.lengths, &m.lengths))
            .collect();
        let Ok(camera) = draw_camera_seeing(&cfg.cameras, &world, CAMERA_TRIES, &mut rng) else {
            continue;
        };
        let cam = &camera.camera;
        let k = cam.normalized_intrinsics();
        let level = LevelCamera::from_camera(cam)
            .map_err(|e| TrainError::Data(format!("benchmark camera: {e}")))?;
        let track = residuals
            .random_track(&mut rng)
            .ok_or_else(|| TrainError::Data("the residual bank is empty".into()))?;
        let offset = rng.random_range(0..=track.len().saturating_sub(cfg.frames));
        let mut plain = Vec::with_capacity(cfg.frames * 34);
        let mut rectified = Vec::with_capacity(cfg.frames * 34);
        for (t, p) in world.iter().enumerate() {
            let c = cam.world_to_camera_pose(p);
            let mut kp: Keypoints2d = k.project_pose(&c);
            // Short tracks repeat their last frame (residual_at clamps).
            let r = residual_at(track, (offset + t) as f32);
            apply_residual(&mut kp, &r, c[0][2], k.focal);
            plain.extend(kp.iter().flatten());
            rectified.extend(level.rectify(&kp).iter().flatten());
        }
        return Ok(Trial {
            subject_id: person.subject_id,
            lengths: person.lengths,
            motion: format!("{}/{}", m.subject, m.action),
            start,
            camera,
            plain,
            rectified,
        });
    }
    Err(TrainError::Data(format!(
        "no clip of individual {} could be framed by the camera range",
        person.subject_id
    )))
}

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

/// Whether weights were trained with height-normalized targets (their
/// `train_config`); such estimates are scaled by the camera height, as the
/// server does.
pub fn height_normalized(weights: &LoadedWeights) -> bool {
    trained_config(weights).is_some_and(|c| c.height_normalized)
}

/// Whether weights read floor-scaled rectified keypoints (their
/// `train_config`; [`blapose_core::level::scale_to_floor`]).
pub fn floor_scaled(weights: &LoadedWeights) -> bool {
    trained_config(weights).is_some_and(|c| c.floor_scaled)
}

/// One model's final estimate per trial.
pub fn estimate(model: &BenchModel<'_>, trials: &[Trial]) -> Result<Vec<BoneLengths>, TrainError> {
    let floor = model.input == BenchInput::Calibration && floor_scaled(model.weights);
    let streams: Vec<EvalSequence> = trials
        .iter()
        .map(|t| EvalSequence {
            subject: t.subject_id.to_string(),
            sequence: t.motion.clone(),
            camera: "benchmark".into(),
            input: match model.input {
                BenchInput::None => t.plain.clone(),
                BenchInput::Calibration if floor => {
                    scaled_to_floor(&t.rectified, t.camera.height_m as f32)
                }
                BenchInput::Calibration => t.rectified.clone(),
            },
            gt: t.lengths,
        })
        .collect();
    let est = match model.kind {
        ModelKind::Gru => GruEstimator::new(model.weights)?.estimate(&streams)?,
        ModelKind::BiGru => BiGruEstimator::new(model.weights)?.estimate(&streams)?,
    };
    let scaled = model.input == BenchInput::Calibration && height_normalized(model.weights);
    Ok(est
        .into_iter()
        .zip(trials)
        .map(|(e, t)| {
            if scaled {
                let k = height_scale(t.camera.height_m) as f32;
                e.lengths.map(|l| l * k)
            } else {
                e.lengths
            }
        })
        .collect())
}

/// Rectified frames (`17 * 2` values each) from a camera `camera_height`
/// metres up, scaled to the floor.
fn scaled_to_floor(rectified: &[f32], camera_height: f32) -> Vec<f32> {
    rectified
        .chunks_exact(2 * blapose_core::NUM_JOINTS)
        .flat_map(|f| {
            let kp: Keypoints2d = std::array::from_fn(|j| [f[2 * j], f[2 * j + 1]]);
            blapose_core::level::scale_to_floor(&kp, camera_height)
                .into_iter()
                .flatten()
        })
        .collect()
}

/// The scores of one set of predictions.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Score {
    /// Mean over individuals of the mean |pred - true| over 16 bones, mm.
    pub mean_bone_error_mm: f64,
    /// Per bone, mean over individuals, mm.
    pub per_bone_mm: Vec<f64>,
    /// Least-squares slope of predicted against true total length.
    pub size_slope: f64,
}

/// Least-squares slope of `y` against `x` (`None` with fewer than two
/// points or no spread in `x`).
pub fn slope(x: &[f64], y: &[f64]) -> Option<f64> {
    if x.len() != y.len() || x.len() < 2 {
        return None;
    }
    let n = x.len() as f64;
    let mx = x.iter().sum::<f64>() / n;
    let my = y.iter().sum::<f64>() / n;
    let sxx: f64 = x.iter().map(|v| (v - mx).powi(2)).sum();
    let sxy: f64 = x.iter().zip(y).map(|(a, b)| (a - mx) * (b - my)).sum();
    (sxx > 0.0 && sxx.is_finite()).then(|| sxy / sxx)
}

/// Score predictions against the truth (same order, at least two
/// individuals of different total length).
pub fn score(pred: &[BoneLengths], truth: &[BoneLengths]) -> Result<Score, TrainError> {
    if pred.len() != truth.len() || pred.is_empty() {
        return Err(TrainError::InvalidArgument(format!(
            "{} predictions for {} individuals",
            pred.len(),
            truth.len()
        )));
    }
    let n = pred.len() as f64;
    let size_slope = slope(
        &truth.iter().map(summed_length).collect::<Vec<_>>(),
        &pred.iter().map(summed_length).collect::<Vec<_>>(),
    )
    .ok_or_else(|| {
        TrainError::InvalidArgument("size slope needs individuals of different sizes".into())
    })?;
    Ok(Score {
        mean_bone_error_mm: pred
            .iter()
            .zip(truth)
            .map(|(p, t)| trial_error_mm(p, t))
            .sum::<f64>()
            / n,
        per_bone_mm: (0..NUM_BONES)
            .map(|b| {
                pred.iter()
                    .zip(truth)
                    .map(|(p, t)| f64::from((p[b] - t[b]).abs()) * 1000.0)
                    .sum::<f64>()
                    / n
            })
            .collect(),
        size_slope,
    })
}

/// One row of the benchmark (the JSON schema, plus where the
/// weights came from and how long the model took).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Row {
    /// `gru` or `bigru`.
    pub model: String,
    /// `none` or `calibration`.
    pub input: String,
    /// The model's error, mm.
    pub mean_bone_error_mm: f64,
    /// The prior's error on the same individuals, mm.
    pub prior_mean_bone_error_mm: f64,
    /// `mean_bone_error_mm / prior_mean_bone_error_mm`.
    pub ratio_to_prior: f64,
    /// Predicted against true total length (1 reads sizes, 0 one body).
    pub size_slope: f64,
    /// The error of every estimate rescaled to the prior's summed length,
    /// mm: its proportions alone, to read beside the prior's error (the
    /// prior's own proportions score exactly that).
    pub at_prior_size_mm: f64,
    /// Per bone, mm ([`blapose_core::skeleton::BONE_NAMES`] order).
    pub per_bone_mm: Vec<f64>,
    /// Weights file.
    pub weights: String,
    /// Seconds of the model pass.
    pub seconds: f64,
    /// The same answer's error on the training subjects' own real
    /// detections, mm ([`crate::real_check`]; absent where not measured).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub real_check_mm: Option<f64>,
}

/// A constant answer scored like a model.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Baseline {
    /// What it is.
    pub name: String,
    /// Its lengths (metres).
    pub lengths_m: Vec<f32>,
    /// Its error, mm.
    pub mean_bone_error_mm: f64,
    /// Against the prior.
    pub ratio_to_prior: f64,
    /// Per bone, mm.
    pub per_bone_mm: Vec<f64>,
    /// Its error on the training subjects' own real detections, mm
    /// ([`crate::real_check`]; absent where not measured).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub real_check_mm: Option<f64>,
}

/// The mean body of a population (the prior).
pub fn mean_body(people: &[BoneLengths]) -> Option<BoneLengths> {
    if people.is_empty() {
        return None;
    }
    let n = people.len() as f64;
    Some(std::array::from_fn(|b| {
        (people.iter().map(|p| f64::from(p[b])).sum::<f64>() / n) as f32
    }))
}

/// A model's row: its score beside the prior's on the same individuals.
pub fn row(
    model: &str,
    input: BenchInput,
    pred: &[BoneLengths],
    truth: &[BoneLengths],
    prior: &BoneLengths,
) -> Result<Row, TrainError> {
    named_row(model, input.name(), pred, truth, prior)
}

/// [`row`] with any `input` spelling (the stature regression's `height`,
/// `height+sex`).
pub fn named_row(
    model: &str,
    input: &str,
    pred: &[BoneLengths],
    truth: &[BoneLengths],
    prior: &BoneLengths,
) -> Result<Row, TrainError> {
    let s = score(pred, truth)?;
    let prior_mm = prior_error(truth, prior)?;
    let prior_total = summed_length(prior);
    let at_prior_size = pred
        .iter()
        .map(|p| scaled_to(p, prior_total))
        .collect::<Result<Vec<_>, _>>()?;
    Ok(Row {
        model: model.into(),
        input: input.into(),
        mean_bone_error_mm: s.mean_bone_error_mm,
        prior_mean_bone_error_mm: prior_mm,
        ratio_to_prior: s.mean_bone_error_mm / prior_mm,
        size_slope: s.size_slope,
        at_prior_size_mm: score(&at_prior_size, truth)?.mean_bone_error_mm,
        per_bone_mm: s.per_bone_mm,
        weights: String::new(),
        seconds: 0.0,
        real_check_mm: None,
    })
}

fn prior_error(truth: &[BoneLengths], prior: &BoneLengths) -> Result<f64, TrainError> {
    if truth.is_empty() {
        return Err(TrainError::InvalidArgument("no individuals".into()));
    }
    let e = truth.iter().map(|t| trial_error_mm(prior, t)).sum::<f64>() / truth.len() as f64;
    if e > 0.0 {
        Ok(e)
    } else {
        Err(TrainError::InvalidArgument(
            "every individual is the prior body: no ratio".into(),
        ))
    }
}

/// A constant baseline's entry.
pub fn baseline(
    name: &str,
    lengths: &BoneLengths,
    truth: &[BoneLengths],
    prior: &BoneLengths,
) -> Result<Baseline, TrainError> {
    let prior_mm = prior_error(truth, prior)?;
    let n = truth.len() as f64;
    let e = truth
        .iter()
        .map(|t| trial_error_mm(lengths, t))
        .sum::<f64>()
        / n;
    Ok(Baseline {
        name: name.into(),
        lengths_m: lengths.to_vec(),
        mean_bone_error_mm: e,
        ratio_to_prior: e / prior_mm,
        per_bone_mm: (0..NUM_BONES)
            .map(|b| {
                truth
                    .iter()
                    .map(|t| f64::from((lengths[b] - t[b]).abs()) * 1000.0)
                    .sum::<f64>()
                    / n
            })
            .collect(),
        real_check_mm: None,
    })
}

/// One trial in the report (what each individual saw).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct TrialInfo {
    /// Survey id.
    pub subject_id: u64,
    /// Motion.
    pub motion: String,
    /// First frame.
    pub start: usize,
    /// True total length (metres).
    pub true_total_m: f64,
    /// The camera.
    pub camera: DrawnCamera,
}

/// The whole report (`--json`): `rows` as the issue defines them, and
/// everything needed to read and reproduce them.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct BodiesReport {
    /// One row per (model, input).
    pub rows: Vec<Row>,
    /// Constant answers: the prior and the training subjects' mean.
    pub baselines: Vec<Baseline>,
    /// Individuals (held-out ANSUR people).
    pub individuals: usize,
    /// Of which male.
    pub male: usize,
    /// Of which female.
    pub female: usize,
    /// Frames per individual (50 Hz).
    pub frames_per_individual: usize,
    /// Frames read per model.
    pub frames: usize,
    /// Master seed.
    pub seed: u64,
    /// The camera distribution.
    pub camera_distribution: CameraRange,
    /// The prior (population-mean body of the training population), metres.
    pub prior_m: Vec<f32>,
    /// How the rows are computed.
    pub protocol: String,
    /// Wall-clock seconds of the whole benchmark (data loading included
    /// when the caller sets it).
    pub seconds: f64,
    /// Per individual: motion, camera, true size.
    pub trials: Vec<TrialInfo>,
    /// What the real-detection check ran on (`None`: not run).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub real_check: Option<RealCheckInfo>,
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
    /// Training data to fit each model's [`HeightFusion`] on: rows
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
        .filter(|p| !crate::ansur_split::is_held_out(p.subject_id, p.sex))
        .collect();
    let step = (training.len() / n.max(1)).max(1);
    training.into_iter().step_by(step).take(n).collect()
}

/// The `input` of a model's row given the person's stature.
fn with_height(input: BenchInput) -> &'static str {
    match input {
        BenchInput::None => "height",
        BenchInput::Calibration => "calibration+height",
    }
}

/// The person of each trial, in trial order: `people` and `trials` are in
/// the same order (the trials of `people[..trials.len()]`); a shorter or
/// misaligned `people` is an error.
fn trial_people<'a>(
    people: &[&'a Person],
    trials: &[Trial],
) -> Result<Vec<&'a Person>, TrainError> {
    if people.len() < trials.len() {
        return Err(TrainError::InvalidArgument(format!(
            "{} people for {} trials",
            people.len(),
            trials.len()
        )));
    }
    trials
        .iter()
        .zip(people)
        .map(|(t, &p)| {
            if p.subject_id == t.subject_id {
                Ok(p)
            } else {
                Err(TrainError::InvalidArgument(format!(
                    "person {} is not the individual of trial {}",
                    p.subject_id, t.subject_id
                )))
            }
        })
        .collect()
}

/// Each individual's stature, in trial order ([`trial_people`]).
fn statures(people: &[&Person], trials: &[Trial]) -> Result<Vec<f64>, TrainError> {
    Ok(trial_people(people, trials)?
        .iter()
        .map(|p| f64::from(p.stature_m))
        .collect())
}

/// The stature regression's rows: each individual's lengths predicted
/// from its measured stature (and sex), scored like a model. `people` and
/// `trials` are in the same order (the trials of `people[..trials.len()]`).
pub fn stature_rows(
    regression: &StatureRegression,
    people: &[&Person],
    trials: &[Trial],
    prior: &BoneLengths,
) -> Result<Vec<Row>, TrainError> {
    let people = trial_people(people, trials)?;
    let truth: Vec<BoneLengths> = trials.iter().map(|t| t.lengths).collect();
    let mut rows = Vec::with_capacity(StatureInput::ALL.len());
    for input in StatureInput::ALL {
        let t = Instant::now();
        let pred = people
            .iter()
            .map(|p| regression.predict(input, f64::from(p.stature_m), p.sex))
            .collect::<Result<Vec<_>, _>>()?;
        let mut r = named_row(
            crate::stature::MODEL_NAME,
            input.name(),
            &pred,
            &truth,
            prior,
        )?;
        r.weights = format!(
            "least squares on {} ANSUR II training-split people",
            regression.fitted_on.len()
        );
        r.seconds = t.elapsed().as_secs_f64();
        rows.push(r);
    }
    Ok(rows)
}

/// The size oracles' rows: each individual's lengths given its true
/// summed length for free, with the prior's proportions
/// ([`ORACLE_PRIOR`]) or the stature regression's at the matched stature
/// ([`ORACLE_REGRESSION`], [`crate::stature::matched_lengths`]). They read
/// the truth: they bound what a model that reads size perfectly and
/// proportion not at all can score, so a target below them needs
/// proportions read from the 2D.
pub fn size_oracle_rows(
    lines: &StatureLines,
    truth: &[BoneLengths],
    prior: &BoneLengths,
) -> Result<Vec<Row>, TrainError> {
    let scaled_prior = truth
        .iter()
        .map(|t| scaled_to(prior, summed_length(t)))
        .collect::<Result<Vec<_>, _>>()?;
    let regression = truth
        .iter()
        .map(|t| {
            matched_lengths(lines, t).ok_or_else(|| {
                TrainError::InvalidArgument("stature lines with no positive summed slope".into())
            })
        })
        .collect::<Result<Vec<_>, _>>()?;
    [
        (ORACLE_PRIOR, scaled_prior),
        (ORACLE_REGRESSION, regression),
    ]
    .into_iter()
    .map(|(model, pred)| {
        let mut r = named_row(model, ORACLE_INPUT, &pred, truth, prior)?;
        r.weights = "reads the truth: each individual's summed length".into();
        Ok(r)
    })
    .collect()
}

/// `l` with its proportions kept and its summed length set to `total`.
fn scaled_to(l: &BoneLengths, total: f64) -> Result<BoneLengths, TrainError> {
    let own = summed_length(l);
    if !(own > 0.0 && own.is_finite()) {
        return Err(TrainError::InvalidArgument(format!(
            "lengths summing to {own} m have no proportions"
        )));
    }
    let k = total / own;
    Ok(std::array::from_fn(|b| (f64::from(l[b]) * k) as f32))
}

/// Names of the size oracles' rows ([`size_oracle_rows`]).
pub const ORACLE_PRIOR: &str = "oracle: prior proportions";
/// See [`ORACLE_PRIOR`].
pub const ORACLE_REGRESSION: &str = "oracle: stature-regression proportions";
/// The `input` of the size oracles' rows.
pub const ORACLE_INPUT: &str = "true size";

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
    let fit_trials = match &input.fit_set {
        Some(f) => {
            let fit_cfg = BodiesConfig {
                seed: f.seed,
                limit: None,
                ..cfg.clone()
            };
            let fit_trials = build_trials(&f.people, &f.motions, input.residuals, &fit_cfg)?;
            let fit_statures = statures(&f.people, &fit_trials)?;
            Some((fit_trials, fit_statures, statures(&input.people, &trials)?))
        }
        None => None,
    };
    let mut rows = Vec::with_capacity(models.len());
    let mut fused_rows = Vec::new();
    for m in models {
        let t = Instant::now();
        let pred = estimate(m, &trials)?;
        let mut r = row(m.kind.as_str(), m.input, &pred, &truth, &input.prior)?;
        r.weights = m.path.clone();
        r.seconds = t.elapsed().as_secs_f64();
        if let Some(check) = &input.real_check {
            r.real_check_mm = Some(check.model_error(m)?);
        }
        rows.push(r);
        if let Some((fit_trials, fit_statures, test_statures)) = &fit_trials {
            let t = Instant::now();
            let fit_pred = estimate(m, fit_trials)?;
            let samples: Vec<_> = fit_statures
                .iter()
                .zip(&fit_pred)
                .zip(fit_trials)
                .map(|((&h, &e), tr)| (h, e, tr.lengths))
                .collect();
            let fusion = HeightFusion::fit(&samples)?;
            let fused: Vec<BoneLengths> = test_statures
                .iter()
                .zip(&pred)
                .map(|(&h, e)| fusion.predict(h, e))
                .collect();
            let mut r = named_row(
                m.kind.as_str(),
                with_height(m.input),
                &fused,
                &truth,
                &input.prior,
            )?;
            r.weights = format!(
                "{} + per-bone least squares on stature and the estimate over {} training-split \
                 people on training-subject motion (mean estimate weight {:.2})",
                m.path,
                fusion.people,
                fusion.mean_estimate_weight()
            );
            r.seconds = t.elapsed().as_secs_f64();
            fused_rows.push(r);
        }
    }
    rows.extend(fused_rows);
    if let Some(reg) = input.stature {
        let pooled = StatureLines::from(&reg.pooled);
        let mut stature = stature_rows(reg, &input.people, &trials, &input.prior)?;
        if let Some(check) = &input.real_check {
            let error = check.matched_stature_error(&pooled)?;
            for r in stature
                .iter_mut()
                .filter(|r| r.input == StatureInput::Height.name())
            {
                r.real_check_mm = Some(error);
            }
        }
        rows.extend(stature);
        rows.extend(size_oracle_rows(&pooled, &truth, &input.prior)?);
    }
    let mut training_mean = baseline(
        "training subjects' mean lengths",
        &input.training_mean,
        &truth,
        &input.prior,
    )?;
    if let Some(check) = &input.real_check {
        // In-sample there: these are the checked subjects' own mean.
        training_mean.real_check_mm = Some(check.constant_error(&input.training_mean)?);
    }
    let baselines = vec![
        baseline(
            "prior (training population mean)",
            &input.prior,
            &truth,
            &input.prior,
        )?,
        training_mean,
    ];
    let used: Vec<&&Person> = input.people.iter().take(trials.len()).collect();
    let male = used
        .iter()
        .filter(|p| p.sex == blapose_data::ansur::Sex::Male)
        .count();
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
    let lengths = crate::dataset::subject_lengths(h36m);
    let mut out = Vec::new();
    for (s, a, poses) in h36m.sequences() {
        if !subjects.contains(&s) || poses.len() < 2 {
            continue;
        }
        let l = *lengths
            .get(s)
            .ok_or_else(|| TrainError::Data(format!("no lengths for {s}")))?;
        out.push(crate::dataset::decompose_sequence(
            s,
            a,
            poses,
            l,
            Arc::new(Vec::new()),
        )?);
    }
    Ok(out)
}

/// The report as a markdown table: the models beside the baselines.
pub fn markdown(r: &BodiesReport) -> String {
    let mut s = format!(
        "## Many-bodies benchmark: {} held-out ANSUR II individuals ({} male, {} female), \
         {} frames each on S9/S11 motion, wide cameras, seed {}\n\n",
        r.individuals, r.male, r.female, r.frames_per_individual, r.seed
    );
    let check = r.real_check.is_some();
    s.push_str(
        "| model | input | mean bone error (mm) | prior (mm) | ratio to prior | size slope | \
         at prior size (mm) |",
    );
    s.push_str(if check {
        " training subjects' real SH (mm) |\n|---|---|---:|---:|---:|---:|---:|---:|\n"
    } else {
        "\n|---|---|---:|---:|---:|---:|---:|\n"
    });
    let real = |v: Option<f64>| match (check, v) {
        (false, _) => String::new(),
        (true, Some(v)) => format!(" {v:.2} |"),
        (true, None) => " - |".into(),
    };
    for row in &r.rows {
        s.push_str(&format!(
            "| {} | {} | {:.2} | {:.2} | {:.3} | {:.3} | {:.2} |{}\n",
            row.model,
            row.input,
            row.mean_bone_error_mm,
            row.prior_mean_bone_error_mm,
            row.ratio_to_prior,
            row.size_slope,
            row.at_prior_size_mm,
            real(row.real_check_mm)
        ));
    }
    let prior_mm = r
        .baselines
        .first()
        .map_or(f64::NAN, |b| b.mean_bone_error_mm);
    for b in &r.baselines {
        s.push_str(&format!(
            "| baseline: {} | - | {:.2} | {:.2} | {:.3} | 0 | - |{}\n",
            b.name,
            b.mean_bone_error_mm,
            prior_mm,
            b.ratio_to_prior,
            real(b.real_check_mm)
        ));
    }
    if let Some(c) = &r.real_check {
        s.push_str(&format!(
            "\nReal-detection check: {} trials ({} frames) of {}'s Stacked Hourglass detections \
             with their true lengths (training data; camera-aware models read them with each \
             view's calibration; the stature regression with each subject's matched stature, \
             which reads the truth).\n",
            c.trials,
            c.frames,
            c.subjects.join(", ")
        ));
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_fit_set_never_holds_a_held_out_person() {
        use blapose_data::ansur::Sex;
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
            .filter(|p| crate::ansur_split::is_held_out(p.subject_id, p.sex))
            .count();
        assert!(held_out > 0, "the split holds some of them out");
        let fit = fit_people(&everyone, 500);
        assert_eq!(fit.len(), 500);
        assert!(fit
            .iter()
            .all(|p| !crate::ansur_split::is_held_out(p.subject_id, p.sex)));
        assert!(fit.iter().any(|p| p.sex == Sex::Female));
        assert!(fit.iter().any(|p| p.sex == Sex::Male));
    }

    #[test]
    fn slope_and_ratio_on_a_hand_made_case() {
        // Three individuals, bones all equal: totals 16*0.2, 16*0.25, 16*0.3.
        let truth: Vec<BoneLengths> = [0.20f32, 0.25, 0.30].map(|v| [v; NUM_BONES]).to_vec();
        // A model that reads half the size difference around 0.25.
        let pred: Vec<BoneLengths> = [0.225f32, 0.25, 0.275].map(|v| [v; NUM_BONES]).to_vec();
        let prior = [0.25f32; NUM_BONES];
        let r = row("bigru", BenchInput::None, &pred, &truth, &prior).unwrap();
        assert!((r.size_slope - 0.5).abs() < 1e-4, "{}", r.size_slope);
        // Errors: 25, 0, 25 mm -> 16.67; prior 50, 0, 50 -> 33.33; ratio 0.5.
        assert!((r.mean_bone_error_mm - 50.0 / 3.0).abs() < 1e-3);
        assert!((r.prior_mean_bone_error_mm - 100.0 / 3.0).abs() < 1e-3);
        assert!((r.ratio_to_prior - 0.5).abs() < 1e-4);
        assert_eq!(r.per_bone_mm.len(), NUM_BONES);
        assert!((r.per_bone_mm[3] - 50.0 / 3.0).abs() < 1e-3);
        // A constant has slope 0 and is the prior's ratio when it is the prior.
        let c = row("gru", BenchInput::Calibration, &[prior; 3], &truth, &prior).unwrap();
        assert!(c.size_slope.abs() < 1e-12);
        assert!((c.ratio_to_prior - 1.0).abs() < 1e-12);
        let b = baseline("prior", &prior, &truth, &prior).unwrap();
        assert!((b.ratio_to_prior - 1.0).abs() < 1e-12);
        // The truth itself: slope 1, no error.
        let t = score(&truth, &truth).unwrap();
        assert!((t.size_slope - 1.0).abs() < 1e-9 && t.mean_bone_error_mm == 0.0);
    }

    #[test]
    fn the_size_oracles_get_the_size_exactly_and_only_the_size() {
        let prior: BoneLengths = std::array::from_fn(|b| 0.1 + 0.02 * b as f32);
        // Two individuals with the prior's proportions, one without.
        let mut odd = prior;
        odd[0] += 0.05;
        odd[1] -= 0.05;
        let truth = vec![prior.map(|v| v * 0.9), prior.map(|v| v * 1.1), odd];
        let lines = StatureLines {
            intercept: vec![0.01; NUM_BONES],
            slope: (0..NUM_BONES).map(|b| 0.05 + 0.002 * b as f64).collect(),
            people: 3,
        };
        let rows = size_oracle_rows(&lines, &truth, &prior).unwrap();
        assert_eq!(rows.len(), 2);
        let scaled = &rows[0];
        assert_eq!(scaled.model, ORACLE_PRIOR);
        // Exact on the first two; on the third only the two changed bones
        // (the sum is unchanged) miss, by 50 mm each.
        assert!((scaled.mean_bone_error_mm - 100.0 / 16.0 / 3.0).abs() < 1e-3);
        assert!((scaled.size_slope - 1.0).abs() < 1e-6);
        // At the prior's size, the prior's proportions are the prior.
        assert!((scaled.at_prior_size_mm - scaled.prior_mean_bone_error_mm).abs() < 1e-3);
        assert!(
            (rows[1].size_slope - 1.0).abs() < 1e-6,
            "matched stature reads the size"
        );
        assert!(rows[1].mean_bone_error_mm > 0.0);
    }

    #[test]
    fn degenerate_inputs_are_errors_not_panics() {
        let one = vec![[0.2f32; NUM_BONES]];
        assert!(score(&one, &one).is_err(), "one individual has no slope");
        assert!(score(&one, &[]).is_err());
        let same = vec![[0.2f32; NUM_BONES]; 3];
        assert!(row("gru", BenchInput::None, &same, &same, &[0.2; NUM_BONES]).is_err());
        assert_eq!(slope(&[1.0, 1.0], &[0.0, 2.0]), None);
        assert_eq!(mean_body(&[]), None);
        assert_eq!(BenchInput::Calibration.name(), "calibration");
        assert_eq!(
            serde_json::to_value(BenchInput::None).unwrap(),
            serde_json::json!("none")
        );
    }
}

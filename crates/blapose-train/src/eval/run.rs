//! One evaluation run on Human3.6M: the trials the flags select, a model
//! scored on them by the protocol beside the baselines, and the report
//! written where the flags ask.
//!
//! Why in the library: `blapose eval` (the product's evaluation of a
//! shipped model) and `blapose-lab diagnose` (the same run with research
//! diagnostics around it) share it, flags included ([`EvalRunArgs`]), so a
//! diagnostic number is always measured exactly as the product's.
//!
//! A run: [`EvalData::load`] reads every subject's poses (the true
//! lengths and the baselines), the evaluated subjects' data and their
//! trials (`--cameras`, `--every`); the caller may transform the trials
//! (the lab's diagnostics do); [`EvalData::at_rate`] resamples them to
//! `--fps`; [`EvalData::score`] runs a network's estimator on them with
//! `--flip-average` and `--calibrated`; [`EvalRunArgs::write`] writes
//! `--json` and `--plot`.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use blapose_core::camera::Camera;
use blapose_core::BoneLengths;
use blapose_data::h36m::{H36m, Parts, ALL_SUBJECTS, TRAIN_SUBJECTS};
use blapose_model::Precision;
use blapose_model::{LoadedWeights, ModelKind};
use serde::Serialize;

use super::LengthEstimator;
use super::{calibrate, evaluate, BiGruEstimator, EvalReport, FlipAveraged, GruEstimator};
use crate::cli::{camera_list, known_subjects};
use crate::dataset::{
    eval_sequences, mean_subject_lengths, subject_lengths, EvalSequence, InputKind, SOURCE_FPS,
};
use crate::error::TrainError;

/// The flags of an evaluation run (all but the model and its weights).
#[derive(clap::Args, Debug, Clone, PartialEq)]
pub struct EvalRunArgs {
    /// 2D input: sh (real Stacked Hourglass detections) or gt (projected ground truth).
    #[arg(long, value_enum, default_value_t = InputKind::Sh)]
    pub input: InputKind,
    /// Write the full report as JSON here.
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// Write the error-vs-frames plot (SVG) here (online GRU).
    #[arg(long)]
    pub plot: Option<PathBuf>,
    /// Subjects to evaluate (comma separated).
    #[arg(long, default_value = "S9,S11", value_delimiter = ',')]
    pub subjects: Vec<String>,
    /// Test-time flip: average the estimates of each trial and of its
    /// mirror image (twice the compute).
    #[arg(long)]
    pub flip_average: bool,
    /// Feed the model a stream of this many frames per second (the 50 Hz
    /// data linearly resampled; e.g. 25 or 60).
    #[arg(long, default_value_t = SOURCE_FPS)]
    pub fps: f32,
    /// Evaluate the trials of these cameras only (ids, comma separated;
    /// default all).
    #[arg(long, value_delimiter = ',')]
    pub cameras: Vec<String>,
    /// Evaluate as the server serves a session that sends its camera's
    /// calibration: every trial's keypoints undistorted (the detections
    /// are pixels of the distorted video; the protocol takes undistorted
    /// ones), then prepared as the weights' input contract says (rectified
    /// with the trial's camera, scaled to the floor when they were trained
    /// so). For camera-aware weights.
    #[arg(long)]
    pub calibrated: bool,
    /// Evaluate only every k-th trial (quick subsets; 1 = all).
    #[arg(long, default_value_t = 1)]
    pub every: usize,
    /// Data root (default: $BLAPOSE_DATA or ../shared/data).
    #[arg(long)]
    pub data: Option<PathBuf>,
    /// Storage precision of the fast engines' GRU weights (f32, f16 or
    /// bf16), to score a serving precision against f32.
    #[arg(long, default_value = "f32")]
    pub precision: Precision,
}

/// What a run reads besides its trials: the data, the true lengths and
/// the baselines.
pub struct EvalData {
    /// Every subject's poses (`ALL_SUBJECTS`, poses only): the true
    /// lengths, the baselines, the lab's stature proxy.
    pub all: H36m,
    /// The evaluated subjects' data (their cameras, their detections for
    /// `--input sh`).
    pub h36m: H36m,
    /// Every subject's true lengths.
    pub lengths: BTreeMap<String, BoneLengths>,
    /// The naive baselines, `(name, lengths)` predicted for every trial:
    /// the training subjects' mean and all seven subjects' mean.
    pub baselines: Vec<(&'static str, BoneLengths)>,
    /// The run's flags.
    pub args: EvalRunArgs,
}

impl EvalData {
    /// Load what `args` asks for: the data and the selected trials (every
    /// sequence and camera of the subjects, `--cameras` only, every
    /// `--every`-th), at 50 Hz.
    pub fn load(args: &EvalRunArgs) -> Result<(Self, Vec<EvalSequence>), TrainError> {
        let subjects = known_subjects(&args.subjects)?;
        let root = blapose_data::data_root(args.data.clone());
        let all = H36m::load(&root, &ALL_SUBJECTS, Parts::POSES)?;
        let lengths = subject_lengths(&all);
        let parts = if args.input == InputKind::Sh {
            Parts::ALL
        } else {
            Parts::POSES
        };
        let h36m = H36m::load(&root, &subjects, parts)?;
        let mut trials = eval_sequences(&h36m, &subjects, args.input, &lengths)?;
        if !args.cameras.is_empty() {
            trials.retain(|t| args.cameras.contains(&t.camera));
        }
        if args.every > 1 {
            trials = trials.into_iter().step_by(args.every).collect();
        }
        let mean_of = |names: &[&str]| {
            mean_subject_lengths(&lengths, names)
                .ok_or_else(|| TrainError::Data("missing subject lengths".into()))
        };
        let baselines = vec![
            ("training_mean", mean_of(&TRAIN_SUBJECTS)?),
            ("all_subjects_mean", mean_of(&ALL_SUBJECTS)?),
        ];
        let data = Self {
            all,
            h36m,
            lengths,
            baselines,
            args: args.clone(),
        };
        Ok((data, trials))
    }

    /// The calibration of an evaluated subject's camera.
    pub fn camera(&self, subject: &str, id: &str) -> Option<&Camera> {
        self.h36m.cameras.get(subject, id)
    }

    /// `trials` as streams of `--fps` frames per second; an error when no
    /// trial is left to evaluate.
    pub fn at_rate(&self, trials: Vec<EvalSequence>) -> Result<Vec<EvalSequence>, TrainError> {
        let trials = if self.args.fps == SOURCE_FPS {
            trials
        } else {
            trials
                .iter()
                .map(|t| t.resampled(self.args.fps))
                .collect::<Result<_, _>>()?
        };
        if trials.is_empty() {
            return Err(TrainError::InvalidArgument(format!(
                "no trials for subjects {} (cameras: {})",
                self.args.subjects.join(","),
                camera_list(&self.args.cameras)
            )));
        }
        Ok(trials)
    }

    /// A network of `kind` (its `estimator`, reading `weights` loaded from
    /// `path`) scored on `trials`, with the run's `--flip-average` and
    /// `--calibrated` ([`calibrate`]); the report's model label says
    /// which (`gru+flip+calibrated`).
    pub fn score(
        &self,
        kind: ModelKind,
        estimator: Box<dyn LengthEstimator>,
        weights: &LoadedWeights,
        path: &Path,
        mut trials: Vec<EvalSequence>,
    ) -> Result<EvalReport, TrainError> {
        let mut estimator = estimator;
        let mut label = kind.as_str().to_string();
        if self.args.flip_average {
            estimator = Box::new(FlipAveraged::new(estimator));
            label.push_str("+flip");
        }
        if self.args.calibrated {
            calibrate(weights, &mut trials, |s, id| self.camera(s, id))?;
            label.push_str("+calibrated");
        }
        self.evaluate(
            estimator.as_ref(),
            &trials,
            &label,
            &path.display().to_string(),
        )
    }

    /// The protocol ([`evaluate`]) on `trials` beside the run's baselines,
    /// the report labelled with `model` and `weights`.
    pub fn evaluate(
        &self,
        estimator: &dyn LengthEstimator,
        trials: &[EvalSequence],
        model: &str,
        weights: &str,
    ) -> Result<EvalReport, TrainError> {
        evaluate(
            estimator,
            trials,
            &self.baselines,
            model,
            self.args.input.name(),
            weights,
            &self.args.subjects,
        )
    }
}

/// The protocol's estimator of a network of `kind`: the offline Bi-GRU
/// over whole trials, or the online GRU's running mean, its weights stored
/// at `precision` in the engine.
pub fn network_estimator(
    kind: ModelKind,
    weights: &LoadedWeights,
    precision: Precision,
) -> Result<Box<dyn LengthEstimator>, TrainError> {
    Ok(match kind {
        ModelKind::BiGru => Box::new(BiGruEstimator::with_precision(weights, precision)?),
        ModelKind::Gru => Box::new(GruEstimator::with_precision(weights, precision)?),
    })
}

/// The line a run prints about the model pass: seconds, frames, rate.
pub fn model_pass(report: &EvalReport) -> String {
    format!(
        "model pass: {:.1}s for {} frames ({:.0} frames/s)",
        report.seconds,
        report.frames,
        report.frames as f64 / report.seconds.max(1e-9)
    )
}

impl EvalRunArgs {
    /// Write `json` (the report, or a diagnostic's report around it) to
    /// `--json` and `report`'s online error curve to `--plot`. Returns a
    /// note for the user about the plot: where it went, or that the
    /// offline model has no curve to plot.
    pub fn write(
        &self,
        report: &EvalReport,
        json: &impl Serialize,
    ) -> Result<Option<String>, TrainError> {
        if let Some(p) = &self.json {
            std::fs::write(p, serde_json::to_string_pretty(json)?)
                .map_err(|e| TrainError::io(p, e))?;
        }
        let Some(p) = &self.plot else {
            return Ok(None);
        };
        if report.curve.is_empty() {
            return Ok(Some(
                "no error curve for the offline model; plot not written".into(),
            ));
        }
        crate::plot::error_curve(report, p)?;
        Ok(Some(format!("plot: {}", p.display())))
    }
}

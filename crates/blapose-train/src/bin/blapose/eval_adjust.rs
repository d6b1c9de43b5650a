//! `blapose eval-adjust`: lifters scored on the test subjects before and
//! after the bone-length adjustment ([`blapose_train::eval_adjust`]),
//! beside the baselines that need no model (the training subjects' mean
//! lengths, the lifter's own running median). Why
//! its own module: it loads lifters and both bone-length models, which no
//! other command does.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result};
use blapose_core::motion::{served_causal, served_offline};
use blapose_core::BoneLengths;
use blapose_data::h36m::{H36m, Parts, TRAIN_SUBJECTS};
use blapose_model::stature::StatureModel;
use blapose_model::ModelKind;
use blapose_train::dataset::{mean_subject_lengths, subject_lengths};
use blapose_train::eval_adjust::{evaluate_lifter, markdown, LengthEstimates, MotionSetup};
use blapose_train::lifter::data::{lifter_sequences, LifterSequence};
use blapose_train::lifter::predict::StreamLifter;
use blapose_train::lifter::weights as lifter_weights;
use blapose_train::motion_eval::{Scene, H36M_RATE_HZ};

use crate::common::known_subjects;

/// Arguments of `blapose eval-adjust`.
#[derive(clap::Args, Debug)]
pub struct EvalAdjustArgs {
    /// Lifter weights written by `blapose train-lifter` (repeat or comma
    /// separate for several lifters).
    #[arg(long, required = true, value_delimiter = ',')]
    lifter_weights: Vec<PathBuf>,
    /// Online GRU weights ("none" to skip).
    #[arg(long, default_value = "models/bone_length_gru.safetensors")]
    gru_weights: PathBuf,
    /// Offline Bi-GRU weights ("none" to skip).
    #[arg(long, default_value = "models/bone_length_bigru.safetensors")]
    bigru_weights: PathBuf,
    /// Write the report as JSON here.
    #[arg(long)]
    json: Option<PathBuf>,
    /// Evaluate only every k-th trial (quick subsets; 1 = all).
    #[arg(long, default_value_t = 1)]
    every: usize,
    /// Subjects to evaluate (comma separated).
    #[arg(long, default_value = "S9,S11", value_delimiter = ',')]
    subjects: Vec<String>,
    /// Turn test-time flip off.
    #[arg(long)]
    no_flip: bool,
    /// The stature regression a known height is answered with (the
    /// `gru_motion_height` row).
    #[arg(long, default_value = "models/stature_regression.json")]
    stature_model: PathBuf,
    /// Skip the motion metrics and methods (acceleration, root placement,
    /// foot skating; `gru_motion`, `bigru_motion`, `ground_truth_lengths`).
    #[arg(long)]
    no_motion: bool,
    /// Data root (default: $BLAPOSE_DATA or ../shared/data).
    #[arg(long)]
    data: Option<PathBuf>,
}

/// `blapose eval-adjust`.
pub fn run(a: EvalAdjustArgs) -> Result<()> {
    let root = blapose_data::data_root(a.data.clone());
    let subjects = known_subjects(&a.subjects)?;
    let skip = |p: &PathBuf| p.as_os_str() == "none";
    let mut lifters = BTreeMap::new();
    for p in &a.lifter_weights {
        let l = lifter_weights::load(p)?;
        let mut name = l.metadata.arch.name();
        if lifters.contains_key(&name) {
            name = p
                .file_stem()
                .map_or(name.clone(), |s| s.to_string_lossy().into_owned());
        }
        anyhow::ensure!(!lifters.contains_key(&name), "two lifters named {name}");
        lifters.insert(name, (p.clone(), l));
    }
    let t0 = Instant::now();
    let (trials, scenes) = {
        let h36m = H36m::load(&root, &subjects, Parts::ALL)?;
        let mut trials = lifter_sequences(&h36m, &subjects)?;
        if a.every > 1 {
            trials = trials.into_iter().step_by(a.every).collect();
        }
        let scenes = trials
            .iter()
            .map(|t| Scene::build(&h36m, t))
            .collect::<Result<Vec<_>, _>>()?;
        (trials, scenes)
    };
    anyhow::ensure!(!trials.is_empty(), "no trials for {}", a.subjects.join(","));
    eprintln!(
        "loaded {} trials ({} frames) in {:.1}s",
        trials.len(),
        trials.iter().map(|t| t.frames()).sum::<usize>(),
        t0.elapsed().as_secs_f64()
    );
    let load = |path: &PathBuf, kind| -> Result<Option<blapose_model::weights::LoadedWeights>> {
        Ok(if skip(path) {
            None
        } else {
            Some(blapose_model::weights::load(path, kind)?)
        })
    };
    let training_mean = {
        let h36m = H36m::load(&root, &TRAIN_SUBJECTS, Parts::POSES)?;
        mean_subject_lengths(&subject_lengths(&h36m), &TRAIN_SUBJECTS)
            .ok_or_else(|| anyhow::anyhow!("no training-subject poses under {}", root.display()))?
    };
    let t = Instant::now();
    let mut estimates = LengthEstimates::compute(
        &trials,
        load(&a.gru_weights, ModelKind::Gru)?.as_ref(),
        load(&a.bigru_weights, ModelKind::BiGru)?.as_ref(),
    )?;
    estimates.training_mean = Some(training_mean);
    eprintln!(
        "bone-length estimates (online GRU running, offline Bi-GRU): {:.1}s",
        t.elapsed().as_secs_f64()
    );
    let height_lengths: Vec<BoneLengths> = if a.no_motion {
        Vec::new()
    } else {
        let text = std::fs::read_to_string(&a.stature_model)
            .with_context(|| format!("reading {}", a.stature_model.display()))?;
        let model = StatureModel::from_json(&text)?;
        trials
            .iter()
            .map(|t| {
                let stature = model.pooled.matched_stature(&t.trial.gt).ok_or_else(|| {
                    anyhow::anyhow!("the stature model's summed slope is not positive")
                })?;
                Ok(model.predict(stature, None))
            })
            .collect::<Result<_>>()?
    };
    let mut adjusters = estimates.adjusters();
    if !a.no_motion {
        adjusters.height = Some(&height_lengths);
        adjusters.motion = Some(MotionSetup {
            scenes: &scenes,
            causal: served_causal(H36M_RATE_HZ),
            offline: served_offline(H36M_RATE_HZ),
        });
    }
    let mut reports = BTreeMap::new();
    for (name, (path, l)) in &lifters {
        let t = Instant::now();
        let lifter = StreamLifter::new(l)?;
        let lift = |s: &LifterSequence| lifter.lift(&s.trial, !a.no_flip);
        let mut report = evaluate_lifter(&trials, &lift, adjusters)?;
        report.weights = Some(path.display().to_string());
        reports.insert(name.clone(), report);
        eprintln!(
            "{name}: lifted and scored in {:.1}s",
            t.elapsed().as_secs_f64()
        );
    }
    println!("{}", markdown(&reports));
    if let Some(p) = &a.json {
        std::fs::write(p, serde_json::to_string_pretty(&reports)?)?;
        eprintln!("json: {}", p.display());
    }
    Ok(())
}

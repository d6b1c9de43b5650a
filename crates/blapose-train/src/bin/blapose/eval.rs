//! `blapose eval`: which trials (subjects, cameras, every k-th, from which
//! frame, at which rate, rectified or not, with joints lost or not) and
//! which estimator (plain, flip-averaged, height-corrected) the flags ask
//! for; the protocol itself
//! is [`blapose_train::eval`]. Why here: these are choices of an
//! evaluation run, not of the protocol.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result};
use blapose_core::BoneLengths;
use blapose_data::h36m::{H36m, Parts, ALL_SUBJECTS, TRAIN_SUBJECTS};
use blapose_model::{LoadedWeights, ModelKind};
use blapose_train::dataset::{
    eval_sequences, mean_subject_lengths, rectify_streams, subject_lengths, EvalSequence, InputKind,
};
use blapose_train::eval::{
    evaluate, markdown, BiGruEstimator, EvalReport, FlipAveraged, GruEstimator, LengthEstimator,
};
use blapose_train::joint_dropout::{drop_joints, DropJointsReport};

use crate::bodies::{Benchmark, BodiesArgs};
use crate::common::{camera_list, known_subjects, ModelArg};

/// Arguments of `blapose eval`.
#[derive(clap::Args, Debug)]
pub struct EvalArgs {
    /// Model kind: gru (online, running mean) or bigru (offline).
    #[arg(
        long,
        value_enum,
        ignore_case = true,
        required_unless_present_any = ["benchmark", "stature_proxy"]
    )]
    model: Option<ModelArg>,
    /// 2D input: sh (real Stacked Hourglass detections) or gt (projected ground truth).
    #[arg(long, value_enum, default_value_t = InputKind::Sh)]
    input: InputKind,
    /// Weights file (safetensors written by `blapose train`).
    #[arg(long, required_unless_present_any = ["benchmark", "stature_proxy"])]
    weights: Option<PathBuf>,
    /// Run a benchmark instead of the Human3.6M protocol: `bodies`, the
    /// many-bodies cross-camera benchmark (held-out ANSUR II people on
    /// S9/S11 motion, wide cameras) of the four shipped models in
    /// --models-dir; see `blapose_train::bodies`.
    #[arg(long, value_enum, conflicts_with_all = ["model", "weights"])]
    benchmark: Option<Benchmark>,
    #[command(flatten)]
    bodies: BodiesArgs,
    /// Write the full report as JSON here.
    #[arg(long)]
    json: Option<PathBuf>,
    /// Write the error-vs-frames plot (SVG) here (online GRU).
    #[arg(long)]
    plot: Option<PathBuf>,
    /// Subjects to evaluate (comma separated).
    #[arg(long, default_value = "S9,S11", value_delimiter = ',')]
    subjects: Vec<String>,
    /// Test-time flip: average the estimates of each trial and of its
    /// mirror image (twice the compute).
    #[arg(long)]
    flip_average: bool,
    /// Feed the model a stream of this many frames per second (the 50 Hz
    /// data linearly resampled; e.g. 25 or 60).
    #[arg(long, default_value_t = 50.0)]
    fps: f32,
    /// Start every trial this many 50 Hz frames in (a stream joined mid-way;
    /// shows whether an online error curve depends on the state's age or on
    /// how the recordings begin).
    #[arg(long, default_value_t = 0)]
    skip_frames: usize,
    /// Online GRU: restart its hidden state every this many frames (the
    /// running mean of its predictions carries on).
    #[arg(long)]
    state_frames: Option<usize>,
    /// With --rectify: scale each view's estimate by its camera's height
    /// over the reference height 1.56 m (blapose_core::level::height_scale),
    /// for models trained with `--height-normalized` (a rectified model
    /// cannot see the height; the scene scales with it).
    #[arg(long, requires = "rectify")]
    height_correction: bool,
    /// Evaluate the trials of these cameras only (ids, comma separated;
    /// default all).
    #[arg(long, value_delimiter = ',')]
    cameras: Vec<String>,
    /// Rectify every trial's keypoints with its camera's calibration, for
    /// models trained with `train --rectify`.
    #[arg(long)]
    rectify: bool,
    /// Evaluate as the server serves a session that sends its camera's
    /// calibration: every trial's keypoints undistorted (the detections
    /// are pixels of the distorted video; the protocol takes undistorted
    /// ones) and rectified with its camera, and
    /// the estimate scaled by the camera's height when the weights are
    /// height-normalized (their train_config says), the keypoints scaled
    /// to the floor when they were trained so. For camera-aware weights.
    #[arg(long, conflicts_with_all = ["rectify", "height_correction"])]
    calibrated: bool,
    /// Evaluate only every k-th trial (quick subsets; 1 = all).
    #[arg(long, default_value_t = 1)]
    every: usize,
    /// Lose each joint of each frame with this probability, its
    /// coordinates replaced by garbage (seeded, --drop-seed): the headline
    /// is then the model reading the lost joints held at their last
    /// detection (what honouring confidence 0 gives), reported beside the
    /// clean score and the garbage fed as is (blapose_train::joint_dropout).
    #[arg(long, value_name = "P")]
    drop_joints: Option<f64>,
    /// Seed of --drop-joints.
    #[arg(long, default_value_t = 0, requires = "drop_joints")]
    drop_seed: u64,
    /// Score the stature model the server answers subjects with
    /// (--stature-model) instead of a network: each subject's lengths from
    /// its stature proxy (Human3.6M publishes no statures;
    /// blapose_train::stature::stature_proxy says how it is made).
    #[arg(long, conflicts_with_all = ["model", "weights", "benchmark", "drop_joints"])]
    stature_proxy: bool,
    /// Where --stature-proxy takes each subject's stature from: `proxy`
    /// (blapose_train::stature::stature_proxy), `calibrated-proxy` (the
    /// proxy plus what it reads short by on the training subjects, through
    /// the regression: blapose_train::stature::proxy_offset) or `matched`
    /// (a diagnostic that reads the truth: the stature whose regression
    /// lengths sum to the subject's true summed length, so what is left is
    /// proportion).
    #[arg(long, value_enum, default_value_t = StatureSource::CalibratedProxy)]
    pub(crate) stature_source: StatureSource,
    /// The stature model file, for --stature-proxy.
    #[arg(long, default_value = "models/stature_regression.json")]
    stature_model: PathBuf,
    /// Data root (default: $BLAPOSE_DATA or ../shared/data).
    #[arg(long)]
    data: Option<PathBuf>,
    /// Storage precision of the fast engines' GRU weights (f32, f16 or
    /// bf16), to score a serving precision against f32.
    #[arg(long, default_value = "f32")]
    precision: blapose_model::Precision,
}

/// Where `--stature-proxy` takes each subject's stature from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum StatureSource {
    /// The documented proxy.
    Proxy,
    /// The proxy plus its mean shortfall on the training subjects.
    CalibratedProxy,
    /// Matched to the subject's true summed length (reads the truth).
    Matched,
}

/// `blapose eval`.
pub fn run(a: EvalArgs) -> Result<()> {
    let root = blapose_data::data_root(a.data.clone());
    if a.state_frames.is_some() && a.model.map(ModelKind::from) != Some(ModelKind::Gru) {
        anyhow::bail!("--state-frames restarts the online GRU's state: it needs --model gru");
    }
    if let Some(Benchmark::Bodies) = a.benchmark {
        return crate::bodies::run(&root, &a.bodies, a.json.as_deref());
    }
    let subjects = known_subjects(&a.subjects)?;
    let t0 = Instant::now();
    let all = H36m::load(&root, &ALL_SUBJECTS, Parts::POSES)?;
    let lengths = subject_lengths(&all);
    let parts = if a.input == InputKind::Sh {
        Parts::ALL
    } else {
        Parts::POSES
    };
    let h36m = H36m::load(&root, &subjects, parts)?;
    let mut trials = eval_sequences(&h36m, &subjects, a.input, &lengths)?;
    if !a.cameras.is_empty() {
        trials.retain(|t| a.cameras.contains(&t.camera));
    }
    if a.every > 1 {
        trials = trials.into_iter().step_by(a.every).collect();
    }
    if a.rectify {
        rectify_streams(
            &mut trials,
            &|subject, id| h36m.cameras.get(subject, id),
            false,
        )?;
    }
    if a.skip_frames > 0 {
        trials = trials.iter().map(|t| t.skipped(a.skip_frames)).collect();
    }
    if a.fps != blapose_train::dataset::SOURCE_FPS {
        trials = trials
            .iter()
            .map(|t| t.resampled(a.fps))
            .collect::<Result<_, _>>()?;
    }
    if trials.is_empty() {
        anyhow::bail!(
            "no trials for subjects {} (cameras: {})",
            a.subjects.join(","),
            camera_list(&a.cameras)
        );
    }
    eprintln!(
        "loaded {} trials in {:.1}s",
        trials.len(),
        t0.elapsed().as_secs_f64()
    );
    let mean_of = |names: &[&str]| -> Result<BoneLengths> {
        mean_subject_lengths(&lengths, names)
            .ok_or_else(|| anyhow::anyhow!("missing subject lengths"))
    };
    let baselines = [
        ("training_mean", mean_of(&TRAIN_SUBJECTS)?),
        ("all_subjects_mean", mean_of(&ALL_SUBJECTS)?),
    ];
    if a.stature_proxy {
        let report = stature_proxy_report(&a, &all, &lengths, &subjects, &trials, &baselines)?;
        println!("{}", markdown(&report));
        if let Some(p) = &a.json {
            std::fs::write(p, serde_json::to_string_pretty(&report)?)?;
        }
        return Ok(());
    }
    let (Some(model), Some(weights_path)) = (a.model, a.weights.clone()) else {
        anyhow::bail!("--model and --weights are required without --benchmark or --stature-proxy");
    };
    let kind = ModelKind::from(model);
    let weights = blapose_model::weights::load(&weights_path, kind)?;
    let score = |trials: Vec<EvalSequence>| {
        score_trials(&a, kind, &weights, &weights_path, &h36m, trials, &baselines)
    };
    let report = match a.drop_joints {
        None => score(trials)?,
        Some(probability) => {
            let dropped = drop_joints(&trials, probability, a.drop_seed)?;
            let lost_share = dropped.lost as f64 / dropped.joints.max(1) as f64;
            let empty_frames = dropped.empty_frames;
            let clean = score(trials)?.mean_bone_error_mm;
            let without = score(dropped.garbage)?.mean_bone_error_mm;
            let mut report = score(dropped.held)?;
            let with = report.mean_bone_error_mm;
            report.drop_joints = Some(DropJointsReport {
                probability,
                seed: a.drop_seed,
                lost_share,
                empty_frames,
                clean_mm: clean,
                with_confidence_mm: with,
                without_confidence_mm: without,
                rise_mm: with - clean,
                rise_without_confidence_mm: without - clean,
            });
            report
        }
    };
    println!("{}", markdown(&report));
    if let Some(d) = &report.drop_joints {
        println!(
            "joints lost: {:.1} % (p = {}, seed {}), {} frames lost every joint\n\
             clean {:.2} mm | lost joints held (confidence honoured) {:.2} mm ({:+.2}) | \
             garbage fed as is {:.2} mm ({:+.2})",
            100.0 * d.lost_share,
            d.probability,
            d.seed,
            d.empty_frames,
            d.clean_mm,
            d.with_confidence_mm,
            d.rise_mm,
            d.without_confidence_mm,
            d.rise_without_confidence_mm
        );
    }
    println!(
        "model pass: {:.1}s for {} frames ({:.0} frames/s)",
        report.seconds,
        report.frames,
        report.frames as f64 / report.seconds.max(1e-9)
    );
    if let Some(p) = &a.json {
        std::fs::write(p, serde_json::to_string_pretty(&report)?)?;
    }
    if let Some(p) = &a.plot {
        if report.curve.is_empty() {
            eprintln!("no error curve for the offline model; plot not written");
        } else {
            blapose_train::plot::error_curve(&report, p)?;
            eprintln!("plot: {}", p.display());
        }
    }
    Ok(())
}

/// The model (with --flip-average, --calibrated, --height-correction as
/// asked) scored on `trials`.
#[allow(clippy::too_many_arguments)]
fn score_trials(
    a: &EvalArgs,
    kind: ModelKind,
    weights: &LoadedWeights,
    weights_path: &Path,
    h36m: &H36m,
    mut trials: Vec<EvalSequence>,
    baselines: &[(&str, BoneLengths)],
) -> Result<EvalReport> {
    let mut estimator: Box<dyn LengthEstimator> = match kind {
        ModelKind::BiGru => Box::new(BiGruEstimator::with_precision(weights, a.precision)?),
        ModelKind::Gru => Box::new(
            GruEstimator::with_precision(weights, a.precision)?.with_state_frames(a.state_frames),
        ),
    };
    let mut model_label = kind.as_str().to_string();
    if a.flip_average {
        estimator = Box::new(FlipAveraged::new(estimator));
        model_label.push_str("+flip");
    }
    if a.calibrated {
        estimator = blapose_train::eval::calibrated(estimator, weights, &mut trials, |s, id| {
            h36m.cameras.get(s, id)
        })?;
        model_label.push_str("+calibrated");
    }
    if a.height_correction {
        estimator = blapose_train::eval::height_corrected(estimator, &trials, |s, id| {
            h36m.cameras.get(s, id)
        })?;
        model_label.push_str("+height");
    }
    Ok(evaluate(
        estimator.as_ref(),
        &trials,
        baselines,
        &model_label,
        a.input.name(),
        &weights_path.display().to_string(),
        &a.subjects,
    )?)
}

/// `--stature-proxy`: the stature model on each evaluated subject's
/// stature proxy (from all of its recordings in `all`), scored on
/// `trials` by the same protocol beside the same baselines.
fn stature_proxy_report(
    a: &EvalArgs,
    all: &H36m,
    lengths: &std::collections::BTreeMap<String, BoneLengths>,
    subjects: &[&str],
    trials: &[EvalSequence],
    baselines: &[(&str, BoneLengths)],
) -> Result<EvalReport> {
    use blapose_model::stature::StatureModel;
    use blapose_train::eval::PerSubject;
    use blapose_train::stature::{matched_stature, proxy_offset, stature_proxy};
    let text = std::fs::read_to_string(&a.stature_model)
        .with_context(|| format!("reading {}", a.stature_model.display()))?;
    let model = StatureModel::from_json(&text)?;
    let proxy_of = |s: &str| -> Result<f32> {
        let poses: Vec<_> = all
            .sequences()
            .filter(|(subject, _, _)| *subject == s)
            .flat_map(|(_, _, p)| p.iter().copied())
            .collect();
        stature_proxy(&poses).with_context(|| format!("no poses of {s} for its stature proxy"))
    };
    let truth_of = |s: &str| -> Result<BoneLengths> {
        lengths
            .get(s)
            .copied()
            .with_context(|| format!("no true lengths for {s}"))
    };
    let offset = match a.stature_source {
        StatureSource::CalibratedProxy => {
            let training = TRAIN_SUBJECTS
                .iter()
                .map(|s| Ok((proxy_of(s)?, truth_of(s)?)))
                .collect::<Result<Vec<_>>>()?;
            let offset = proxy_offset(&model.pooled, &training)
                .context("no training subject to calibrate the proxy on")?;
            println!(
                "calibrated proxy: the proxy reads {:.1} mm short on the training subjects",
                offset * 1000.0
            );
            offset
        }
        StatureSource::Proxy | StatureSource::Matched => 0.0,
    };
    let mut answers = std::collections::BTreeMap::new();
    for s in subjects {
        let truth = truth_of(s)?;
        let stature = match a.stature_source {
            StatureSource::Matched => matched_stature(&model.pooled, &truth)
                .context("the stature regression's summed slope is not positive")?,
            StatureSource::Proxy | StatureSource::CalibratedProxy => proxy_of(s)? + offset,
        };
        let predicted = model.predict(stature, None);
        println!(
            "{s}: stature {stature:.3} m ({:?}) -> total length {:.3} m (true {:.3})",
            a.stature_source,
            predicted.iter().sum::<f32>(),
            truth.iter().sum::<f32>()
        );
        answers.insert(s.to_string(), predicted);
    }
    let label = match a.stature_source {
        StatureSource::Proxy => "stature-regression+proxy",
        StatureSource::CalibratedProxy => "stature-regression+calibrated-proxy",
        StatureSource::Matched => "stature-regression+matched-stature",
    };
    Ok(evaluate(
        &PerSubject(answers),
        trials,
        baselines,
        label,
        a.input.name(),
        &a.stature_model.display().to_string(),
        &a.subjects,
    )?)
}

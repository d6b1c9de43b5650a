//! `blapose-lab diagnose`: the product's evaluation run (`blapose eval`'s
//! flags, [`EvalRunArgs`]) with the research diagnostics around it: trials
//! joined mid-way (`--skip-frames`), rectified whatever the weights record
//! (`--rectify`), the online state restarted (`--state-frames`), joints
//! lost (`--drop-joints`), or the stature regression scored in a model's
//! place (`--stature-proxy`). The diagnostics are
//! [`blapose_lab::diagnose`]; the run and the protocol are
//! `blapose-train`'s. Why here: which diagnostic a run asks for is the
//! command's choice.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result};
use blapose_lab::diagnose::{rectified, skipped, state_frames, DiagnoseReport};
use blapose_lab::joint_dropout::score_with_lost_joints;
use blapose_lab::stature_proxy::{stature_answers, StatureSource};
use blapose_model::stature::StatureModel;
use blapose_model::ModelKind;
use blapose_train::cli::ModelArg;
use blapose_train::eval::run::{model_pass, network_estimator, EvalData, EvalRunArgs};
use blapose_train::eval::{markdown, GruEstimator, LengthEstimator};

/// Arguments of `blapose-lab diagnose`.
#[derive(clap::Args, Debug)]
pub struct DiagnoseArgs {
    /// Model kind: gru (online, running mean) or bigru (offline).
    #[arg(
        long,
        value_enum,
        ignore_case = true,
        required_unless_present = "stature_proxy"
    )]
    model: Option<ModelArg>,
    /// Weights file (safetensors written by `blapose train`).
    #[arg(long, required_unless_present = "stature_proxy")]
    weights: Option<PathBuf>,
    #[command(flatten)]
    run: EvalRunArgs,
    /// Start every trial this many 50 Hz frames in (a stream joined mid-way;
    /// shows whether an online error curve depends on the state's age or on
    /// how the recordings begin).
    #[arg(long, default_value_t = 0)]
    skip_frames: usize,
    /// Online GRU: restart its hidden state every this many frames (the
    /// running mean of its predictions carries on).
    #[arg(long)]
    state_frames: Option<usize>,
    /// Rectify every trial's keypoints with its camera's calibration (no
    /// lens undistortion, no floor scaling), whatever the weights record:
    /// for models trained with `train --rectify` alone.
    #[arg(long, conflicts_with = "calibrated")]
    rectify: bool,
    /// Lose each joint of each frame with this probability, its
    /// coordinates replaced by garbage (seeded, --drop-seed): the headline
    /// is then the model reading the lost joints held at their last
    /// detection (what honouring confidence 0 gives), reported beside the
    /// clean score and the garbage fed as is (blapose_lab::joint_dropout).
    #[arg(long, value_name = "P")]
    drop_joints: Option<f64>,
    /// Seed of --drop-joints.
    #[arg(long, default_value_t = 0, requires = "drop_joints")]
    drop_seed: u64,
    /// Score the stature model the server answers subjects with
    /// (--stature-model) instead of a network: each subject's lengths from
    /// its stature proxy (Human3.6M publishes no statures;
    /// blapose_lab::stature_proxy says how it is made).
    #[arg(long, conflicts_with_all = ["model", "weights", "drop_joints"])]
    stature_proxy: bool,
    /// Where --stature-proxy takes each subject's stature from: `proxy`
    /// (blapose_lab::stature_proxy::stature_proxy), `calibrated-proxy` (the
    /// proxy plus what it reads short by on the training subjects, through
    /// the regression: blapose_lab::stature_proxy::proxy_offset) or
    /// `matched` (a diagnostic that reads the truth: the stature whose
    /// regression lengths sum to the subject's true summed length, so what
    /// is left is proportion).
    #[arg(long, value_enum, default_value_t = StatureSource::CalibratedProxy)]
    pub(crate) stature_source: StatureSource,
    /// The stature model file, for --stature-proxy.
    #[arg(long, default_value = "models/stature_regression.json")]
    stature_model: PathBuf,
}

/// `blapose-lab diagnose`.
pub fn run(a: DiagnoseArgs) -> Result<()> {
    if a.state_frames.is_some() && a.model.map(ModelKind::from) != Some(ModelKind::Gru) {
        anyhow::bail!("--state-frames restarts the online GRU's state: it needs --model gru");
    }
    let t0 = Instant::now();
    let (data, mut trials) = EvalData::load(&a.run)?;
    if a.rectify {
        rectified(&mut trials, &data)?;
    }
    if a.skip_frames > 0 {
        trials = trials.iter().map(|t| skipped(t, a.skip_frames)).collect();
    }
    let trials = data.at_rate(trials)?;
    eprintln!(
        "loaded {} trials in {:.1}s",
        trials.len(),
        t0.elapsed().as_secs_f64()
    );
    if a.stature_proxy {
        return stature_proxy(&a, &data, &trials);
    }
    let (Some(model), Some(weights_path)) = (a.model, &a.weights) else {
        anyhow::bail!("--model and --weights are required without --stature-proxy");
    };
    let kind = ModelKind::from(model);
    let weights = blapose_model::weights::load(weights_path, kind)?;
    let score = |trials| {
        let estimator: Box<dyn LengthEstimator> = match kind {
            ModelKind::Gru => Box::new(state_frames(
                GruEstimator::with_precision(&weights, a.run.precision)?,
                a.state_frames,
            )),
            ModelKind::BiGru => network_estimator(kind, &weights, a.run.precision)?,
        };
        data.score(kind, estimator, &weights, weights_path, trials)
    };
    let (report, lost) = match a.drop_joints {
        None => (score(trials)?, None),
        Some(p) => {
            let (report, lost) = score_with_lost_joints(trials, p, a.drop_seed, score)?;
            (report, Some(lost))
        }
    };
    println!("{}", markdown(&report));
    if let Some(lost) = &lost {
        println!("{}", lost.summary());
    }
    println!("{}", model_pass(&report));
    let json = DiagnoseReport {
        report: &report,
        drop_joints: lost.as_ref(),
    };
    if let Some(note) = a.run.write(&report, &json)? {
        eprintln!("{note}");
    }
    Ok(())
}

/// `--stature-proxy`: the stature model on each evaluated subject's
/// stature, scored on `trials` by the same protocol beside the same
/// baselines.
fn stature_proxy(
    a: &DiagnoseArgs,
    data: &EvalData,
    trials: &[blapose_train::dataset::EvalSequence],
) -> Result<()> {
    let text = std::fs::read_to_string(&a.stature_model)
        .with_context(|| format!("reading {}", a.stature_model.display()))?;
    let model = StatureModel::from_json(&text)?;
    let answers = stature_answers(data, a.stature_source, &model)?;
    if let Some(offset) = answers.offset_m {
        println!(
            "calibrated proxy: the proxy reads {:.1} mm short on the training subjects",
            offset * 1000.0
        );
    }
    for s in &answers.subjects {
        println!(
            "{}: stature {:.3} m ({:?}) -> total length {:.3} m (true {:.3})",
            s.subject, s.stature_m, a.stature_source, s.predicted_total_m, s.true_total_m
        );
    }
    let report = data.evaluate(
        &answers.answers,
        trials,
        a.stature_source.label(),
        &a.stature_model.display().to_string(),
    )?;
    println!("{}", markdown(&report));
    if let Some(p) = &a.run.json {
        std::fs::write(p, serde_json::to_string_pretty(&report)?)?;
    }
    Ok(())
}

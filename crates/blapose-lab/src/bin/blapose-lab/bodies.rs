//! `blapose-lab bodies`: loads what the many-bodies benchmark needs (the
//! held-out people, S9/S11 motion, the training subjects' detector
//! residuals, the four shipped models) and prints its table; the benchmark
//! itself is [`blapose_lab::bodies`]. Why here: file locations and flags
//! are the command's, the protocol is the library's.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Result;
use blapose_data::h36m::{H36m, Parts, TRAIN_SUBJECTS};
use blapose_lab::bodies::{
    fit_people, markdown, mean_body, test_motions, BenchModel, BodiesConfig, BodiesInput, FitSet,
    DEFAULT_FRAMES, DEFAULT_SEED, SHIPPED_MODELS,
};
use blapose_lab::real_check::RealCheck;
use blapose_train::ansur_split::{AnsurPeople, AnsurSplit};
use blapose_train::dataset::{eval_sequences, mean_subject_lengths, InputKind, TrainingSet};
use blapose_train::lengths::TrainingLengthStats;
use blapose_train::stature::StatureRegression;

/// Arguments of `blapose-lab bodies`.
#[derive(clap::Args, Debug)]
pub struct BodiesArgs {
    /// Benchmark seed (individuals' clips, cameras and noise).
    #[arg(long, default_value_t = DEFAULT_SEED)]
    bench_seed: u64,
    /// Frames (50 Hz) of S9/S11 motion per individual.
    #[arg(long, default_value_t = DEFAULT_FRAMES)]
    bench_frames: usize,
    /// Use only the first N held-out individuals (default: all).
    #[arg(long)]
    bench_individuals: Option<usize>,
    /// Folder with bone_length_{gru,bigru}{,_rectified}.safetensors.
    #[arg(long, default_value = "models")]
    models_dir: PathBuf,
    /// Training-split people to fit the height-fusion rows on (`height`,
    /// `calibration+height`), on the training subjects' motion; 0: no such
    /// rows.
    #[arg(long, default_value_t = 630)]
    fit_individuals: usize,
    /// Score every model beside its row on every N-th trial of the training
    /// subjects' own Stacked Hourglass detections (real data selection may
    /// use; blapose_lab::real_check); 0: no such check.
    #[arg(long, default_value_t = 4)]
    real_check_every: usize,
    /// Write the full report as JSON here.
    #[arg(long)]
    json: Option<PathBuf>,
    /// Data root (default: $BLAPOSE_DATA or ../shared/data).
    #[arg(long)]
    data: Option<PathBuf>,
}

/// Seed of the height-fusion fit trials (never the benchmark's).
const FIT_SEED: u64 = 7;

/// The benchmark's test subjects (their motion, never their bodies).
const MOTION_SUBJECTS: [&str; 2] = ["S9", "S11"];

/// Run the benchmark and print (and write) its report.
pub fn run(a: BodiesArgs) -> Result<()> {
    let root = &blapose_data::data_root(a.data.clone());
    let t0 = Instant::now();
    let set = TrainingSet::load(root)?;
    let stats = TrainingLengthStats::from_training(&set.lengths_list())?;
    let split = AnsurSplit::load(root, &stats)?;
    let training_pop = split.training_population(AnsurPeople::Train)?;
    let prior = mean_body(training_pop.people())
        .ok_or_else(|| anyhow::anyhow!("empty training population"))?;
    let training_mean = mean_subject_lengths(&set.subject_lengths, &TRAIN_SUBJECTS)
        .ok_or_else(|| anyhow::anyhow!("missing training subjects' lengths"))?;
    let h36m = H36m::load(root, &MOTION_SUBJECTS, Parts::POSES)?;
    let motions = test_motions(&h36m, &MOTION_SUBJECTS)?;
    // The stature-regression baseline: fitted on the training split only.
    let stature = StatureRegression::fit_training(&split.everyone)?;
    // The training subjects, loaded once for the height-fusion fit (their
    // motion) and the real-detection check (their detections too).
    let train_h36m = match (a.fit_individuals > 0, a.real_check_every > 0) {
        (false, false) => None,
        (_, real) => Some(H36m::load(
            root,
            &TRAIN_SUBJECTS,
            if real { Parts::ALL } else { Parts::POSES },
        )?),
    };
    let fit_set = match &train_h36m {
        Some(h) if a.fit_individuals > 0 => Some(FitSet {
            people: fit_people(&split.everyone, a.fit_individuals),
            motions: test_motions(h, &TRAIN_SUBJECTS)?,
            seed: FIT_SEED,
        }),
        _ => None,
    };
    let real_camera = |s: &str, id: &str| train_h36m.as_ref().and_then(|h| h.cameras.get(s, id));
    let real_check = match &train_h36m {
        Some(h) if a.real_check_every > 0 => Some(RealCheck {
            trials: eval_sequences(h, &TRAIN_SUBJECTS, InputKind::Sh, &set.subject_lengths)?
                .into_iter()
                .step_by(a.real_check_every)
                .collect(),
            camera: &real_camera,
        }),
        _ => None,
    };
    let input = BodiesInput {
        people: split.held_out(),
        motions,
        residuals: &set.residuals,
        prior,
        training_mean,
        stature: Some(&stature),
        fit_set,
        real_check,
    };
    eprintln!(
        "loaded {} held-out individuals, {} test sequences in {:.1}s",
        input.people.len(),
        input.motions.len(),
        t0.elapsed().as_secs_f64()
    );
    let specs = SHIPPED_MODELS;
    let mut loaded = Vec::with_capacity(specs.len());
    for (kind, bench_input, file) in specs {
        let path = a.models_dir.join(file);
        loaded.push((
            kind,
            bench_input,
            blapose_model::weights::load(&path, kind)?,
            path.display().to_string(),
        ));
    }
    let models: Vec<BenchModel<'_>> = loaded
        .iter()
        .map(|(kind, bench_input, weights, path)| BenchModel {
            kind: *kind,
            input: *bench_input,
            weights,
            path: path.clone(),
        })
        .collect();
    let cfg = BodiesConfig {
        seed: a.bench_seed,
        frames: a.bench_frames,
        limit: a.bench_individuals,
        ..BodiesConfig::default()
    };
    let mut report = blapose_lab::bodies::run(&input, &models, &cfg)?;
    report.seconds = t0.elapsed().as_secs_f64();
    println!("{}", markdown(&report));
    println!(
        "{} individuals x {} frames, {} rows, {:.0}s in all (data loading included)",
        report.individuals,
        report.frames_per_individual,
        report.rows.len(),
        report.seconds
    );
    if let Some(p) = &a.json {
        std::fs::write(p, serde_json::to_string_pretty(&report)?)?;
    }
    Ok(())
}

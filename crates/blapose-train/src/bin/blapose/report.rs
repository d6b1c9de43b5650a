//! `blapose data-report` and `blapose bench-train`: what the training data
//! hold and how fast the pipeline and the network run. Why together: both
//! print measurements for a person to read and change nothing on disk.

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

use anyhow::Result;
use blapose_core::skeleton::{BONE_NAMES, JOINT_NAMES};
use blapose_model::{LoadedWeights, ModelKind};
use blapose_train::ansur::load_population;
use blapose_train::dataset::TrainingSet;
use blapose_train::fastnet::{FastNet, LossConfig};
use blapose_train::lengths::{LengthSampler, LengthStrategy, TrainingLengthStats};
use blapose_train::synth::{SynthConfig, SynthSource};
use rand::{Rng, SeedableRng};

use crate::common::ModelArg;

/// Arguments of `blapose data-report`.
#[derive(clap::Args, Debug)]
pub struct DataReportArgs {
    /// Data root (default: $BLAPOSE_DATA or ../shared/data).
    #[arg(long)]
    data: Option<PathBuf>,
}

/// Arguments of `blapose bench-train`.
#[derive(clap::Args, Debug)]
pub struct BenchTrainArgs {
    /// gru or bigru.
    #[arg(long, value_enum, ignore_case = true, default_value_t = ModelArg::BiGru)]
    model: ModelArg,
    /// Samples per batch.
    #[arg(long, default_value_t = 64)]
    batch: usize,
    /// Frames per window.
    #[arg(long, default_value_t = 64)]
    seq_len: usize,
    /// Timed steps (after one warm-up step).
    #[arg(long, default_value_t = 5)]
    steps: usize,
    /// Weight of the running-mean loss (GRU).
    #[arg(long, default_value_t = 0.0)]
    per_frame_weight: f32,
}

/// `blapose data-report`.
pub fn data_report(a: DataReportArgs) -> Result<()> {
    let root = blapose_data::data_root(a.data);
    let t0 = Instant::now();
    let set = TrainingSet::load(&root)?;
    println!(
        "loaded {} training sequences in {:.1}s",
        set.sequences.len(),
        t0.elapsed().as_secs_f64()
    );
    let stats = TrainingLengthStats::from_training(&set.lengths_list())?;
    let pop = load_population(&root, &stats)?;
    let (pm, ps) = pop.moments();
    println!("| bone | train mean mm | train std mm | ANSUR scale | ANSUR std mm |");
    println!("|---|---|---|---|---|");
    for b in 0..16 {
        println!(
            "| {} | {:.1} | {:.1} | {:.3} | {:.1} (mean {:.1}) |",
            BONE_NAMES[b],
            stats.mean[b] * 1000.0,
            stats.std[b] * 1000.0,
            pop.scale[b],
            ps[b] * 1000.0,
            pm[b] * 1000.0
        );
    }
    let bank = &set.residuals;
    println!(
        "residual bank: {} frames; per-joint std (mm at subject) x/y and mean:",
        bank.frames()
    );
    for (j, name) in JOINT_NAMES.iter().enumerate() {
        println!(
            "  {:>10}: std {:5.1} {:5.1}  mean {:6.1} {:6.1}",
            name,
            bank.std()[j][0] * 1000.0,
            bank.std()[j][1] * 1000.0,
            bank.mean()[j][0] * 1000.0,
            bank.mean()[j][1] * 1000.0
        );
    }
    let sampler = LengthSampler::new(LengthStrategy::Ansur, stats, Some(pop))?;
    let source = Arc::new(SynthSource::new(
        set.sequences.clone(),
        set.residuals.clone(),
        sampler,
    )?);
    let cfg = SynthConfig::default();
    let t0 = Instant::now();
    let n = 20;
    for step in 0..n {
        let b = source.batch(&cfg, 1, step, 64);
        std::hint::black_box(b);
    }
    let dt = t0.elapsed().as_secs_f64();
    println!(
        "synthesis: {:.0} frames/s (batch 64 x T {})",
        (n as usize * 64 * cfg.seq_len) as f64 / dt,
        cfg.seq_len
    );
    Ok(())
}

/// `blapose bench-train`.
pub fn bench_train(a: BenchTrainArgs) -> Result<()> {
    let kind = ModelKind::from(a.model);
    let (batch, seq_len, steps) = (a.batch, a.seq_len, a.steps);
    let w = LoadedWeights::random(kind, 0)?;
    let net = FastNet::from_tensors(kind, w.tensors())?;
    let mut rng = rand::rngs::StdRng::seed_from_u64(0);
    let x: Vec<f32> = (0..batch * seq_len * 34)
        .map(|_| rng.random_range(-1.0f32..1.0))
        .collect();
    let y: Vec<f32> = (0..batch * 16)
        .map(|_| rng.random_range(0.1f32..0.5))
        .collect();
    let mut grad = vec![0.0f32; net.params.len()];
    let cfg = LossConfig {
        running_mean_weight: a.per_frame_weight,
        ..Default::default()
    };
    net.train_step(&x, &y, batch, seq_len, cfg, &mut rng, &mut grad);
    let t0 = Instant::now();
    for _ in 0..steps {
        net.train_step(&x, &y, batch, seq_len, cfg, &mut rng, &mut grad);
    }
    let dt = t0.elapsed().as_secs_f64();
    println!(
        "{kind} batch {batch} seq_len {seq_len}: {:.3} s/step",
        dt / steps as f64
    );
    println!(
        "frames_per_second={:.0}",
        (batch * seq_len * steps) as f64 / dt
    );
    Ok(())
}

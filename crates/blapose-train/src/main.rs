//! The `blapose` command line (see `blapose --help`).

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

use anyhow::Result;
use blapose_core::skeleton::BONE_NAMES;
use blapose_train::ansur::{load_population, AnsurPopulation};
use blapose_train::dataset::TrainingSet;
use blapose_train::lengths::{LengthSampler, LengthStrategy, TrainingLengthStats};
use blapose_train::synth::{SynthConfig, SynthSource};
use blapose_train::train::TrainConfig;
use clap::{Parser, Subcommand};
use indicatif::{ProgressBar, ProgressStyle};

#[derive(Parser)]
#[command(name = "blapose", version, about = "Train and evaluate the BLAPose bone-length models")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

/// Arguments of `blapose train`.
#[derive(clap::Args, Debug)]
struct TrainArgs {
    /// Model kind: gru (online) or bigru (offline).
    #[arg(long, default_value = "bigru")]
    model: String,
    /// Bone-length sampling strategy: true|uniform|normal|ansur.
    #[arg(long, default_value = "ansur")]
    lengths: String,
    /// 2D detector-noise model: none|gaussian|residual.
    #[arg(long, default_value = "residual")]
    noise: String,
    /// Run directory (log, checkpoint, weights, curve).
    #[arg(long)]
    out: PathBuf,
    /// Continue from OUT/checkpoint.safetensors.
    #[arg(long)]
    resume: bool,
    /// Optimizer steps.
    #[arg(long, default_value_t = 2000)]
    steps: u64,
    /// Steps per "epoch" (the learning rate is multiplied by --lr-decay each epoch).
    #[arg(long, default_value_t = 100)]
    epoch_steps: u64,
    /// Frames per training window.
    #[arg(long, default_value_t = 64)]
    seq_len: usize,
    /// Samples per batch.
    #[arg(long, default_value_t = 64)]
    batch: usize,
    /// Initial learning rate.
    #[arg(long, default_value_t = 1e-4)]
    lr: f64,
    /// Learning-rate factor per epoch.
    #[arg(long, default_value_t = 0.95)]
    lr_decay: f64,
    /// Clip the global gradient norm (0 = off).
    #[arg(long, default_value_t = 5.0)]
    clip_norm: f64,
    /// Smallest playback stride in 50 Hz frames (50/60: 60 fps streams).
    #[arg(long, default_value_t = 50.0 / 60.0)]
    stride_min: f32,
    /// Largest playback stride (2.0: 25 fps streams).
    #[arg(long, default_value_t = 2.0)]
    stride_max: f32,
    /// Std of the per-sequence 3D shift, metres.
    #[arg(long, default_value_t = 0.5)]
    shift_std: f32,
    /// Horizontal flip probability.
    #[arg(long, default_value_t = 0.5)]
    flip_prob: f32,
    /// GRU only: weight of the L1 loss on the running mean of per-frame predictions.
    #[arg(long, default_value_t = 0.0)]
    per_frame_weight: f32,
    /// Master seed (data, initial weights).
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Validate every N steps.
    #[arg(long, default_value_t = 100)]
    val_every: u64,
    /// Synthetic validation samples.
    #[arg(long, default_value_t = 256)]
    val_samples: usize,
    /// Frames per real-SH validation window (training subjects).
    #[arg(long, default_value_t = 128)]
    val_frames: usize,
    /// Seconds between checkpoints.
    #[arg(long, default_value_t = 300)]
    checkpoint_secs: u64,
    /// Data root (default: $BLAPOSE_DATA or ../shared/data).
    #[arg(long)]
    data: Option<PathBuf>,
}

#[derive(Subcommand)]
enum Command {
    /// Train a bone-length model on synthetic sequences built from the
    /// Human3.6M training subjects (S1 S5 S6 S7 S8).
    Train(Box<TrainArgs>),
    /// Print the training data statistics, the ANSUR calibration and the
    /// detector residuals; time the augmentation pipeline.
    DataReport {
        /// Data root (default: $BLAPOSE_DATA or ../shared/data).
        #[arg(long)]
        data: Option<PathBuf>,
    },
}

fn main() -> Result<()> {
    let cli = Cli::parse();
    match cli.command {
        Command::DataReport { data } => data_report(data),
        Command::Train(args) => train(*args),
    }
}

fn data_report(data: Option<PathBuf>) -> Result<()> {
    let root = blapose_data::data_root(data);
    let t0 = Instant::now();
    let set = TrainingSet::load(&root)?;
    println!("loaded {} training sequences in {:.1}s", set.sequences.len(), t0.elapsed().as_secs_f64());
    let stats = TrainingLengthStats::from_training(&set.lengths_list())?;
    let pop: AnsurPopulation = load_population(&root, &stats)?;
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
    println!("residual bank: {} frames; per-joint std (mm at subject) x/y and mean:", bank.frames());
    for j in 0..17 {
        println!(
            "  {:>10}: std {:5.1} {:5.1}  mean {:6.1} {:6.1}",
            blapose_core::skeleton::JOINT_NAMES[j],
            bank.std()[j][0] * 1000.0,
            bank.std()[j][1] * 1000.0,
            bank.mean()[j][0] * 1000.0,
            bank.mean()[j][1] * 1000.0
        );
    }
    let sampler = LengthSampler::new(LengthStrategy::Ansur, stats, Some(pop))?;
    let source = Arc::new(SynthSource::new(set.sequences.clone(), set.residuals.clone(), sampler)?);
    let cfg = SynthConfig::default();
    let t0 = Instant::now();
    let n = 20;
    for step in 0..n {
        let b = source.batch(&cfg, 1, step, 64);
        std::hint::black_box(b);
    }
    let dt = t0.elapsed().as_secs_f64();
    println!("synthesis: {:.0} frames/s (batch 64 x T {})", (n as usize * 64 * cfg.seq_len) as f64 / dt, cfg.seq_len);
    Ok(())
}

fn train(a: TrainArgs) -> Result<()> {
    let root = blapose_data::data_root(a.data.clone());
    let strategy: LengthStrategy = a.lengths.parse()?;
    let cfg = TrainConfig {
        kind: a.model.parse::<blapose_model::ModelKind>()?.to_string(),
        lengths: strategy.to_string(),
        noise: a.noise.parse::<blapose_train::noise::NoiseKind>()?.to_string(),
        seq_len: a.seq_len,
        stride_min: a.stride_min,
        stride_max: a.stride_max,
        shift_std: a.shift_std,
        flip_prob: a.flip_prob,
        batch: a.batch,
        steps: a.steps,
        epoch_steps: a.epoch_steps,
        lr: a.lr,
        lr_decay: a.lr_decay,
        clip_norm: a.clip_norm,
        per_frame_weight: a.per_frame_weight,
        seed: a.seed,
        val_every: a.val_every,
        val_samples: a.val_samples,
        val_frames: a.val_frames,
        checkpoint_secs: a.checkpoint_secs,
    };
    let t0 = Instant::now();
    let set = TrainingSet::load(&root)?;
    let stats = TrainingLengthStats::from_training(&set.lengths_list())?;
    let pop = if strategy == LengthStrategy::Ansur { Some(load_population(&root, &stats)?) } else { None };
    let sampler = LengthSampler::new(strategy, stats, pop)?;
    let source = Arc::new(SynthSource::new(set.sequences.clone(), set.residuals.clone(), sampler)?);
    eprintln!(
        "data: {} training sequences, {} real SH validation streams, loaded in {:.1}s",
        set.sequences.len(),
        set.real_sh.len(),
        t0.elapsed().as_secs_f64()
    );
    let training_data = format!(
        "Human3.6M S1 S5 S6 S7 S8, lengths={}, noise={}, seq_len={}, stride=[{:.3},{:.3}], shift_std={} m, flip={}",
        cfg.lengths, cfg.noise, cfg.seq_len, cfg.stride_min, cfg.stride_max, cfg.shift_std, cfg.flip_prob
    );
    let pb = ProgressBar::new(cfg.steps);
    pb.set_style(
        ProgressStyle::with_template("{elapsed_precise} [{bar:30}] {pos}/{len} eta {eta} {msg}")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    let mut progress = |step: u64, _total: u64, loss: f64, fps: f64| {
        pb.set_position(step);
        pb.set_message(format!("loss {loss:.2} mm, {fps:.0} frames/s"));
    };
    let outcome = blapose_train::train::train(&cfg, source, &set.real_sh, &a.out, a.resume, &training_data, &mut progress)?;
    pb.finish();
    let curve = a.out.join("curve.svg");
    blapose_train::plot::training_curve(&a.out.join(blapose_train::train::LOG_FILE), &curve)?;
    println!(
        "trained {} steps in {:.0}s ({:.0} frames/s); validation: synthetic {:.2} mm, real SH (training subjects) {:.2} mm{}",
        outcome.steps_run,
        outcome.elapsed_s,
        outcome.frames_per_s,
        outcome.validation.synth_mm,
        outcome.validation.real_sh_mm,
        if outcome.validation.real_sh_running_mm.is_finite() {
            format!(", running mean {:.2} mm", outcome.validation.real_sh_running_mm)
        } else {
            String::new()
        }
    );
    println!("weights: {}", outcome.weights.display());
    println!("curve: {}", curve.display());
    Ok(())
}

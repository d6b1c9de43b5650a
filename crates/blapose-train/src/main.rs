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
use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(name = "blapose", version, about = "Train and evaluate the BLAPose bone-length models")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
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

//! `blapose eval`: a model's bone-length error on Human3.6M as a user of
//! the shipped weights measures it: which model and weights, and the run's
//! flags ([`EvalRunArgs`]: which trials, at which rate, flip-averaged or
//! not, calibrated or not). The run and the protocol are the library's
//! ([`blapose_train::eval::run`]); research diagnostics of the same run
//! are `blapose-lab diagnose`. Why here: these are choices of an
//! evaluation run, not of the protocol.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Result;
use blapose_model::ModelKind;
use blapose_train::eval::markdown;
use blapose_train::eval::run::{model_pass, network_estimator, EvalData, EvalRunArgs};

use crate::common::ModelArg;

/// Arguments of `blapose eval`.
#[derive(clap::Args, Debug)]
pub struct EvalArgs {
    /// Model kind: gru (online, running mean) or bigru (offline).
    #[arg(long, value_enum, ignore_case = true)]
    model: ModelArg,
    /// Weights file (safetensors written by `blapose train`).
    #[arg(long)]
    weights: PathBuf,
    #[command(flatten)]
    run: EvalRunArgs,
}

/// `blapose eval`.
pub fn run(a: EvalArgs) -> Result<()> {
    let t0 = Instant::now();
    let (data, trials) = EvalData::load(&a.run)?;
    let trials = data.at_rate(trials)?;
    eprintln!(
        "loaded {} trials in {:.1}s",
        trials.len(),
        t0.elapsed().as_secs_f64()
    );
    let kind = ModelKind::from(a.model);
    let weights = blapose_model::weights::load(&a.weights, kind)?;
    let estimator = network_estimator(kind, &weights, a.run.precision)?;
    let report = data.score(kind, estimator, &weights, &a.weights, trials)?;
    println!("{}", markdown(&report));
    println!("{}", model_pass(&report));
    if let Some(note) = a.run.write(&report, &report)? {
        eprintln!("{note}");
    }
    Ok(())
}

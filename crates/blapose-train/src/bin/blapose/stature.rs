//! The models a session with a known stature is answered with.
//!
//! `blapose fit-stature`: fit the stature regression on the ANSUR II
//! training split and write the file the server embeds
//! (`models/stature_regression.json`); the fit is
//! [`blapose_train::stature`], the file format
//! [`blapose_model::stature`].
//!
//! `blapose fit-proportions`: fit the proportion reader on training-split
//! bodies on the training subjects' motion through wide cameras and write
//! `models/proportion_reader.json`; the fit is
//! [`blapose_train::proportions`], the file format
//! [`blapose_model::proportions`].

use std::path::PathBuf;

use std::time::Instant;

use anyhow::{Context, Result};
use blapose_data::h36m::{H36m, Parts, TRAIN_SUBJECTS};
use blapose_train::ansur_split::AnsurSplit;
use blapose_train::bodies::{fit_people, test_motions};
use blapose_train::dataset::TrainingSet;
use blapose_train::lengths::TrainingLengthStats;
use blapose_train::proportions::TrainingBodies;
use blapose_train::stature::StatureRegression;

/// Arguments of `blapose fit-stature`.
#[derive(clap::Args, Debug)]
pub struct FitStatureArgs {
    /// Where to write the model.
    #[arg(long, default_value = "models/stature_regression.json")]
    out: PathBuf,
    /// Data root (default: $BLAPOSE_DATA or ../shared/data).
    #[arg(long)]
    data: Option<PathBuf>,
}

/// Fit and write.
pub fn run(a: FitStatureArgs) -> Result<()> {
    let root = blapose_data::data_root(a.data.clone());
    let set = TrainingSet::load(&root)?;
    let stats = TrainingLengthStats::from_training(&set.lengths_list())?;
    let split = AnsurSplit::load(&root, &stats)?;
    let regression = StatureRegression::fit_training(&split.everyone)?;
    let model = regression.to_model(&format!(
        "ANSUR II public release, the {} people outside the held-out split \
         (blapose_train::ansur_split), lengths calibrated to the Human3.6M training \
         subjects (blapose_train::ansur); one least-squares line per bone on measured \
         stature, per sex and pooled; written by `blapose fit-stature`",
        regression.fitted_on.len()
    ))?;
    std::fs::write(&a.out, model.to_json())
        .with_context(|| format!("writing {}", a.out.display()))?;
    println!(
        "fitted on {} people ({} women, {} men); wrote {}",
        model.pooled.people,
        model.female.people,
        model.male.people,
        a.out.display()
    );
    Ok(())
}

/// Arguments of `blapose fit-proportions`.
#[derive(clap::Args, Debug)]
pub struct FitProportionsArgs {
    /// Where to write the model.
    #[arg(long, default_value = "models/proportion_reader.json")]
    out: PathBuf,
    /// Data root (default: $BLAPOSE_DATA or ../shared/data).
    #[arg(long)]
    data: Option<PathBuf>,
    /// Training-split bodies to fit on (default: all of them).
    #[arg(long)]
    people: Option<usize>,
    /// Seed of the fitting clips, cameras and noise.
    #[arg(long, default_value_t = blapose_train::proportions::FIT_SEED)]
    seed: u64,
    /// Frames (50 Hz) of training-subject motion per body.
    #[arg(long, default_value_t = blapose_train::bodies::DEFAULT_FRAMES)]
    frames: usize,
}

/// Build the fitting clips, fit and write.
pub fn fit_proportions(a: FitProportionsArgs) -> Result<()> {
    let t0 = Instant::now();
    let root = blapose_data::data_root(a.data.clone());
    let set = TrainingSet::load(&root)?;
    let stats = TrainingLengthStats::from_training(&set.lengths_list())?;
    let split = AnsurSplit::load(&root, &stats)?;
    let h36m = H36m::load(&root, &TRAIN_SUBJECTS, Parts::POSES)?;
    let motions = test_motions(&h36m, &TRAIN_SUBJECTS)?;
    let people = fit_people(&split.everyone, a.people.unwrap_or(usize::MAX));
    eprintln!(
        "fitting on {} clips of {} frames on {} training-subject sequences...",
        people.len(),
        a.frames,
        motions.len()
    );
    let model = blapose_train::proportions::fit_training(&TrainingBodies {
        people,
        motions: &motions,
        residuals: &set.residuals,
        seed: a.seed,
        frames: a.frames,
    })?;
    std::fs::write(&a.out, model.to_json())
        .with_context(|| format!("writing {}", a.out.display()))?;
    println!(
        "fitted on {} bodies ({} women, {} men) in {:.0}s; wrote {}",
        model.pooled.people,
        model.female.people,
        model.male.people,
        t0.elapsed().as_secs_f64(),
        a.out.display()
    );
    Ok(())
}

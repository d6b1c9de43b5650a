//! `blapose fit-stature`: fit the stature regression on the ANSUR II
//! training split and write the file the server embeds
//! (`models/stature_regression.json`); the fit is
//! [`blapose_train::stature`], the file format
//! [`blapose_model::stature`].

use std::path::PathBuf;

use anyhow::{Context, Result};
use blapose_train::ansur_split::AnsurSplit;
use blapose_train::dataset::TrainingSet;
use blapose_train::lengths::TrainingLengthStats;
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

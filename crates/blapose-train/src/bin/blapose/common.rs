//! What several commands share: the model-kind flag, subject and camera
//! lists, the progress bar. Kept here so each command reads them the same
//! way.

use anyhow::Result;
use blapose_data::h36m::ALL_SUBJECTS;
use blapose_model::ModelKind;
use indicatif::{ProgressBar, ProgressStyle};

/// `--model` of the bone-length commands: [`ModelKind`] as a flag
/// (`gru`, `bigru`, also spelled `bi-gru`; any case).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum ModelArg {
    /// The online model (two unidirectional GRUs).
    Gru,
    /// The offline model (one bidirectional GRU).
    #[value(name = "bigru", alias = "bi-gru")]
    BiGru,
}

impl From<ModelArg> for ModelKind {
    fn from(m: ModelArg) -> Self {
        match m {
            ModelArg::Gru => ModelKind::Gru,
            ModelArg::BiGru => ModelKind::BiGru,
        }
    }
}

/// The progress bar of a training run (`steps` optimizer steps).
pub fn step_bar(steps: u64) -> ProgressBar {
    let pb = ProgressBar::new(steps);
    pb.set_style(
        ProgressStyle::with_template("{elapsed_precise} [{bar:30}] {pos}/{len} eta {eta} {msg}")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    pb
}

/// A `--cameras` list for messages: the ids, or `all` when none is given.
pub fn camera_list(ids: &[String]) -> String {
    if ids.is_empty() {
        "all".to_string()
    } else {
        ids.join(",")
    }
}

/// `--subjects` as names, refusing any Human3.6M does not have.
pub fn known_subjects(subjects: &[String]) -> Result<Vec<&str>> {
    let names: Vec<&str> = subjects.iter().map(String::as_str).collect();
    if let Some(bad) = names.iter().find(|s| !ALL_SUBJECTS.contains(s)) {
        anyhow::bail!("unknown subject {bad} (known: {})", ALL_SUBJECTS.join(","));
    }
    Ok(names)
}

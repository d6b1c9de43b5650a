//! What the `blapose` and `blapose-lab` command lines share: the model-kind
//! flag and the reading of subject and camera lists. Here, in the library,
//! so that both binaries read them the same way.

use blapose_data::h36m::ALL_SUBJECTS;
use blapose_model::ModelKind;

use crate::error::TrainError;

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

/// A `--cameras` list for messages: the ids, or `all` when none is given.
pub fn camera_list(ids: &[String]) -> String {
    if ids.is_empty() {
        "all".to_string()
    } else {
        ids.join(",")
    }
}

/// `--subjects` as names, refusing any Human3.6M does not have.
pub fn known_subjects(subjects: &[String]) -> Result<Vec<&str>, TrainError> {
    let names: Vec<&str> = subjects.iter().map(String::as_str).collect();
    if let Some(bad) = names.iter().find(|s| !ALL_SUBJECTS.contains(s)) {
        return Err(TrainError::InvalidArgument(format!(
            "unknown subject {bad} (known: {})",
            ALL_SUBJECTS.join(",")
        )));
    }
    Ok(names)
}

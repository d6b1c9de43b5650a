//! The one error type of the training library. Binaries wrap it in
//! `anyhow`; library code never panics on user input or data files.

use std::path::PathBuf;

/// What can go wrong while loading data, training or evaluating.
#[derive(Debug, thiserror::Error)]
pub enum TrainError {
    /// A flag or argument has an impossible value.
    #[error("invalid argument: {0}")]
    InvalidArgument(String),
    /// The data set is missing something or is malformed.
    #[error("data: {0}")]
    Data(String),
    /// Human3.6M could not be read.
    #[error(transparent)]
    H36m(#[from] blapose_data::h36m::H36mError),
    /// The ANSUR II CSVs could not be read.
    #[error(transparent)]
    AnsurData(#[from] blapose_data::ansur::AnsurError),
    /// A keypoint layout conversion failed.
    #[error(transparent)]
    Layout(#[from] blapose_core::layouts::LayoutError),
    /// The ANSUR mapping could not be applied.
    #[error("ANSUR II: {0}")]
    Ansur(String),
    /// The stature regression could not be fitted or applied.
    #[error(transparent)]
    Stature(#[from] StatureError),
    /// A geometric operation failed.
    #[error(transparent)]
    Bone(#[from] blapose_core::bones::BoneError),
    /// A model or tensor operation failed.
    #[error(transparent)]
    Candle(#[from] candle_core::Error),
    /// Loading or saving model weights failed.
    #[error(transparent)]
    Model(#[from] blapose_model::ModelError),
    /// Weights' input contract cannot be applied to a view.
    #[error(transparent)]
    Contract(#[from] blapose_model::input::ContractError),
    /// An inference-crate lifter failed.
    #[error(transparent)]
    Lifter(#[from] blapose_lifters::LifterError),
    /// A checkpoint is unreadable or does not fit the run.
    #[error("checkpoint {path}: {msg}")]
    Checkpoint {
        /// The checkpoint file.
        path: PathBuf,
        /// What is wrong.
        msg: String,
    },
    /// Filesystem error with the path it happened on.
    #[error("{path}: {source}")]
    Io {
        /// The path.
        path: PathBuf,
        /// The underlying error.
        source: std::io::Error,
    },
    /// Plot rendering failed.
    #[error("plot: {0}")]
    Plot(String),
    /// JSON (de)serialisation failed.
    #[error(transparent)]
    Json(#[from] serde_json::Error),
}

impl TrainError {
    /// Wrap an I/O error with its path.
    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        Self::Io {
            path: path.into(),
            source,
        }
    }
}

/// Why the regression could not be fitted or applied.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum StatureError {
    /// A group has fewer than two people: no line through them.
    #[error("stature regression ({group}): needs at least 2 people, got {people}")]
    TooFewPeople {
        /// `everyone`, `male` or `female`.
        group: &'static str,
        /// How many there were.
        people: usize,
    },
    /// Everyone in a group has the same stature: no slope.
    #[error("stature regression ({group}): every person has the same stature")]
    NoStatureSpread {
        /// `everyone`, `male` or `female`.
        group: &'static str,
    },
    /// A person's stature or a length is NaN or infinite.
    #[error("stature regression: person {subject_id} has a non-finite stature or length")]
    NonFinite {
        /// The survey id.
        subject_id: u64,
    },
    /// A stature to predict from is not a positive finite height.
    #[error("stature regression: {0} m is not a positive finite stature")]
    BadStature(f64),
    /// Sex was given but that sex had no fit.
    #[error("stature regression: no fit for {0} (too few of them, or no spread)")]
    NoFitForSex(&'static str),
}

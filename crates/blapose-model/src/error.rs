//! The crate's one error type.
//!
//! Weight files and per-frame inputs come from outside the process, so every
//! way they can be wrong has its own variant: callers (the server, the CLI)
//! turn these into user-facing messages and status codes without parsing
//! strings.

use crate::ModelKind;

/// Everything that can go wrong loading weights or running a model.
#[derive(Debug, thiserror::Error)]
pub enum ModelError {
    /// The weights' input contract cannot be read or is no longer served.
    #[error(transparent)]
    Contract(#[from] crate::input::ContractError),

    /// A model kind string that is neither `gru` nor `bigru`.
    #[error(transparent)]
    UnknownKind(#[from] blapose_core::model_kind::UnknownModelKind),

    /// Reading or writing a weights file failed.
    #[error("{path}: {source}")]
    Io {
        /// The file involved.
        path: String,
        /// The underlying error.
        source: std::io::Error,
    },

    /// The bytes are not a valid safetensors file.
    #[error("not a valid safetensors file: {0}")]
    InvalidFile(String),

    /// The safetensors header has no blapose metadata entry `key`.
    #[error("weights metadata is missing {key:?} (not a blapose weights file?)")]
    MissingMetadata {
        /// The missing `__metadata__` key.
        key: &'static str,
    },

    /// A metadata entry exists but cannot be used.
    #[error("weights metadata {key:?} = {value:?} is invalid: {reason}")]
    BadMetadata {
        /// The `__metadata__` key.
        key: &'static str,
        /// Its value in the file.
        value: String,
        /// Why it was refused.
        reason: String,
    },

    /// The file holds weights for another model kind.
    #[error("weights are for model kind {found}, expected {expected}")]
    WrongKind {
        /// The kind the caller asked for.
        expected: ModelKind,
        /// The kind recorded in the file.
        found: ModelKind,
    },

    /// A tensor the model needs is absent.
    #[error("weights for {kind} lack tensor {name:?}")]
    MissingTensor {
        /// Model kind being loaded.
        kind: ModelKind,
        /// Name of the missing tensor.
        name: String,
    },

    /// A tensor that no model of this kind has.
    #[error("weights for {kind} contain unexpected tensor {name:?}")]
    UnexpectedTensor {
        /// Model kind being loaded.
        kind: ModelKind,
        /// Name of the extra tensor.
        name: String,
    },

    /// A tensor with the wrong shape.
    #[error("tensor {name:?} has shape {found:?}, expected {expected:?}")]
    ShapeMismatch {
        /// Tensor name.
        name: String,
        /// Shape the model needs.
        expected: Vec<usize>,
        /// Shape in the file.
        found: Vec<usize>,
    },

    /// A tensor stored in a dtype the loader does not convert.
    #[error("tensor {name:?} has unsupported dtype {dtype}")]
    UnsupportedDtype {
        /// Tensor name.
        name: String,
        /// The dtype as safetensors names it.
        dtype: String,
    },

    /// A weight is NaN or infinite.
    #[error("tensor {name:?} contains a non-finite value")]
    NonFiniteWeight {
        /// Tensor name.
        name: String,
    },

    /// A caller passed a buffer of the wrong length.
    #[error("{what}: expected {expected} values, got {found}")]
    BadLength {
        /// Which argument.
        what: &'static str,
        /// Required length.
        expected: usize,
        /// Given length.
        found: usize,
    },

    /// An input keypoint value is NaN or infinite; nothing was updated.
    #[error("non-finite input at row {row}, value {col}; no hidden state was updated")]
    NonFiniteInput {
        /// Batch row (session) or frame index of the bad value.
        row: usize,
        /// Index within the 34 input values of that row.
        col: usize,
    },

    /// A step produced a non-finite state (e.g. from absurdly large inputs);
    /// the step was discarded and no hidden state was updated.
    #[error("step produced a non-finite state for row {row}; no hidden state was updated")]
    NonFiniteState {
        /// Batch row (session) whose result was non-finite.
        row: usize,
    },

    /// An offline sequence with no frames.
    #[error("cannot predict from an empty sequence")]
    EmptySequence,

    /// A bad engine configuration (thread count, ISA not supported here, ...).
    #[error("invalid engine configuration: {0}")]
    Config(String),

    /// An error from candle.
    #[error(transparent)]
    Candle(#[from] candle_core::Error),
}

/// An instruction set this CPU lacks (or a name that is none) is a bad
/// engine configuration; the message is the instruction set's own.
impl From<blapose_core::isa::IsaError> for ModelError {
    fn from(e: blapose_core::isa::IsaError) -> Self {
        ModelError::Config(e.to_string())
    }
}

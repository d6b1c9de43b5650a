//! Model execution behind a trait, so the batcher and the service can be
//! tested with a fake model and the real engines stay in blapose-model.
//!
//! [`Backend`] is one batched online step (what the batcher runs);
//! [`SequenceBackend`] is a whole-sequence prediction (what offline requests
//! run). The real implementations wrap blapose-model's fast engines.

use blapose_core::BoneLengths;

/// Values per input frame (17 joints x 2 normalized coordinates).
pub const INPUT_DIM: usize = blapose_model::INPUT_DIM;
/// Floats of recurrent state per session.
pub const STATE_DIM: usize = blapose_model::STATE_DIM;
/// Predicted lengths per frame.
pub const OUTPUT_DIM: usize = blapose_model::OUTPUT_DIM;

/// A failed model call.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum BackendError {
    /// Buffers do not match the batch size.
    #[error("buffer shapes do not match batch {batch}: {detail}")]
    Shape {
        /// The batch size given.
        batch: usize,
        /// What was wrong.
        detail: String,
    },
    /// The model refused the input or failed.
    #[error("model error: {0}")]
    Model(String),
}

/// One batched step of the online model.
pub trait Backend: Send + 'static {
    /// Advance `batch` independent sessions by one frame.
    ///
    /// `inputs` is `batch x INPUT_DIM` normalized keypoints, `hidden` is
    /// `batch x STATE_DIM` recurrent states (read, then overwritten with the
    /// new states), `lengths_out` receives `batch x OUTPUT_DIM` per-frame
    /// length predictions (symmetric pairs averaged).
    fn step(
        &mut self,
        inputs: &[f32],
        hidden: &mut [f32],
        lengths_out: &mut [f32],
        batch: usize,
    ) -> Result<(), BackendError>;
}

/// A whole-sequence bone-length prediction (the offline Bi-GRU).
pub trait SequenceBackend: Send + 'static {
    /// Predict one set of lengths from `frames x INPUT_DIM` inputs.
    fn predict(&mut self, inputs: &[f32], frames: usize) -> Result<BoneLengths, BackendError>;
}

/// Check the buffer sizes of a [`Backend::step`] call.
pub fn check_step_shapes(
    inputs: &[f32],
    hidden: &[f32],
    lengths_out: &[f32],
    batch: usize,
) -> Result<(), BackendError> {
    let want = (batch * INPUT_DIM, batch * STATE_DIM, batch * OUTPUT_DIM);
    let got = (inputs.len(), hidden.len(), lengths_out.len());
    if want != got {
        return Err(BackendError::Shape {
            batch,
            detail: format!(
                "inputs/hidden/lengths have {}/{}/{} floats, expected {}/{}/{}",
                got.0, got.1, got.2, want.0, want.1, want.2
            ),
        });
    }
    Ok(())
}

impl Backend for Box<dyn Backend> {
    fn step(
        &mut self,
        inputs: &[f32],
        hidden: &mut [f32],
        lengths_out: &mut [f32],
        batch: usize,
    ) -> Result<(), BackendError> {
        (**self).step(inputs, hidden, lengths_out, batch)
    }
}

impl SequenceBackend for Box<dyn SequenceBackend> {
    fn predict(&mut self, inputs: &[f32], frames: usize) -> Result<BoneLengths, BackendError> {
        (**self).predict(inputs, frames)
    }
}

//! The step stage: one batched GRU step per model for the rows of a batch.
//!
//! The rows [`crate::prepare`] finished are gathered into contiguous
//! buffers (each session's hidden state and its model input), run through
//! [`Backend::step`] once per model, and left in the buffers for
//! [`crate::answer`] to commit; this module answers only the rows that
//! failed. Sessions opened with a camera calibration are served by a
//! second model ([`OnlineBackends::camera_aware`]): a batch's rows are
//! grouped by model and each group runs as its own step. Hidden states
//! stay in their sessions until committed, so a failed step never corrupts
//! a session. When the engine refuses a whole batch for one bad row, the
//! rows are retried one at a time, so one session's problem never fails
//! another session's frame.

use std::ops::Range;

use crate::backend::{Backend, BackendError, INPUT_DIM, OUTPUT_DIM, STATE_DIM};
use crate::batch::Queued;
use crate::frame::{FrameJob, StepError, StepResult};
use crate::prepare;

/// The online models a batcher runs.
#[derive(Debug)]
pub struct OnlineBackends<B> {
    /// For sessions without a camera calibration.
    pub default: B,
    /// For sessions with one (fed their keypoints as the model's input
    /// contract says); `None`: the server has no camera-aware model and
    /// refuses such sessions at open.
    pub camera_aware: Option<B>,
}

/// Run one step on zero inputs and check the outputs are finite, so a
/// server reports SERVING only with a model that works.
pub fn warm_up<B: Backend>(backend: &mut B) -> Result<(), BackendError> {
    let inputs = [0.0f32; INPUT_DIM];
    let mut hidden = vec![0.0f32; STATE_DIM];
    let mut lengths = [0.0f32; OUTPUT_DIM];
    backend.step(&inputs, &mut hidden, &mut lengths, 1)?;
    if hidden.iter().chain(lengths.iter()).all(|v| v.is_finite()) {
        Ok(())
    } else {
        Err(BackendError::Model(
            "warm-up step produced non-finite values".into(),
        ))
    }
}

/// Preallocated step buffers (no allocation per batch).
#[derive(Debug)]
pub struct StepBuffers {
    inputs: Vec<f32>,
    hidden: Vec<f32>,
    lengths: Vec<f32>,
    /// For each buffer row, its index in the batch.
    rows: Vec<usize>,
}

impl StepBuffers {
    /// Buffers for batches of up to `max_batch` frames.
    pub fn new(max_batch: usize) -> Self {
        Self {
            inputs: vec![0.0; max_batch * INPUT_DIM],
            hidden: vec![0.0; max_batch * STATE_DIM],
            lengths: vec![0.0; max_batch * OUTPUT_DIM],
            rows: Vec::with_capacity(max_batch),
        }
    }

    /// The rows stepped by the last [`run`], as (index in the batch, new
    /// hidden state, predicted lengths); a row's values are meaningful only
    /// when its frame has no answer yet.
    pub fn stepped(&self) -> impl Iterator<Item = (usize, &[f32], &[f32])> {
        self.rows.iter().enumerate().map(|(r, &i)| {
            (
                i,
                &self.hidden[r * STATE_DIM..(r + 1) * STATE_DIM],
                &self.lengths[r * OUTPUT_DIM..(r + 1) * OUTPUT_DIM],
            )
        })
    }
}

/// Step every row of `batch` not answered yet: the default model's rows
/// first, then the camera-aware ones, each group one step. A row that
/// fails gets its answer here; the others' new hidden states and
/// predictions are left in `buf` ([`StepBuffers::stepped`]). Returns the
/// rows stepped.
pub fn run<B: Backend>(
    backends: &mut OnlineBackends<B>,
    batch: &[Queued],
    answers: &mut [Option<StepResult>],
    buf: &mut StepBuffers,
) -> usize {
    buf.rows.clear();
    let split = gather_rows(batch, answers, buf, false);
    let n = gather_rows(batch, answers, buf, true);
    step_rows(&mut backends.default, batch, answers, buf, 0..split);
    if split < n {
        match &mut backends.camera_aware {
            Some(backend) => step_rows(backend, batch, answers, buf, split..n),
            None => {
                for &i in &buf.rows[split..n] {
                    answers[i] = Some(Err(StepError::Model(
                        "this server has no camera-aware model".into(),
                    )));
                }
            }
        }
    }
    n
}

/// Append to the buffers the rows of sessions with (`camera_aware`) or
/// without a camera that are still owned by the frame's stream and not yet
/// answered: their hidden states and their model inputs
/// ([`prepare::model_row`]); returns the rows gathered so far.
fn gather_rows(
    batch: &[Queued],
    answers: &mut [Option<StepResult>],
    buf: &mut StepBuffers,
    camera_aware: bool,
) -> usize {
    for (i, item) in batch.iter().enumerate() {
        let has_camera = item.job.session.config().camera.is_some();
        if answers[i].is_some() || has_camera != camera_aware {
            continue;
        }
        let st = item.job.session.lock();
        if !st.accepts(item.job.epoch) {
            answers[i] = Some(Err(StepError::Superseded));
            continue;
        }
        let r = buf.rows.len();
        buf.hidden[r * STATE_DIM..(r + 1) * STATE_DIM].copy_from_slice(&st.hidden);
        drop(st);
        prepare::model_row(
            &item.job,
            &mut buf.inputs[r * INPUT_DIM..(r + 1) * INPUT_DIM],
        );
        buf.rows.push(i);
    }
    buf.rows.len()
}

/// Run the buffer rows `range` through `backend` as one step.
fn step_rows<B: Backend>(
    backend: &mut B,
    batch: &[Queued],
    answers: &mut [Option<StepResult>],
    buf: &mut StepBuffers,
    range: Range<usize>,
) {
    let n = range.len();
    if n == 0 {
        return;
    }
    let (start, end) = (range.start, range.end);
    let result = backend.step(
        &buf.inputs[start * INPUT_DIM..end * INPUT_DIM],
        &mut buf.hidden[start * STATE_DIM..end * STATE_DIM],
        &mut buf.lengths[start * OUTPUT_DIM..end * OUTPUT_DIM],
        n,
    );
    match result {
        Ok(()) => {}
        // The engine refuses a whole batch for one bad row; isolate it by
        // re-running the rows one at a time, so one session's problem
        // never fails another session's frame.
        Err(e) if n > 1 => {
            tracing::warn!(error = %e, batch = n, "batched step failed; retrying its rows one by one");
            for r in start..end {
                let i = buf.rows[r];
                if let Err(e) = step_alone(backend, &batch[i].job, buf, r) {
                    answers[i] = Some(Err(e));
                }
            }
        }
        Err(e) => {
            for &i in &buf.rows[range] {
                answers[i] = Some(Err(StepError::Model(e.to_string())));
            }
        }
    }
}

/// Run buffer row `r` on its own, its state re-read from the session
/// (a failed step may have touched the gathered buffer).
fn step_alone<B: Backend>(
    backend: &mut B,
    job: &FrameJob,
    buf: &mut StepBuffers,
    r: usize,
) -> Result<(), StepError> {
    let hidden = &mut buf.hidden[r * STATE_DIM..(r + 1) * STATE_DIM];
    {
        let st = job.session.lock();
        if !st.accepts(job.epoch) {
            return Err(StepError::Superseded);
        }
        hidden.copy_from_slice(&st.hidden);
    }
    backend
        .step(
            &buf.inputs[r * INPUT_DIM..(r + 1) * INPUT_DIM],
            hidden,
            &mut buf.lengths[r * OUTPUT_DIM..(r + 1) * OUTPUT_DIM],
            1,
        )
        .map_err(|e| StepError::Model(e.to_string()))
}

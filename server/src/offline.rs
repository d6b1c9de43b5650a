//! Offline adjustment of a whole sequence (the `AdjustSequence` RPC).
//!
//! A request runs on tokio's blocking pool, never on an async worker, and at
//! most `compute_threads` run at once (a semaphore) so offline work cannot
//! starve the online batcher of CPU. Backends are pooled: building one
//! re-lays-out the weights, which is worth doing once, not per request.

use std::sync::{Arc, Mutex, PoisonError};
use std::time::Instant;

use blapose_core::bones::{self, ZeroBonePolicy};
use blapose_core::{BoneLengths, Pose};
use tokio::sync::Semaphore;
use tonic::Status;

use crate::backend::{Backend, BackendError, INPUT_DIM, OUTPUT_DIM, STATE_DIM};
use crate::metrics;
use crate::models::ModelProvider;
use crate::session::RunningLengths;
use crate::validate::{OfflineModel, ValidSequence};

/// Result of an offline request.
#[derive(Debug, Clone, PartialEq)]
pub struct AdjustedSequence {
    /// Adjusted poses, one per frame.
    pub poses: Vec<Pose>,
    /// Lengths applied to each frame.
    pub lengths: Vec<BoneLengths>,
}

type Pool<T> = Arc<Mutex<Vec<T>>>;

/// Runs offline requests with bounded concurrency.
pub struct OfflineRunner {
    provider: Arc<dyn ModelProvider>,
    permits: Arc<Semaphore>,
    online: Pool<Box<dyn Backend>>,
    offline: Pool<Box<dyn crate::backend::SequenceBackend>>,
}

impl std::fmt::Debug for OfflineRunner {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("OfflineRunner")
            .field("available_permits", &self.permits.available_permits())
            .finish()
    }
}

fn take<T>(pool: &Pool<T>) -> Option<T> {
    pool.lock().unwrap_or_else(PoisonError::into_inner).pop()
}

fn give<T>(pool: &Pool<T>, item: T) {
    pool.lock()
        .unwrap_or_else(PoisonError::into_inner)
        .push(item);
}

fn internal(e: BackendError) -> Status {
    Status::internal(format!("model failed: {e}"))
}

impl OfflineRunner {
    /// A runner allowing `concurrency` requests at once.
    pub fn new(provider: Arc<dyn ModelProvider>, concurrency: usize) -> Self {
        Self {
            provider,
            permits: Arc::new(Semaphore::new(concurrency.max(1))),
            online: Arc::default(),
            offline: Arc::default(),
        }
    }

    /// Predict lengths for a validated sequence and adjust its poses.
    pub async fn adjust(&self, seq: ValidSequence) -> Result<AdjustedSequence, Status> {
        let _permit = self
            .permits
            .clone()
            .acquire_owned()
            .await
            .map_err(|_| Status::unavailable("the server is shutting down"))?;
        let provider = self.provider.clone();
        let online = self.online.clone();
        let offline = self.offline.clone();
        let started = Instant::now();
        let model = seq.model;
        let result = tokio::task::spawn_blocking(move || -> Result<AdjustedSequence, Status> {
            let frames = seq.poses.len();
            let lengths = match model {
                OfflineModel::BiGru => {
                    let mut backend = match take(&offline) {
                        Some(b) => b,
                        None => provider.offline().map_err(internal)?,
                    };
                    let predicted = backend.predict(&seq.inputs, frames);
                    give(&offline, backend);
                    let predicted = predicted.map_err(internal)?;
                    if !predicted.iter().all(|v| v.is_finite()) {
                        return Err(Status::internal(
                            "the model produced non-finite bone lengths",
                        ));
                    }
                    vec![predicted; frames]
                }
                OfflineModel::OnlineGru => {
                    let mut backend = match take(&online) {
                        Some(b) => b,
                        None => provider.online().map_err(internal)?,
                    };
                    let result = online_lengths(backend.as_mut(), &seq.inputs, frames);
                    give(&online, backend);
                    result?
                }
            };
            let poses =
                bones::adjust_sequence_per_frame(&seq.poses, &lengths, ZeroBonePolicy::Error)
                    .map_err(|e| Status::internal(format!("adjustment failed: {e}")))?;
            Ok(AdjustedSequence { poses, lengths })
        })
        .await
        .map_err(|e| Status::internal(format!("offline worker failed: {e}")))?;
        metrics::offline(
            match model {
                OfflineModel::BiGru => "bigru",
                OfflineModel::OnlineGru => "gru",
            },
            started.elapsed(),
        );
        result
    }
}

/// The online model run causally over a sequence, one step per frame: row
/// `t` is the running mean of the predictions of frames `0..=t`, exactly
/// what a stream would have answered.
pub fn online_lengths(
    backend: &mut dyn Backend,
    inputs: &[f32],
    frames: usize,
) -> Result<Vec<BoneLengths>, Status> {
    let mut hidden = vec![0.0f32; STATE_DIM];
    let mut prediction = [0.0f32; OUTPUT_DIM];
    let mut running = RunningLengths::default();
    let mut out = Vec::with_capacity(frames);
    for (t, x) in inputs.chunks_exact(INPUT_DIM).take(frames).enumerate() {
        backend
            .step(x, &mut hidden, &mut prediction, 1)
            .map_err(internal)?;
        if !hidden
            .iter()
            .chain(prediction.iter())
            .all(|v| v.is_finite())
        {
            return Err(Status::internal(format!(
                "the model produced a non-finite result at frame {t}"
            )));
        }
        running.add(&prediction);
        out.push(running.mean().unwrap_or(prediction));
    }
    Ok(out)
}

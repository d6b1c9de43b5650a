//! blapose-model's fast engines behind the [`Backend`] traits.
//!
//! The engines are immutable after construction (weights repacked once) and
//! take `&self`, so one engine per model is shared by the batcher and every
//! offline worker; each backend only owns its scratch buffers.

use std::sync::Arc;

use blapose_core::BoneLengths;
use blapose_model::{
    EngineOptions, LoadedWeights, ModelError, OfflineBiGruEngine, OnlineGruEngine, Precision,
    StepScratch,
};

use crate::backend::{check_step_shapes, Backend, BackendError, SequenceBackend, INPUT_DIM};

fn options(threads: usize, precision: Precision) -> EngineOptions {
    EngineOptions {
        precision,
        ..EngineOptions::threads(threads.max(1))
    }
}

fn model_error(e: ModelError) -> BackendError {
    BackendError::Model(e.to_string())
}

/// Build the online engine (`threads` workers per step, GRU weights
/// stored at `precision`).
pub fn online_engine(
    weights: &LoadedWeights,
    threads: usize,
    precision: Precision,
) -> Result<Arc<OnlineGruEngine>, BackendError> {
    OnlineGruEngine::with_options(weights, options(threads, precision))
        .map(Arc::new)
        .map_err(model_error)
}

/// Build the offline engine (`threads >= 2` runs both directions at once).
pub fn offline_engine(
    weights: &LoadedWeights,
    threads: usize,
    precision: Precision,
) -> Result<Arc<OfflineBiGruEngine>, BackendError> {
    OfflineBiGruEngine::with_options(weights, options(threads, precision))
        .map(Arc::new)
        .map_err(model_error)
}

/// The online GRU step on the shared fast engine.
pub struct GruBackend {
    engine: Arc<OnlineGruEngine>,
    scratch: StepScratch,
}

impl std::fmt::Debug for GruBackend {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("GruBackend")
            .field("engine", &self.engine)
            .field("scratch_batch", &self.scratch.capacity())
            .finish()
    }
}

impl GruBackend {
    /// A backend with scratch for batches up to `max_batch` (it grows if
    /// needed).
    pub fn new(engine: Arc<OnlineGruEngine>, max_batch: usize) -> Self {
        let scratch = engine.scratch(max_batch.max(1));
        Self { engine, scratch }
    }
}

impl Backend for GruBackend {
    fn step(
        &mut self,
        inputs: &[f32],
        hidden: &mut [f32],
        lengths_out: &mut [f32],
        batch: usize,
    ) -> Result<(), BackendError> {
        check_step_shapes(inputs, hidden, lengths_out, batch)?;
        if batch == 0 {
            return Ok(());
        }
        self.engine
            .step(inputs, hidden, lengths_out, &mut self.scratch)
            .map_err(model_error)
    }
}

/// The offline Bi-GRU on the shared fast engine.
#[derive(Debug, Clone)]
pub struct BiGruBackend {
    engine: Arc<OfflineBiGruEngine>,
}

impl BiGruBackend {
    /// A backend over `engine`.
    pub fn new(engine: Arc<OfflineBiGruEngine>) -> Self {
        Self { engine }
    }
}

impl SequenceBackend for BiGruBackend {
    fn predict(&mut self, inputs: &[f32], frames: usize) -> Result<BoneLengths, BackendError> {
        if inputs.len() != frames * INPUT_DIM {
            return Err(BackendError::Shape {
                batch: frames,
                detail: format!(
                    "{} input values for {frames} frames of {INPUT_DIM}",
                    inputs.len()
                ),
            });
        }
        self.engine.predict(inputs).map_err(model_error)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use blapose_model::ModelKind;

    #[test]
    fn online_backend_matches_the_engine_and_refuses_bad_shapes() {
        let weights = LoadedWeights::random(ModelKind::Gru, 3).unwrap();
        let engine = online_engine(&weights, 1, Precision::F32).unwrap();
        let mut backend = GruBackend::new(engine.clone(), 4);
        let inputs: Vec<f32> = (0..2 * INPUT_DIM)
            .map(|i| (i as f32 * 0.37).sin())
            .collect();
        let mut h1 = vec![0.0; 2 * crate::backend::STATE_DIM];
        let mut y1 = vec![0.0; 2 * crate::backend::OUTPUT_DIM];
        backend.step(&inputs, &mut h1, &mut y1, 2).unwrap();
        let mut h2 = vec![0.0; 2 * crate::backend::STATE_DIM];
        let mut y2 = vec![0.0; 2 * crate::backend::OUTPUT_DIM];
        engine
            .step(&inputs, &mut h2, &mut y2, &mut engine.scratch(2))
            .unwrap();
        assert_eq!(h1, h2);
        assert_eq!(y1, y2);
        assert!(h1.iter().any(|&v| v != 0.0));
        assert!(matches!(
            backend.step(&inputs, &mut h1, &mut y1, 3),
            Err(BackendError::Shape { .. })
        ));
        let mut bad = inputs.clone();
        bad[3] = f32::NAN;
        let before = h1.clone();
        assert!(matches!(
            backend.step(&bad, &mut h1, &mut y1, 2),
            Err(BackendError::Model(_))
        ));
        assert_eq!(h1, before, "a refused step leaves the states alone");
    }

    #[test]
    fn offline_backend_predicts_finite_lengths() {
        let weights = LoadedWeights::random(ModelKind::BiGru, 4).unwrap();
        let mut backend = BiGruBackend::new(offline_engine(&weights, 1, Precision::F32).unwrap());
        let inputs: Vec<f32> = (0..5 * INPUT_DIM)
            .map(|i| (i as f32 * 0.11).cos())
            .collect();
        let y = backend.predict(&inputs, 5).unwrap();
        assert!(y.iter().all(|v| v.is_finite()));
        assert!(matches!(
            backend.predict(&inputs, 4),
            Err(BackendError::Shape { .. })
        ));
    }
}

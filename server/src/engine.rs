//! blapose-model's fast engines behind the [`Backend`] traits (wiring pending).

use blapose_core::BoneLengths;
use blapose_model::LoadedWeights;

use crate::backend::{Backend, BackendError, SequenceBackend};

/// The online GRU step.
#[derive(Debug)]
pub struct GruBackend;

impl GruBackend {
    /// Build from weights.
    pub fn new(_weights: &LoadedWeights, _threads: usize) -> Result<Self, BackendError> {
        Err(BackendError::Model("fast engine not wired yet".into()))
    }
}

impl Backend for GruBackend {
    fn step(&mut self, _: &[f32], _: &mut [f32], _: &mut [f32], _: usize) -> Result<(), BackendError> {
        Err(BackendError::Model("fast engine not wired yet".into()))
    }
}

/// The offline Bi-GRU.
#[derive(Debug)]
pub struct BiGruBackend;

impl BiGruBackend {
    /// Build from weights.
    pub fn new(_weights: &LoadedWeights) -> Result<Self, BackendError> {
        Err(BackendError::Model("fast engine not wired yet".into()))
    }
}

impl SequenceBackend for BiGruBackend {
    fn predict(&mut self, _: &[f32], _: usize) -> Result<BoneLengths, BackendError> {
        Err(BackendError::Model("fast engine not wired yet".into()))
    }
}

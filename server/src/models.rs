//! Which weights the server runs and how model backends are made from them.
//!
//! The default weights are compiled into the binary (`include_bytes!` of
//! `models/bone_length_{gru,bigru}.safetensors`, located by `build.rs`), so
//! `blapose-server` serves with no arguments; `--weights` and
//! `--bigru-weights` override them. [`ModelProvider`] is the seam between the
//! service and model execution: the real [`WeightsProvider`] builds
//! blapose-model's fast engines, tests plug in fakes. A server lifter is
//! never embedded: it runs only when `--lifter-weights` names a trained file
//! ([`LoadedLifter`]).

use std::collections::HashMap;
use std::path::Path;
use std::sync::Arc;

use blapose_lifters::{TrainedLifter, TrainedLifterError};
use blapose_model::weights::{self, LoadedWeights};
use blapose_model::{ModelError, ModelKind, OfflineBiGruEngine, OnlineGruEngine, Precision};
use blapose_proto::v1 as pb;
use sha2::{Digest, Sha256};

use crate::backend::{Backend, BackendError, SequenceBackend};
use crate::config::WeightsSource;
use crate::engine;
use crate::error::ServerError;

/// The embedded online GRU weights, if the build found them.
pub fn embedded_gru() -> Option<&'static [u8]> {
    #[cfg(blapose_embedded_gru)]
    {
        Some(include_bytes!(env!("BLAPOSE_EMBEDDED_GRU")))
    }
    #[cfg(not(blapose_embedded_gru))]
    {
        None
    }
}

/// The embedded offline Bi-GRU weights, if the build found them.
pub fn embedded_bigru() -> Option<&'static [u8]> {
    #[cfg(blapose_embedded_bigru)]
    {
        Some(include_bytes!(env!("BLAPOSE_EMBEDDED_BIGRU")))
    }
    #[cfg(not(blapose_embedded_bigru))]
    {
        None
    }
}

/// Why weights could not be loaded.
#[derive(Debug, thiserror::Error)]
pub enum WeightsError {
    /// The binary was built without default weights.
    #[error("this binary has no embedded {kind} weights (models/ was empty at build time); pass them with {flag}")]
    NotEmbedded {
        /// Which model.
        kind: ModelKind,
        /// The flag to use.
        flag: &'static str,
    },
    /// The file could not be read.
    #[error("cannot read {kind} weights {path}: {source}")]
    Io {
        /// Which model.
        kind: ModelKind,
        /// The path.
        path: String,
        /// The cause.
        #[source]
        source: std::io::Error,
    },
    /// The file is not valid weights of the right kind.
    #[error("invalid {kind} weights from {origin}: {source}")]
    Invalid {
        /// Which model.
        kind: ModelKind,
        /// Where they came from.
        origin: String,
        /// The cause.
        #[source]
        source: ModelError,
    },
    /// The `--lifter-weights` file cannot be served. (The cause is part of
    /// the message, not a `source()`, so an error chain prints it once.)
    #[error("cannot serve the lifter weights {path} (--lifter-weights): {cause}")]
    Lifter {
        /// The path.
        path: String,
        /// The cause.
        cause: TrainedLifterError,
    },
}

/// Weights of one model plus where they came from.
#[derive(Debug, Clone)]
pub struct LoadedModel {
    /// The validated tensors and metadata.
    pub weights: LoadedWeights,
    /// "embedded" or the file path.
    pub origin: String,
    /// Lowercase hex SHA-256 of the file bytes.
    pub sha256: String,
}

impl LoadedModel {
    /// Read and validate weights of `kind` from `source`.
    pub fn load(source: &WeightsSource, kind: ModelKind) -> Result<Self, WeightsError> {
        let (bytes, origin): (std::borrow::Cow<'static, [u8]>, String) = match source {
            WeightsSource::Embedded => {
                let (embedded, flag) = match kind {
                    ModelKind::Gru => (embedded_gru(), "--weights"),
                    ModelKind::BiGru => (embedded_bigru(), "--bigru-weights"),
                };
                let bytes = embedded.ok_or(WeightsError::NotEmbedded { kind, flag })?;
                (bytes.into(), "embedded".to_string())
            }
            WeightsSource::File(path) => {
                let bytes = std::fs::read(path).map_err(|source| WeightsError::Io {
                    kind,
                    path: path.display().to_string(),
                    source,
                })?;
                (bytes.into(), path.display().to_string())
            }
        };
        let weights =
            weights::load_bytes(&bytes, kind).map_err(|source| WeightsError::Invalid {
                kind,
                origin: origin.clone(),
                source,
            })?;
        Ok(Self {
            weights,
            origin,
            sha256: sha256_hex(&bytes),
        })
    }

    /// The `ModelInfo` entry for this model.
    pub fn describe(&self) -> pb::ModelDescription {
        let kind = self.weights.kind();
        let (model, name) = match kind {
            ModelKind::Gru => (pb::Model::OnlineGru, "bone_length_gru"),
            ModelKind::BiGru => (pb::Model::OfflineBigru, "bone_length_bigru"),
        };
        let parameter_count =
            blapose_model::reference::count_parameters(self.weights.tensors().values()) as u64;
        let metadata: HashMap<String, String> = self.weights.meta.to_header().into_iter().collect();
        pb::ModelDescription {
            model: model as i32,
            name: name.to_string(),
            parameter_count,
            hidden_size: blapose_model::HIDDEN as u32,
            weights_source: self.origin.clone(),
            weights_sha256: self.sha256.clone(),
            metadata,
        }
    }
}

fn sha256_hex(bytes: &[u8]) -> String {
    Sha256::digest(bytes)
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

/// The server lifter: a trained causal lifter plus where it came from.
#[derive(Debug)]
pub struct LoadedLifter {
    /// The lifter.
    pub lifter: TrainedLifter,
    /// The file path given at start.
    pub origin: String,
    /// Lowercase hex SHA-256 of the file bytes.
    pub sha256: String,
}

impl LoadedLifter {
    /// Read `path` and build the lifter, refusing files that cannot be
    /// served online (see [`blapose_lifters::trained`]).
    pub fn load(path: &Path) -> Result<Self, WeightsError> {
        let origin = path.display().to_string();
        let invalid = |cause| WeightsError::Lifter {
            path: origin.clone(),
            cause,
        };
        let bytes = std::fs::read(path).map_err(|source| {
            invalid(TrainedLifterError::Io {
                path: path.to_path_buf(),
                source,
            })
        })?;
        let lifter = TrainedLifter::from_bytes(&bytes).map_err(invalid)?;
        Ok(Self {
            lifter,
            sha256: sha256_hex(&bytes),
            origin,
        })
    }

    /// The lifter's name (as `AdjustedFrame.lifter` reports it).
    pub fn name(&self) -> &str {
        self.lifter.name()
    }

    /// The `ModelInfo` entry for the lifter.
    pub fn describe(&self) -> pb::LifterDescription {
        pb::LifterDescription {
            name: self.lifter.name().to_string(),
            receptive_field: u32::try_from(self.lifter.receptive_field()).unwrap_or(u32::MAX),
            parameter_count: self.lifter.params() as u64,
            causal: self.lifter.arch().causal,
            weights_source: self.origin.clone(),
            weights_sha256: self.sha256.clone(),
            metadata: self.lifter.metadata().to_pairs().into_iter().collect(),
        }
    }
}

/// Model execution as the service needs it.
pub trait ModelProvider: Send + Sync + 'static {
    /// A new online-step backend (one per batcher or offline worker).
    fn online(&self) -> Result<Box<dyn Backend>, BackendError>;
    /// A new whole-sequence backend.
    fn offline(&self) -> Result<Box<dyn SequenceBackend>, BackendError>;
    /// `ModelInfo` entries.
    fn describe(&self) -> Vec<pb::ModelDescription>;
}

/// The real provider: blapose-model's fast engines on loaded weights,
/// built once and shared by every backend.
#[derive(Debug, Clone)]
pub struct WeightsProvider {
    gru: LoadedModel,
    bigru: LoadedModel,
    online: Arc<OnlineGruEngine>,
    offline: Arc<OfflineBiGruEngine>,
}

/// Scratch preallocated per online backend (it grows if a batch is larger).
const SCRATCH_BATCH: usize = 64;

impl WeightsProvider {
    /// Load both models and build their engines with `threads` workers and
    /// the GRU weights stored at `precision`.
    pub fn load(
        gru: &WeightsSource,
        bigru: &WeightsSource,
        threads: usize,
        precision: Precision,
    ) -> Result<Self, ServerError> {
        let gru = LoadedModel::load(gru, ModelKind::Gru)?;
        let bigru = LoadedModel::load(bigru, ModelKind::BiGru)?;
        let online = engine::online_engine(&gru.weights, threads, precision)?;
        let offline = engine::offline_engine(&bigru.weights, threads, precision)?;
        Ok(Self {
            gru,
            bigru,
            online,
            offline,
        })
    }

    /// The online model's weights.
    pub fn gru(&self) -> &LoadedModel {
        &self.gru
    }

    /// The offline model's weights.
    pub fn bigru(&self) -> &LoadedModel {
        &self.bigru
    }
}

impl ModelProvider for WeightsProvider {
    fn online(&self) -> Result<Box<dyn Backend>, BackendError> {
        Ok(Box::new(engine::GruBackend::new(
            self.online.clone(),
            SCRATCH_BATCH,
        )))
    }

    fn offline(&self) -> Result<Box<dyn SequenceBackend>, BackendError> {
        Ok(Box::new(engine::BiGruBackend::new(self.offline.clone())))
    }

    fn describe(&self) -> Vec<pb::ModelDescription> {
        vec![self.gru.describe(), self.bigru.describe()]
    }
}

//! Which weights the server runs and how model backends are made from them.
//!
//! The default weights are compiled into the binary (`include_bytes!` of
//! `models/bone_length_{gru,bigru}{,_rectified}.safetensors`, located by
//! `build.rs`), so `blapose-server` serves with no arguments; `--weights`,
//! `--bigru-weights` and their `--rectified-*` twins override them. The
//! rectified pair is the *camera-aware* family: it serves the sessions and
//! requests that send a camera calibration (their keypoints prepared as the
//! weights' input contract says, [`crate::prepare`]);
//! [`ModelProvider::camera_aware`] is how the service reaches it. What a
//! file expects as input is read once, at load, into a [`ModelInput`]
//! (blapose-model's one reading of the weights' metadata); the server reads
//! no metadata key itself. [`ModelProvider`] is the seam between the
//! service and model execution: the real [`WeightsProvider`] builds
//! blapose-model's fast engines, tests plug in fakes. The server lifter
//! ([`LoadedLifter`]) is embedded the same way
//! (`models/lifter_videopose27_causal.safetensors`, 8.7 MB), so that a
//! browser or a 2D-only client is served by the no-argument server;
//! `--lifter-weights` overrides it and `--no-lifter` leaves it out.

use std::collections::HashMap;
use std::sync::Arc;

use blapose_lifters::{TrainedLifter, TrainedLifterError};
use blapose_model::input::ModelInput;
use blapose_model::stature::StatureModel;
use blapose_model::weights::{self, LoadedWeights};
use blapose_model::{
    CpuFeatures, ModelError, ModelKind, OfflineBiGruEngine, OnlineGruEngine, Precision,
    PrecisionChoice,
};
use blapose_proto::v1 as pb;
use sha2::{Digest, Sha256};

use crate::backend::{Backend, BackendError, SequenceBackend};
use crate::config::WeightsSource;
use crate::engine;

/// The stature model sessions and requests with a subject are answered
/// with: `models/stature_regression.json` (written by `blapose
/// fit-stature`), embedded.
pub fn embedded_stature_model() -> Result<StatureModel, WeightsError> {
    StatureModel::from_json(include_str!("../../models/stature_regression.json"))
        .map_err(|e| WeightsError::Stature(e.to_string()))
}

/// `pub fn $name() -> Option<&'static [u8]>`: the weights file `build.rs`
/// found for `$cfg` (its path in the environment variable `$env`), or
/// `None` when the build had none.
macro_rules! embedded_weights {
    ($(#[$doc:meta])* $name:ident, $cfg:ident, $env:literal) => {
        $(#[$doc])*
        pub fn $name() -> Option<&'static [u8]> {
            #[cfg($cfg)]
            {
                Some(include_bytes!(env!($env)))
            }
            #[cfg(not($cfg))]
            {
                None
            }
        }
    };
}

embedded_weights!(
    /// The embedded online GRU weights, if the build found them.
    embedded_gru,
    blapose_embedded_gru,
    "BLAPOSE_EMBEDDED_GRU"
);
embedded_weights!(
    /// The embedded offline Bi-GRU weights, if the build found them.
    embedded_bigru,
    blapose_embedded_bigru,
    "BLAPOSE_EMBEDDED_BIGRU"
);
embedded_weights!(
    /// The embedded camera-aware (rectified) online GRU weights, if the
    /// build found them.
    embedded_gru_rectified,
    blapose_embedded_gru_rectified,
    "BLAPOSE_EMBEDDED_GRU_RECTIFIED"
);
embedded_weights!(
    /// The embedded camera-aware (rectified) offline Bi-GRU weights, if the
    /// build found them.
    embedded_bigru_rectified,
    blapose_embedded_bigru_rectified,
    "BLAPOSE_EMBEDDED_BIGRU_RECTIFIED"
);

embedded_weights!(
    /// The embedded causal lifter, if the build found it.
    embedded_lifter,
    blapose_embedded_lifter,
    "BLAPOSE_EMBEDDED_LIFTER"
);

/// Which family a model belongs to: the default one, fed keypoints as
/// sent, or the camera-aware one, fed them through the session's
/// calibration.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Family {
    /// Sessions and requests without a camera calibration.
    Default,
    /// Sessions and requests with one (rectified keypoints).
    CameraAware,
}

impl Family {
    /// For messages.
    fn describe(self) -> &'static str {
        match self {
            Self::Default => "the default models (no camera)",
            Self::CameraAware => "the camera-aware models",
        }
    }

    /// Whether this family's models read a camera calibration.
    pub const fn calibrated(self) -> bool {
        matches!(self, Self::CameraAware)
    }

    /// Suffix of the model names and weight files of this family.
    fn suffix(self) -> &'static str {
        match self {
            Self::Default => "",
            Self::CameraAware => "_rectified",
        }
    }

    fn embedded(self, kind: ModelKind) -> (Option<&'static [u8]>, &'static str) {
        match (self, kind) {
            (Self::Default, ModelKind::Gru) => (embedded_gru(), "--weights"),
            (Self::Default, ModelKind::BiGru) => (embedded_bigru(), "--bigru-weights"),
            (Self::CameraAware, ModelKind::Gru) => {
                (embedded_gru_rectified(), "--rectified-weights")
            }
            (Self::CameraAware, ModelKind::BiGru) => {
                (embedded_bigru_rectified(), "--rectified-bigru-weights")
            }
        }
    }
}

/// Why weights could not be loaded.
#[derive(Debug, thiserror::Error)]
pub enum WeightsError {
    /// The binary was built without default weights.
    #[error("this binary has no embedded {kind} weights of this family (models/ lacked them at build time); pass them with {flag}")]
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
    /// The file's input contract says it reads the other family's input,
    /// e.g. default weights given as `--rectified-weights`.
    #[error("{kind} weights from {origin} were trained {trained} keypoints but are loaded for {family}; pass them with {flag}")]
    WrongFamily {
        /// Which model.
        kind: ModelKind,
        /// Where they came from.
        origin: String,
        /// How they were trained.
        trained: &'static str,
        /// Which family they were loaded for.
        family: &'static str,
        /// The flag that takes them.
        flag: &'static str,
    },
    /// The GRU and the Bi-GRU of a family read their input differently.
    #[error("the GRU ({gru}) and the Bi-GRU ({bigru}) of a family must read a camera alike (their model_input: framing and trained cameras): {gru_input:?} vs {bigru_input:?}")]
    MixedInput {
        /// The GRU's origin.
        gru: String,
        /// The Bi-GRU's origin.
        bigru: String,
        /// What the GRU reads.
        gru_input: Box<ModelInput>,
        /// What the Bi-GRU reads.
        bigru_input: Box<ModelInput>,
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
    /// No engine could be built for the weights.
    #[error("model backend: {0}")]
    Backend(#[from] BackendError),
    /// The embedded stature model does not load.
    #[error("stature model: {0}")]
    Stature(String),
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
    /// What the model reads: its recorded input contract, or its family's
    /// when it records none.
    pub input: ModelInput,
}

impl LoadedModel {
    /// Read and validate weights of `kind` from `source` (the embedded
    /// ones of `family` for [`WeightsSource::Embedded`]).
    pub fn load(
        source: &WeightsSource,
        kind: ModelKind,
        family: Family,
    ) -> Result<Self, WeightsError> {
        let (embedded, flag) = family.embedded(kind);
        let origin = source.origin();
        let bytes = read_source(source, embedded)
            .map_err(|e| WeightsError::Io {
                kind,
                path: origin.clone(),
                source: e,
            })?
            .ok_or(WeightsError::NotEmbedded { kind, flag })?;
        let weights =
            weights::load_bytes(&bytes, kind).map_err(|source| WeightsError::Invalid {
                kind,
                origin: origin.clone(),
                source,
            })?;
        // A file that records its input must match the family (files that
        // do not, e.g. converted ones, are taken as the family's).
        if let Some(recorded) = weights.meta.input {
            let rectified = recorded.framing.needs_calibration();
            if rectified != (family == Family::CameraAware) {
                let other = if rectified {
                    Family::CameraAware
                } else {
                    Family::Default
                };
                return Err(WeightsError::WrongFamily {
                    kind,
                    origin,
                    trained: if rectified { "on rectified" } else { "on raw" },
                    family: family.describe(),
                    flag: other.embedded(kind).1,
                });
            }
        }
        let input = weights.meta.input_contract(family.calibrated());
        Ok(Self {
            weights,
            origin,
            sha256: sha256_hex(&bytes),
            input,
        })
    }

    /// The `ModelInfo` entry for this model, serving `family`.
    pub fn describe(&self, family: Family) -> pb::ModelDescription {
        let kind = self.weights.kind();
        let name = match kind {
            ModelKind::Gru => "bone_length_gru",
            ModelKind::BiGru => "bone_length_bigru",
        };
        let parameter_count =
            blapose_model::reference::count_parameters(self.weights.tensors().values()) as u64;
        let metadata: HashMap<String, String> = self.weights.meta.to_header().into_iter().collect();
        pb::ModelDescription {
            model: pb::Model::from(kind) as i32,
            name: format!("{name}{}", family.suffix()),
            parameter_count,
            hidden_size: blapose_model::HIDDEN as u32,
            weights_source: self.origin.clone(),
            weights_sha256: self.sha256.clone(),
            metadata,
            camera_aware: family == Family::CameraAware,
        }
    }
}

/// The bytes `source` names: the file's, or `embedded` (`None` when the
/// build had none).
fn read_source(
    source: &WeightsSource,
    embedded: Option<&'static [u8]>,
) -> std::io::Result<Option<std::borrow::Cow<'static, [u8]>>> {
    Ok(match source {
        WeightsSource::Embedded => embedded.map(std::borrow::Cow::Borrowed),
        WeightsSource::File(path) => Some(std::fs::read(path)?.into()),
    })
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
    /// The lifter `source` names: the file, read and refused if it cannot
    /// be served online (see [`blapose_lifters::trained`]), or the embedded
    /// one (`None` when the build had none).
    pub fn load(source: &WeightsSource) -> Result<Option<Self>, WeightsError> {
        let origin = source.origin();
        let bytes = read_source(source, embedded_lifter()).map_err(|e| WeightsError::Lifter {
            path: origin.clone(),
            cause: TrainedLifterError::Io {
                path: origin.clone().into(),
                source: e,
            },
        })?;
        let Some(bytes) = bytes else {
            return Ok(None);
        };
        let lifter = TrainedLifter::from_bytes(&bytes).map_err(|cause| WeightsError::Lifter {
            path: origin.clone(),
            cause,
        })?;
        Ok(Some(Self {
            lifter,
            sha256: sha256_hex(&bytes),
            origin,
        }))
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
    /// The camera-aware models, for sessions and requests that send a
    /// camera calibration (their backends are fed keypoints prepared as
    /// [`ModelProvider::model_input`] says); `None` when the server has
    /// none.
    fn camera_aware(&self) -> Option<Arc<dyn ModelProvider>> {
        None
    }
    /// What these models read (their weights' input contract); what the
    /// camera-aware family's is decides how a calibration is read.
    /// Default: what camera-aware weights that record no contract are
    /// taken to read ([`blapose_model::WeightsMetadata::input_contract`]).
    fn model_input(&self) -> ModelInput {
        blapose_model::WeightsMetadata::new(ModelKind::Gru).input_contract(true)
    }
}

/// The real provider: blapose-model's fast engines on loaded weights,
/// built once and shared by every backend.
#[derive(Debug, Clone)]
pub struct WeightsProvider {
    family: Family,
    gru: LoadedModel,
    bigru: LoadedModel,
    online: Arc<OnlineGruEngine>,
    offline: Arc<OfflineBiGruEngine>,
    /// The GRU weights' precision in the engines, and why.
    precision: PrecisionChoice,
    camera_aware: Option<Arc<WeightsProvider>>,
}

/// `ModelInfo` metadata: the precision the server's engines store the GRU
/// weights at (`--weight-precision`), beside the file's own metadata.
pub const PRECISION_KEY: &str = "served_weight_precision";
/// `ModelInfo` metadata: why that precision ([`PrecisionChoice::reason`]).
pub const PRECISION_REASON_KEY: &str = "served_weight_precision_reason";

/// Scratch preallocated per online backend (it grows if a batch is larger).
const SCRATCH_BATCH: usize = 64;

impl WeightsProvider {
    /// Load both models of `family` and build their engines with
    /// `threads` workers and the GRU weights stored at `precision`.
    pub fn load(
        family: Family,
        gru: &WeightsSource,
        bigru: &WeightsSource,
        threads: usize,
        precision: Precision,
    ) -> Result<Self, WeightsError> {
        let gru = LoadedModel::load(gru, ModelKind::Gru, family)?;
        let bigru = LoadedModel::load(bigru, ModelKind::BiGru, family)?;
        if gru.input != bigru.input {
            return Err(WeightsError::MixedInput {
                gru: gru.origin,
                bigru: bigru.origin,
                gru_input: Box::new(gru.input),
                bigru_input: Box::new(bigru.input),
            });
        }
        let online = engine::online_engine(&gru.weights, threads, precision)?;
        let offline = engine::offline_engine(&bigru.weights, threads, precision)?;
        Ok(Self {
            family,
            gru,
            bigru,
            online,
            offline,
            precision: PrecisionChoice::requested(precision, CpuFeatures::detect()),
            camera_aware: None,
        })
    }

    /// Serve `camera_aware` (a provider of [`Family::CameraAware`]) to the
    /// sessions and requests that send a camera calibration.
    pub fn with_camera_aware(mut self, camera_aware: WeightsProvider) -> Self {
        self.camera_aware = Some(Arc::new(camera_aware));
        self
    }

    /// The precision the engines store the GRU weights at, and why.
    pub fn precision(&self) -> PrecisionChoice {
        self.precision
    }

    /// The camera-aware models, if loaded.
    pub fn camera_aware_models(&self) -> Option<&WeightsProvider> {
        self.camera_aware.as_deref()
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
        let mut models = vec![
            self.gru.describe(self.family),
            self.bigru.describe(self.family),
        ];
        for model in &mut models {
            let precision = self.precision;
            model.metadata.extend([
                (PRECISION_KEY.to_string(), precision.precision.to_string()),
                (
                    PRECISION_REASON_KEY.to_string(),
                    precision.reason.to_string(),
                ),
            ]);
        }
        if let Some(camera_aware) = &self.camera_aware {
            models.extend(camera_aware.describe());
        }
        models
    }

    fn camera_aware(&self) -> Option<Arc<dyn ModelProvider>> {
        self.camera_aware
            .clone()
            .map(|p| p as Arc<dyn ModelProvider>)
    }

    fn model_input(&self) -> ModelInput {
        self.gru.input
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn weights_load_only_for_the_family_they_were_trained_for() {
        if embedded_gru().is_none() || embedded_gru_rectified().is_none() {
            println!("skipping: this build has no embedded weights");
            return;
        }
        let embedded = WeightsSource::Embedded;
        for (kind, flag) in [
            (ModelKind::Gru, "--rectified-weights"),
            (ModelKind::BiGru, "--rectified-bigru-weights"),
        ] {
            assert!(LoadedModel::load(&embedded, kind, Family::Default).is_ok());
            assert!(LoadedModel::load(&embedded, kind, Family::CameraAware).is_ok());
            // The rectified files given as default weights, and back.
            let dir = std::env::temp_dir().join(format!(
                "blapose-family-{}-{}",
                std::process::id(),
                kind.as_str()
            ));
            std::fs::create_dir_all(&dir).unwrap();
            let rectified = dir.join("rectified.safetensors");
            std::fs::write(&rectified, Family::CameraAware.embedded(kind).0.unwrap()).unwrap();
            let err = LoadedModel::load(&WeightsSource::File(rectified), kind, Family::Default)
                .unwrap_err();
            assert!(matches!(err, WeightsError::WrongFamily { .. }), "{err}");
            assert!(err.to_string().contains(flag), "{err}");
            let plain = dir.join("plain.safetensors");
            std::fs::write(&plain, Family::Default.embedded(kind).0.unwrap()).unwrap();
            let err = LoadedModel::load(&WeightsSource::File(plain), kind, Family::CameraAware)
                .unwrap_err();
            assert!(err.to_string().contains("trained on raw"), "{err}");
            let _ = std::fs::remove_dir_all(&dir);
        }
        // Files that record no input contract load for either family, and
        // read what the family reads.
        let random = LoadedWeights::random(ModelKind::Gru, 1).unwrap();
        assert_eq!(random.meta.input, None);
        let dir = std::env::temp_dir().join(format!("blapose-family-{}-none", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("random.safetensors");
        weights::save(&path, random.tensors(), &random.meta).unwrap();
        for family in [Family::Default, Family::CameraAware] {
            let loaded =
                LoadedModel::load(&WeightsSource::File(path.clone()), ModelKind::Gru, family)
                    .unwrap();
            assert_eq!(
                loaded.input,
                random.meta.input_contract(family.calibrated())
            );
            assert_eq!(
                loaded.input.framing.needs_calibration(),
                family.calibrated()
            );
        }
        let _ = std::fs::remove_dir_all(&dir);
        // The shipped files record what they read; each family's pair agrees.
        for family in [Family::Default, Family::CameraAware] {
            let gru = LoadedModel::load(&embedded, ModelKind::Gru, family).unwrap();
            let bigru = LoadedModel::load(&embedded, ModelKind::BiGru, family).unwrap();
            assert!(gru.weights.meta.input.is_some(), "{family:?}");
            assert_eq!(gru.input, bigru.input, "{family:?}");
            assert_eq!(
                gru.input.framing.needs_calibration(),
                family == Family::CameraAware
            );
        }
    }
}

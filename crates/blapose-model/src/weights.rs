//! Safetensors weights files with blapose metadata.
//!
//! A weights file is a plain safetensors file (tensor names from
//! [`crate::names`], any float dtype, converted to f32 on load) whose
//! `__metadata__` header says what the numbers mean: the model kind, the
//! keypoint layout and input normalization the network expects, what it was
//! trained on and a version. Loading is strict — a missing, extra or
//! misshaped tensor, a non-finite weight or the wrong model kind is a typed
//! error — because a silently half-loaded model would serve plausible but
//! wrong bone lengths. Loading from bytes exists for weights embedded in a
//! binary with `include_bytes!`.

use std::collections::{BTreeMap, HashMap};
use std::path::Path;

use candle_core::safetensors::Load;
use candle_core::{DType, Device, Tensor};
use candle_nn::{VarBuilder, VarMap};

use crate::input::{ModelInput, KEY_MODEL_INPUT};
use crate::names::tensor_specs;
use crate::{ModelError, ModelKind};

/// Value of the `format` metadata key of every blapose weights file.
pub const FORMAT: &str = "blapose-bone-length";
/// Version of the file layout this crate writes and reads.
pub const FORMAT_VERSION: u32 = 1;

const KEY_FORMAT: &str = "format";
const KEY_FORMAT_VERSION: &str = "format_version";
const KEY_KIND: &str = "kind";
const KEY_LAYOUT: &str = "keypoint_layout";
const KEY_NORMALIZATION: &str = "input_normalization";
const KEY_TRAINING_DATA: &str = "training_data";
const KEY_VERSION: &str = "version";
const RESERVED: [&str; 8] = [
    KEY_MODEL_INPUT,
    KEY_FORMAT,
    KEY_FORMAT_VERSION,
    KEY_KIND,
    KEY_LAYOUT,
    KEY_NORMALIZATION,
    KEY_TRAINING_DATA,
    KEY_VERSION,
];

/// Keypoint layout the paper's models read: the 17 Human3.6M joints.
pub const DEFAULT_KEYPOINT_LAYOUT: &str = "h36m17";
/// Input normalization the paper's models expect (w, h: image size in pixels).
pub const DEFAULT_INPUT_NORMALIZATION: &str = "screen: u = x/w*2-1, v = y/w*2-h/w";

/// What a weights file is for; stored as strings in the safetensors header.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct WeightsMetadata {
    /// Model kind the tensors belong to.
    pub kind: ModelKind,
    /// Name of the 2D keypoint layout of the input (e.g. `h36m17`).
    pub keypoint_layout: String,
    /// How pixel coordinates were normalized before entering the network.
    pub input_normalization: String,
    /// Free-text description of the training data and sampling strategy.
    pub training_data: String,
    /// Version of these weights (not of the file format).
    pub version: String,
    /// What the network expects as input ([`crate::input`]): recorded by
    /// the trainer, or read from an older file's `train_config`; `None`
    /// when the file records neither.
    pub input: Option<ModelInput>,
    /// Any further key/value pairs (training metrics, command line, ...).
    pub extra: BTreeMap<String, String>,
}

impl WeightsMetadata {
    /// What these weights read, the one place that decides it: the input
    /// contract they record, or for weights that record none (older or
    /// converted files) the default for what they are fed: screen
    /// coordinates ([`ModelInput::screen`]), or with a camera calibration
    /// (`calibrated`) plain rectified keypoints from any camera
    /// ([`ModelInput::level`]). The server, the evaluation and the
    /// benchmarks all read a contract through this.
    pub fn input_contract(&self, calibrated: bool) -> ModelInput {
        self.input.unwrap_or(if calibrated {
            ModelInput::level()
        } else {
            ModelInput::screen()
        })
    }

    /// Metadata for `kind` with the paper's input conventions and empty
    /// provenance fields.
    pub fn new(kind: ModelKind) -> Self {
        Self {
            kind,
            keypoint_layout: DEFAULT_KEYPOINT_LAYOUT.to_string(),
            input_normalization: DEFAULT_INPUT_NORMALIZATION.to_string(),
            training_data: String::new(),
            version: String::new(),
            input: None,
            extra: BTreeMap::new(),
        }
    }

    /// The header map written to the file.
    pub fn to_header(&self) -> HashMap<String, String> {
        let mut m: HashMap<String, String> = self
            .extra
            .iter()
            .filter(|(k, _)| !RESERVED.contains(&k.as_str()))
            .map(|(k, v)| (k.clone(), v.clone()))
            .collect();
        m.insert(KEY_FORMAT.into(), FORMAT.into());
        m.insert(KEY_FORMAT_VERSION.into(), FORMAT_VERSION.to_string());
        m.insert(KEY_KIND.into(), self.kind.to_string());
        m.insert(KEY_LAYOUT.into(), self.keypoint_layout.clone());
        m.insert(KEY_NORMALIZATION.into(), self.input_normalization.clone());
        m.insert(KEY_TRAINING_DATA.into(), self.training_data.clone());
        m.insert(KEY_VERSION.into(), self.version.clone());
        if let Some(input) = &self.input {
            m.insert(KEY_MODEL_INPUT.into(), input.to_json());
        }
        m
    }

    /// Parse a header map, refusing files that are not blapose weights.
    pub fn from_header(header: &HashMap<String, String>) -> Result<Self, ModelError> {
        let get = |key: &'static str| {
            header
                .get(key)
                .ok_or(ModelError::MissingMetadata { key })
                .cloned()
        };
        let format = get(KEY_FORMAT)?;
        if format != FORMAT {
            return Err(ModelError::BadMetadata {
                key: KEY_FORMAT,
                value: format,
                reason: format!("expected {FORMAT:?}"),
            });
        }
        let fv = get(KEY_FORMAT_VERSION)?;
        match fv.parse::<u32>() {
            Ok(v) if (1..=FORMAT_VERSION).contains(&v) => {}
            _ => {
                return Err(ModelError::BadMetadata {
                    key: KEY_FORMAT_VERSION,
                    value: fv,
                    reason: format!("this build reads versions 1..={FORMAT_VERSION}"),
                })
            }
        }
        let kind_s = get(KEY_KIND)?;
        let kind = kind_s
            .parse::<ModelKind>()
            .map_err(|e| ModelError::BadMetadata {
                key: KEY_KIND,
                value: kind_s.clone(),
                reason: e.to_string(),
            })?;
        let input = ModelInput::from_metadata(|key| header.get(key))?;
        let extra = header
            .iter()
            .filter(|(k, _)| !RESERVED.contains(&k.as_str()))
            .map(|(k, v)| (k.clone(), v.clone()))
            .collect();
        Ok(Self {
            input,
            kind,
            keypoint_layout: get(KEY_LAYOUT)?,
            input_normalization: get(KEY_NORMALIZATION)?,
            training_data: header.get(KEY_TRAINING_DATA).cloned().unwrap_or_default(),
            version: header.get(KEY_VERSION).cloned().unwrap_or_default(),
            extra,
        })
    }
}

/// A validated set of f32 CPU tensors for one model kind, plus its metadata.
#[derive(Debug, Clone)]
pub struct LoadedWeights {
    /// What the file said about itself.
    pub meta: WeightsMetadata,
    tensors: HashMap<String, Tensor>,
}

impl LoadedWeights {
    /// Validate `tensors` against `meta.kind` (names, shapes, finiteness) and
    /// convert them to contiguous f32 on the CPU.
    pub fn from_tensors(
        tensors: HashMap<String, Tensor>,
        meta: WeightsMetadata,
    ) -> Result<Self, ModelError> {
        let kind = meta.kind;
        let specs = tensor_specs(kind);
        if let Some(name) = tensors
            .keys()
            .filter(|n| !specs.iter().any(|(s, _)| s == *n))
            .min()
        {
            return Err(ModelError::UnexpectedTensor {
                kind,
                name: name.clone(),
            });
        }
        let mut out = HashMap::with_capacity(specs.len());
        for (name, shape) in specs {
            let t = tensors
                .get(&name)
                .ok_or_else(|| ModelError::MissingTensor {
                    kind,
                    name: name.clone(),
                })?;
            if t.dims() != shape.as_slice() {
                return Err(ModelError::ShapeMismatch {
                    name,
                    expected: shape,
                    found: t.dims().to_vec(),
                });
            }
            if !t.dtype().is_float() {
                return Err(ModelError::UnsupportedDtype {
                    name,
                    dtype: format!("{:?}", t.dtype()),
                });
            }
            let t = t
                .to_device(&Device::Cpu)?
                .to_dtype(DType::F32)?
                .contiguous()?;
            let values = t.flatten_all()?.to_vec1::<f32>()?;
            if values.iter().any(|v| !v.is_finite()) {
                return Err(ModelError::NonFiniteWeight { name });
            }
            out.insert(name, t);
        }
        Ok(Self { meta, tensors: out })
    }

    /// PyTorch-style random weights for `kind` (benchmarks, tests, training start).
    pub fn random(kind: ModelKind, seed: u64) -> Result<Self, ModelError> {
        let mut meta = WeightsMetadata::new(kind);
        meta.training_data = format!("none (random initialization, seed {seed})");
        Self::from_tensors(crate::init::random_tensors(kind, seed)?, meta)
    }

    /// The model kind.
    pub fn kind(&self) -> ModelKind {
        self.meta.kind
    }

    /// All tensors by name.
    pub fn tensors(&self) -> &HashMap<String, Tensor> {
        &self.tensors
    }

    /// One tensor (f32, contiguous, CPU); `None` if the model has no such tensor.
    pub fn tensor(&self, name: &str) -> Option<&Tensor> {
        self.tensors.get(name)
    }

    /// A tensor's values, row-major.
    pub fn values(&self, name: &str) -> Result<Vec<f32>, ModelError> {
        let t = self
            .tensors
            .get(name)
            .ok_or_else(|| ModelError::MissingTensor {
                kind: self.kind(),
                name: name.to_string(),
            })?;
        Ok(t.flatten_all()?.to_vec1::<f32>()?)
    }

    /// A `VarBuilder` over these (frozen) tensors, for building a reference model.
    pub fn var_builder(&self) -> VarBuilder<'static> {
        VarBuilder::from_tensors(self.tensors.clone(), DType::F32, &Device::Cpu)
    }

    /// A `VarMap` initialized from these tensors, for continuing training.
    pub fn to_varmap(&self) -> Result<VarMap, ModelError> {
        let map = VarMap::new();
        {
            let mut data = map
                .data()
                .lock()
                .map_err(|_| ModelError::Config("VarMap lock poisoned".into()))?;
            for (name, t) in &self.tensors {
                data.insert(name.clone(), candle_core::Var::from_tensor(t)?);
            }
        }
        Ok(map)
    }
}

/// Serialize `tensors` with `meta` to safetensors bytes, after checking they
/// form a valid model of `meta.kind` (what would not load is not written).
pub fn to_bytes(
    tensors: &HashMap<String, Tensor>,
    meta: &WeightsMetadata,
) -> Result<Vec<u8>, ModelError> {
    let checked = LoadedWeights::from_tensors(tensors.clone(), meta.clone())?;
    let mut named: Vec<(&String, &Tensor)> = checked.tensors.iter().collect();
    named.sort_by(|a, b| a.0.cmp(b.0));
    safetensors::serialize(named, Some(meta.to_header()))
        .map_err(|e| ModelError::InvalidFile(e.to_string()))
}

/// Write `tensors` with `meta` to `path` (see [`to_bytes`]).
pub fn save(
    path: impl AsRef<Path>,
    tensors: &HashMap<String, Tensor>,
    meta: &WeightsMetadata,
) -> Result<(), ModelError> {
    let bytes = to_bytes(tensors, meta)?;
    let path = path.as_ref();
    std::fs::write(path, bytes).map_err(|source| ModelError::Io {
        path: path.display().to_string(),
        source,
    })
}

/// Write the variables of a training `VarMap` with `meta` to `path`.
pub fn save_varmap(
    path: impl AsRef<Path>,
    varmap: &VarMap,
    meta: &WeightsMetadata,
) -> Result<(), ModelError> {
    save(path, &varmap_tensors(varmap)?, meta)
}

/// Snapshot of a `VarMap`'s variables as plain tensors.
pub fn varmap_tensors(varmap: &VarMap) -> Result<HashMap<String, Tensor>, ModelError> {
    let data = varmap
        .data()
        .lock()
        .map_err(|_| ModelError::Config("VarMap lock poisoned".into()))?;
    Ok(data
        .iter()
        .map(|(k, v)| (k.clone(), v.as_tensor().detach()))
        .collect())
}

/// Parse and validate weights from safetensors bytes; `expected` is the kind
/// the caller will build (a file for the other kind is refused).
pub fn load_bytes(bytes: &[u8], expected: ModelKind) -> Result<LoadedWeights, ModelError> {
    let (_, header) = safetensors::SafeTensors::read_metadata(bytes)
        .map_err(|e| ModelError::InvalidFile(e.to_string()))?;
    let meta = WeightsMetadata::from_header(header.metadata().as_ref().unwrap_or(&HashMap::new()))?;
    crate::expect_kind(expected, meta.kind)?;
    let st = safetensors::SafeTensors::deserialize(bytes)
        .map_err(|e| ModelError::InvalidFile(e.to_string()))?;
    let mut tensors = HashMap::new();
    for (name, view) in st.iter() {
        let t = view
            .load(&Device::Cpu)
            .map_err(|_| ModelError::UnsupportedDtype {
                name: name.to_string(),
                dtype: format!("{:?}", view.dtype()),
            })?;
        tensors.insert(name.to_string(), t);
    }
    LoadedWeights::from_tensors(tensors, meta)
}

/// Read and validate a weights file (see [`load_bytes`]).
pub fn load(path: impl AsRef<Path>, expected: ModelKind) -> Result<LoadedWeights, ModelError> {
    let path = path.as_ref();
    let bytes = std::fs::read(path).map_err(|source| ModelError::Io {
        path: path.display().to_string(),
        source,
    })?;
    load_bytes(&bytes, expected)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_input_contract_is_the_recorded_one_or_the_default_for_what_is_fed() {
        let mut meta = WeightsMetadata::new(ModelKind::Gru);
        assert_eq!(meta.input, None);
        assert_eq!(meta.input_contract(false), ModelInput::screen());
        assert_eq!(meta.input_contract(true), ModelInput::level());
        let recorded = ModelInput::from_training(true, true, true);
        meta.input = Some(recorded);
        assert_eq!(meta.input_contract(false), recorded);
        assert_eq!(meta.input_contract(true), recorded);
    }
}

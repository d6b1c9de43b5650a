//! Lifter weights files: safetensors holding every variable of the network
//! (batch-norm running statistics included) and, under the header key
//! [`METADATA_KEY`], a JSON [`LifterMetadata`] that says how to rebuild the
//! network and what it expects and was trained on. A file is enough to run
//! the lifter: nothing about its size lives in code or flags.

use std::collections::{BTreeMap, HashMap};
use std::path::Path;

use blapose_model::weights::{DEFAULT_INPUT_NORMALIZATION, DEFAULT_KEYPOINT_LAYOUT};
use candle_core::Tensor;
use candle_nn::VarMap;

use super::{LifterArch, LifterNet};
use crate::error::TrainError;

pub use blapose_lifters::trained::METADATA_KEY;

/// What the output of a lifter is.
pub const OUTPUT_DESCRIPTION: &str =
    "16 joints (H36M-17 order without the pelvis, which is fixed at 0), root-relative camera space, metres";

/// Provenance and conventions of a lifter weights file: the serving
/// crate's struct over this crate's architectures.
pub type LifterMetadata = blapose_lifters::trained::LifterMetadata<LifterArch>;

/// Metadata with the project's input conventions.
pub fn metadata(arch: LifterArch, training_data: &str, train_steps: u64) -> LifterMetadata {
    LifterMetadata {
        arch,
        keypoint_layout: DEFAULT_KEYPOINT_LAYOUT.into(),
        input_normalization: DEFAULT_INPUT_NORMALIZATION.into(),
        output: OUTPUT_DESCRIPTION.into(),
        training_data: training_data.into(),
        train_steps,
        extra: BTreeMap::new(),
    }
}

/// All variables of `varmap` by name (sorted).
pub fn named_tensors(varmap: &VarMap) -> Result<BTreeMap<String, Tensor>, TrainError> {
    let data = varmap
        .data()
        .lock()
        .map_err(|_| TrainError::InvalidArgument("variable map lock poisoned".into()))?;
    Ok(data
        .iter()
        .map(|(k, v)| (k.clone(), v.as_tensor().clone()))
        .collect())
}

/// Serialize `tensors` with `header` entries to safetensors bytes.
pub fn serialize(
    tensors: &BTreeMap<String, Tensor>,
    header: HashMap<String, String>,
    path: &Path,
) -> Result<Vec<u8>, TrainError> {
    safetensors::serialize(tensors.iter().map(|(k, v)| (k.as_str(), v)), Some(header)).map_err(
        |e| TrainError::Checkpoint {
            path: path.into(),
            msg: e.to_string(),
        },
    )
}

/// Write the weights file (atomically).
pub fn save(path: &Path, varmap: &VarMap, meta: &LifterMetadata) -> Result<(), TrainError> {
    let mut header = HashMap::new();
    header.insert(METADATA_KEY.to_string(), serde_json::to_string(meta)?);
    let bytes = serialize(&named_tensors(varmap)?, header, path)?;
    crate::run::write_atomic(path, &bytes)
}

pub use crate::run::{read_tensor_file as read, TensorFile};

/// Copy every variable of `varmap` from `tensors` (same names and shapes;
/// extra tensors are ignored).
pub fn assign(
    varmap: &VarMap,
    tensors: &HashMap<String, Tensor>,
    path: &Path,
) -> Result<(), TrainError> {
    let data = varmap
        .data()
        .lock()
        .map_err(|_| TrainError::InvalidArgument("variable map lock poisoned".into()))?;
    for (name, var) in data.iter() {
        let t = tensors.get(name).ok_or_else(|| TrainError::Checkpoint {
            path: path.into(),
            msg: format!("missing tensor {name}"),
        })?;
        if t.dims() != var.as_tensor().dims() {
            return Err(TrainError::Checkpoint {
                path: path.into(),
                msg: format!(
                    "{name}: shape {:?}, the network needs {:?}",
                    t.dims(),
                    var.as_tensor().dims()
                ),
            });
        }
        var.set(t)?;
    }
    Ok(())
}

/// A lifter loaded from a weights file.
pub struct LoadedLifter {
    /// The network (evaluation use).
    pub net: Box<dyn LifterNet>,
    /// Its variables.
    pub varmap: VarMap,
    /// The file's metadata.
    pub metadata: LifterMetadata,
}

/// Load a weights file written by [`save`].
pub fn load(path: &Path) -> Result<LoadedLifter, TrainError> {
    let (metadata, tensors) = read_lifter(path)?;
    let (net, varmap) = metadata.arch.build(0)?;
    assign(&varmap, &tensors, path)?;
    Ok(LoadedLifter {
        net,
        varmap,
        metadata,
    })
}

/// The metadata and tensors of a weights file written by [`save`], without
/// building the network.
pub fn read_lifter(path: &Path) -> Result<(LifterMetadata, HashMap<String, Tensor>), TrainError> {
    let TensorFile {
        tensors,
        metadata: header,
    } = read(path)?;
    let json = header
        .get(METADATA_KEY)
        .ok_or_else(|| TrainError::Checkpoint {
            path: path.into(),
            msg: format!("no {METADATA_KEY} metadata (not a lifter weights file?)"),
        })?;
    Ok((serde_json::from_str(json)?, tensors))
}

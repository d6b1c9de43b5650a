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

/// Provenance and conventions of a lifter weights file, as the serving
/// crate reads it back.
pub use blapose_lifters::trained::LifterMetadata;

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
    let (net, varmap) = super::build(&metadata.arch, 0)?;
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lifter::objective::Objective;
    use crate::lifter::train::LifterTrainConfig;
    use crate::lifter::{MlpArch, VideoPoseArch};

    /// What a training run writes into the weights file (the metadata, and
    /// the run's configuration under `extra.train_config`) is the JSON
    /// that the trainer wrote before the architecture types moved to
    /// `blapose_lifters::arch`, to the byte: these strings were printed by
    /// that code.
    #[test]
    fn metadata_and_train_config_json_are_unchanged() {
        let archs = [
            LifterArch::Mlp(MlpArch::default()),
            LifterArch::VideoPose(VideoPoseArch {
                causal: true,
                ..VideoPoseArch::default()
            }),
            LifterArch::VideoPose(VideoPoseArch {
                filter_width: 5,
                blocks: 1,
                channels: 7,
                dropout: 0.125,
                causal: false,
            }),
        ];
        let want = [
            (
                r#"{"arch":{"model":"mlp","hidden":1024,"blocks":2,"dropout":0.5},"keypoint_layout":"h36m17","input_normalization":"screen: u = x/w*2-1, v = y/w*2-h/w","output":"16 joints (H36M-17 order without the pelvis, which is fixed at 0), root-relative camera space, metres","training_data":"Human3.6M S1; \"quoted\"","train_steps":123,"extra":{"version":"x"}}"#,
                r#"{"arch":{"model":"mlp","hidden":1024,"blocks":2,"dropout":0.5},"every":4,"batch":256,"steps":10000,"epoch_steps":500,"lr":0.001,"lr_decay":0.95,"clip_norm":5.0,"flip_prob":0.5,"seed":0,"val_every":500,"val_samples":8192,"checkpoint_secs":300,"objective":"adjusted","direction_weight":1.0,"init_weights":"a/b.safetensors"}"#,
            ),
            (
                r#"{"arch":{"model":"videopose","filter_width":3,"blocks":2,"channels":512,"dropout":0.25,"causal":true},"keypoint_layout":"h36m17","input_normalization":"screen: u = x/w*2-1, v = y/w*2-h/w","output":"16 joints (H36M-17 order without the pelvis, which is fixed at 0), root-relative camera space, metres","training_data":"Human3.6M S1; \"quoted\"","train_steps":123,"extra":{"version":"x"}}"#,
                r#"{"arch":{"model":"videopose","filter_width":3,"blocks":2,"channels":512,"dropout":0.25,"causal":true},"every":4,"batch":256,"steps":10000,"epoch_steps":500,"lr":0.001,"lr_decay":0.95,"clip_norm":5.0,"flip_prob":0.5,"seed":0,"val_every":500,"val_samples":8192,"checkpoint_secs":300,"objective":"adjusted","direction_weight":1.0,"init_weights":"a/b.safetensors"}"#,
            ),
            (
                r#"{"arch":{"model":"videopose","filter_width":5,"blocks":1,"channels":7,"dropout":0.125,"causal":false},"keypoint_layout":"h36m17","input_normalization":"screen: u = x/w*2-1, v = y/w*2-h/w","output":"16 joints (H36M-17 order without the pelvis, which is fixed at 0), root-relative camera space, metres","training_data":"Human3.6M S1; \"quoted\"","train_steps":123,"extra":{"version":"x"}}"#,
                r#"{"arch":{"model":"videopose","filter_width":5,"blocks":1,"channels":7,"dropout":0.125,"causal":false},"every":4,"batch":256,"steps":10000,"epoch_steps":500,"lr":0.001,"lr_decay":0.95,"clip_norm":5.0,"flip_prob":0.5,"seed":0,"val_every":500,"val_samples":8192,"checkpoint_secs":300,"objective":"adjusted","direction_weight":1.0,"init_weights":"a/b.safetensors"}"#,
            ),
        ];
        for (arch, (meta_json, config_json)) in archs.into_iter().zip(want) {
            let mut meta = metadata(arch, "Human3.6M S1; \"quoted\"", 123);
            meta.extra.insert("version".into(), "x".into());
            assert_eq!(serde_json::to_string(&meta).unwrap(), meta_json);
            assert_eq!(
                serde_json::from_str::<LifterMetadata>(meta_json).unwrap(),
                meta
            );
            let config = LifterTrainConfig {
                arch,
                every: 4,
                batch: 256,
                steps: 10_000,
                epoch_steps: 500,
                lr: 1e-3,
                lr_decay: 0.95,
                clip_norm: 5.0,
                flip_prob: 0.5,
                seed: 0,
                val_every: 500,
                val_samples: 8192,
                checkpoint_secs: 300,
                objective: Objective::Adjusted,
                direction_weight: 1.0,
                init_weights: Some("a/b.safetensors".into()),
            };
            assert_eq!(serde_json::to_string(&config).unwrap(), config_json);
            assert_eq!(
                serde_json::from_str::<LifterTrainConfig>(config_json).unwrap(),
                config
            );
        }
    }
}

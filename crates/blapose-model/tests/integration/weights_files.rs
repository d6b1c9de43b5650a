//! Saving and loading weights files, and refusing bad ones.

use std::collections::HashMap;

use blapose_model::names::{FC_WEIGHT, GRU_ONLINE_B};
use blapose_model::weights::{self, WeightsMetadata};
use blapose_model::{init, LoadedWeights, ModelError, ModelKind};
use candle_core::{DType, Device, Tensor};

fn meta(kind: ModelKind) -> WeightsMetadata {
    let mut m = WeightsMetadata::new(kind);
    m.training_data = "h36m S1 S5 S6 S7 S8, synthetic lengths".into();
    m.version = "test-1".into();
    m.extra.insert("val_mm".into(), "8.9".into());
    m
}

fn values(t: &Tensor) -> Vec<f32> {
    t.flatten_all().unwrap().to_vec1().unwrap()
}

#[test]
fn round_trip_through_file_and_bytes_keeps_tensors_and_metadata() {
    for kind in [ModelKind::Gru, ModelKind::BiGru] {
        let tensors = init::random_tensors(kind, 42).unwrap();
        let dir = std::env::temp_dir().join(format!("blapose-model-test-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join(format!("{kind}.safetensors"));
        weights::save(&path, &tensors, &meta(kind)).unwrap();
        let from_file = weights::load(&path, kind).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        let from_bytes = weights::load_bytes(&bytes, kind).unwrap();
        std::fs::remove_file(&path).unwrap();
        for loaded in [&from_file, &from_bytes] {
            assert_eq!(loaded.meta, meta(kind));
            assert_eq!(loaded.tensors().len(), tensors.len());
            for (name, t) in &tensors {
                assert_eq!(values(loaded.tensor(name).unwrap()), values(t), "{name}");
            }
        }
    }
}

#[test]
fn half_precision_files_load_as_f32() {
    let tensors: HashMap<String, Tensor> = init::random_tensors(ModelKind::Gru, 1)
        .unwrap()
        .into_iter()
        .map(|(k, v)| (k, v.to_dtype(DType::F16).unwrap()))
        .collect();
    let bytes = weights::to_bytes(&tensors, &meta(ModelKind::Gru)).unwrap();
    let loaded = weights::load_bytes(&bytes, ModelKind::Gru).unwrap();
    assert_eq!(loaded.tensor(FC_WEIGHT).unwrap().dtype(), DType::F32);
}

#[test]
fn varmap_round_trip() {
    let loaded = LoadedWeights::random(ModelKind::BiGru, 3).unwrap();
    let vm = loaded.to_varmap().unwrap();
    let back = weights::varmap_tensors(&vm).unwrap();
    let bytes = weights::to_bytes(&back, &loaded.meta).unwrap();
    let again = weights::load_bytes(&bytes, ModelKind::BiGru).unwrap();
    assert_eq!(
        values(again.tensor(FC_WEIGHT).unwrap()),
        values(loaded.tensor(FC_WEIGHT).unwrap())
    );
}

#[test]
fn wrong_kind_is_refused() {
    let bytes = weights::to_bytes(
        &init::random_tensors(ModelKind::BiGru, 1).unwrap(),
        &meta(ModelKind::BiGru),
    )
    .unwrap();
    let err = weights::load_bytes(&bytes, ModelKind::Gru).unwrap_err();
    assert!(
        matches!(
            err,
            ModelError::WrongKind {
                expected: ModelKind::Gru,
                found: ModelKind::BiGru
            }
        ),
        "{err}"
    );
    assert!(err.to_string().contains("bigru"), "{err}");
}

/// Serialize arbitrary tensors with valid metadata, bypassing `to_bytes`'
/// own validation, to build the bad files a loader must refuse.
fn raw_file(tensors: &HashMap<String, Tensor>, header: HashMap<String, String>) -> Vec<u8> {
    let mut named: Vec<_> = tensors.iter().collect();
    named.sort_by(|a, b| a.0.cmp(b.0));
    safetensors::serialize(named, Some(header)).unwrap()
}

#[test]
fn missing_tensor_is_refused() {
    let mut t = init::random_tensors(ModelKind::Gru, 1).unwrap();
    let name = format!("{GRU_ONLINE_B}.weight_hh_l0");
    t.remove(&name);
    let bytes = raw_file(&t, meta(ModelKind::Gru).to_header());
    let err = weights::load_bytes(&bytes, ModelKind::Gru).unwrap_err();
    assert!(
        matches!(&err, ModelError::MissingTensor { name: n, .. } if *n == name),
        "{err}"
    );
}

#[test]
fn misshaped_tensor_is_refused() {
    let mut t = init::random_tensors(ModelKind::Gru, 1).unwrap();
    t.insert(
        FC_WEIGHT.into(),
        Tensor::zeros((16, 512), DType::F32, &Device::Cpu).unwrap(),
    );
    let bytes = raw_file(&t, meta(ModelKind::Gru).to_header());
    let err = weights::load_bytes(&bytes, ModelKind::Gru).unwrap_err();
    assert!(
        matches!(&err, ModelError::ShapeMismatch { name, expected, found }
            if name == FC_WEIGHT && expected == &[16, 1024] && found == &[16, 512]),
        "{err}"
    );
    // saving refuses it too
    assert!(matches!(
        weights::to_bytes(&t, &meta(ModelKind::Gru)),
        Err(ModelError::ShapeMismatch { .. })
    ));
}

#[test]
fn unexpected_tensor_is_refused() {
    let mut t = init::random_tensors(ModelKind::Gru, 1).unwrap();
    t.insert(
        "fc.bias".into(),
        Tensor::zeros(16, DType::F32, &Device::Cpu).unwrap(),
    );
    let bytes = raw_file(&t, meta(ModelKind::Gru).to_header());
    let err = weights::load_bytes(&bytes, ModelKind::Gru).unwrap_err();
    assert!(
        matches!(&err, ModelError::UnexpectedTensor { name, .. } if name == "fc.bias"),
        "{err}"
    );
}

#[test]
fn non_finite_weight_is_refused() {
    let mut t = init::random_tensors(ModelKind::Gru, 1).unwrap();
    let mut fc = values(&t[FC_WEIGHT]);
    fc[100] = f32::NAN;
    t.insert(
        FC_WEIGHT.into(),
        Tensor::from_vec(fc, (16, 1024), &Device::Cpu).unwrap(),
    );
    let bytes = raw_file(&t, meta(ModelKind::Gru).to_header());
    let err = weights::load_bytes(&bytes, ModelKind::Gru).unwrap_err();
    assert!(
        matches!(&err, ModelError::NonFiniteWeight { name } if name == FC_WEIGHT),
        "{err}"
    );
}

#[test]
fn files_without_blapose_metadata_are_refused() {
    let t = init::random_tensors(ModelKind::Gru, 1).unwrap();
    let bytes = raw_file(&t, HashMap::new());
    let err = weights::load_bytes(&bytes, ModelKind::Gru).unwrap_err();
    assert!(
        matches!(err, ModelError::MissingMetadata { key: "format" }),
        "{err}"
    );

    let mut header = meta(ModelKind::Gru).to_header();
    header.insert("kind".into(), "lstm".into());
    let err = weights::load_bytes(&raw_file(&t, header), ModelKind::Gru).unwrap_err();
    assert!(
        matches!(err, ModelError::BadMetadata { key: "kind", .. }),
        "{err}"
    );

    let mut header = meta(ModelKind::Gru).to_header();
    header.insert("format_version".into(), "99".into());
    let err = weights::load_bytes(&raw_file(&t, header), ModelKind::Gru).unwrap_err();
    assert!(
        matches!(
            err,
            ModelError::BadMetadata {
                key: "format_version",
                ..
            }
        ),
        "{err}"
    );
}

#[test]
fn garbage_and_missing_files_are_refused() {
    let err = weights::load_bytes(b"definitely not safetensors", ModelKind::Gru).unwrap_err();
    assert!(matches!(err, ModelError::InvalidFile(_)), "{err}");
    let err = weights::load("/nonexistent/blapose.safetensors", ModelKind::Gru).unwrap_err();
    assert!(matches!(err, ModelError::Io { .. }), "{err}");
    assert!(err.to_string().contains("/nonexistent/blapose.safetensors"));
}

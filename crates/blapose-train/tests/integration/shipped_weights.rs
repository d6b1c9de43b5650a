//! The shipped weights load and reproduce the model card's subset numbers.
//!
//! `models/subset_check.json` (written when the weights are shipped) holds
//! `{"every": k, "bigru_sh_mm": x, "gru_sh_mm": y}`: the headline error of
//! `blapose eval --model M --input sh --every k` on S9/S11, and the same
//! for the camera-aware pair (`*_rectified_sh_mm`, evaluated with
//! `--calibrated`, as the server serves a calibrated session). Skips when the data, the weights or that file are absent.
//! The weights' training configurations must parse in any case.

use std::path::Path;

use blapose_data::h36m::{H36m, Parts, ALL_SUBJECTS, TEST_SUBJECTS};
use blapose_model::ModelKind;
use blapose_train::dataset::{eval_sequences, subject_lengths, InputKind};
use blapose_train::eval::run::network_estimator;
use blapose_train::eval::{calibrate, evaluate};

#[test]
fn shipped_weights_reproduce_the_model_card() {
    let models = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../models");
    let check = models.join("subset_check.json");
    let Ok(text) = std::fs::read_to_string(&check) else {
        println!(
            "skipping shipped-weights check: {} not found",
            check.display()
        );
        return;
    };
    let Some(root) =
        blapose_data::test_data_root("h36m/detections_sh.npz", "shipped-weights check")
    else {
        return;
    };
    let spec: serde_json::Value = serde_json::from_str(&text).unwrap();
    let every = spec["every"].as_u64().unwrap_or(20) as usize;
    let all = H36m::load(&root, &ALL_SUBJECTS, Parts::POSES).unwrap();
    let lengths = subject_lengths(&all);
    let h = H36m::load(&root, &TEST_SUBJECTS, Parts::ALL).unwrap();
    let trials: Vec<_> = eval_sequences(&h, &TEST_SUBJECTS, InputKind::Sh, &lengths)
        .unwrap()
        .into_iter()
        .step_by(every)
        .collect();
    for (kind, file, key) in [
        (
            ModelKind::BiGru,
            "bone_length_bigru.safetensors",
            "bigru_sh_mm",
        ),
        (ModelKind::Gru, "bone_length_gru.safetensors", "gru_sh_mm"),
        (
            ModelKind::BiGru,
            "bone_length_bigru_rectified.safetensors",
            "bigru_rectified_sh_mm",
        ),
        (
            ModelKind::Gru,
            "bone_length_gru_rectified.safetensors",
            "gru_rectified_sh_mm",
        ),
    ] {
        let Some(expected) = spec[key].as_f64() else {
            continue;
        };
        let weights =
            blapose_model::weights::load(models.join(file), kind).expect("shipped weights load");
        let est = network_estimator(kind, &weights, blapose_model::Precision::F32).unwrap();
        // The camera-aware pair as a calibrated session is served.
        let mut trials = trials.clone();
        if key.contains("rectified") {
            calibrate(&weights, &mut trials, |s, id| h.cameras.get(s, id)).unwrap();
        }
        let r = evaluate(est.as_ref(), &trials, &[], kind.as_str(), "sh", file, &[]).unwrap();
        assert!(
            (r.mean_bone_error_mm - expected).abs() < 0.05,
            "{file}: {:.3} mm on the subset, model card says {expected:.3}",
            r.mean_bone_error_mm
        );
    }
}

/// Every shipped bone-length file's `train_config`, written before some
/// research options were removed, still parses into [`TrainConfig`] and
/// serializes back to the same values, and reads into the input contract
/// its family is served by (`rectify`, `floor_scaled` and `wide_cameras`
/// there: [`blapose_model::input::ModelInput::from_train_config`]).
#[test]
fn shipped_train_configs_still_parse() {
    use blapose_model::input::ModelInput;
    use blapose_train::lengths::LengthStrategy;
    use blapose_train::noise::NoiseKind;
    use blapose_train::synth::ShiftPlane;
    use blapose_train::train::{removed_options, TrainConfig};
    let models = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../models");
    for (file, kind, rectify) in [
        ("bone_length_bigru.safetensors", ModelKind::BiGru, false),
        ("bone_length_gru.safetensors", ModelKind::Gru, false),
        (
            "bone_length_bigru_rectified.safetensors",
            ModelKind::BiGru,
            true,
        ),
        (
            "bone_length_gru_rectified.safetensors",
            ModelKind::Gru,
            true,
        ),
    ] {
        let weights = blapose_model::weights::load(models.join(file), kind).expect(file);
        let text = &weights.meta.extra[blapose_model::input::KEY_TRAIN_CONFIG];
        let old: serde_json::Value = serde_json::from_str(text).unwrap();
        assert_eq!(removed_options(&old), Vec::<&str>::new(), "{file}");
        let cfg: TrainConfig = serde_json::from_str(text).expect(file);
        assert_eq!((cfg.kind, cfg.rectify), (kind, rectify));
        // What the trainer now records, read back from the older file.
        assert_eq!(weights.meta.input, Some(cfg.model_input()), "{file}");
        assert_eq!(cfg.lengths, LengthStrategy::Ansur);
        assert_eq!(cfg.noise, NoiseKind::Residual);
        if rectify {
            // The camera-aware pair: any calibrated camera, metric floor
            // scaling, bodies outside the benchmark's held-out split.
            assert!(cfg.floor_scaled, "{file}");
            assert_eq!(cfg.wide_cameras, 1.0, "{file}");
            assert_eq!(
                cfg.model_input(),
                ModelInput::from_training(true, true, true),
                "{file}"
            );
            assert_eq!(
                cfg.ansur_people,
                blapose_train::ansur_split::AnsurPeople::Train,
                "{file}"
            );
        } else {
            assert_eq!(cfg.model_input(), ModelInput::screen(), "{file}");
            assert_eq!(cfg.shift_plane, ShiftPlane::Ground);
            // Written before the held-out split: every ANSUR person.
            assert_eq!(
                cfg.ansur_people,
                blapose_train::ansur_split::AnsurPeople::All,
                "{file}"
            );
        }
        // As the trainer writes it (f32 fields in their shortest form).
        let new: serde_json::Value =
            serde_json::from_str(&serde_json::to_string(&cfg).unwrap()).unwrap();
        for (field, value) in new.as_object().unwrap() {
            // Fields added after a file was written take their defaults.
            if let Some(was) = old.get(field) {
                assert_eq!(was, value, "{file}: {field}");
            }
        }
    }
    // A configuration that used a removed option says which.
    let mut old: serde_json::Value = serde_json::json!({"detector_gain": true, "noise_scale": 1.0});
    assert_eq!(removed_options(&old), ["detector_gain"]);
    old["noise_scale"] = 1.5.into();
    assert_eq!(removed_options(&old), ["noise_scale", "detector_gain"]);
    // Height-normalized targets are gone; `false` (what every shipped file
    // says, or nothing) is still read.
    let old = serde_json::json!({"rectify": true, "height_normalized": true});
    assert_eq!(removed_options(&old), ["height_normalized"]);
    assert!(removed_options(&serde_json::json!({"height_normalized": false})).is_empty());
}

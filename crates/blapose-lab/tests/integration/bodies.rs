//! The many-bodies benchmark on the real data (skipped when ../shared/data
//! is absent): a tiny end-to-end run of the four shipped models, and the
//! real-detection check beside their rows.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use blapose_core::skeleton::BONE_NAMES;
use blapose_data::h36m::{H36m, Parts, TRAIN_SUBJECTS};
use blapose_data::test_data_root;
use blapose_lab::bodies::{
    build_trials, mean_body, test_motions, BenchModel, BodiesConfig, BodiesInput, RowInput,
    RowModel, SHIPPED_MODELS,
};
use blapose_lab::real_check::RealCheck;
use blapose_model::input::Framing;
use blapose_train::ansur_split::{AnsurPeople, AnsurSplit};
use blapose_train::dataset::{
    eval_sequences, mean_subject_lengths, EvalSequence, InputKind, TrainingSet,
};
use blapose_train::lengths::TrainingLengthStats;
use blapose_train::stature::StatureRegression;
use blapose_train::synth::MotionSequence;

struct Fixture {
    root: PathBuf,
    set: TrainingSet,
    split: AnsurSplit,
    motions: Vec<MotionSequence>,
}

fn fixture() -> Option<&'static Fixture> {
    static F: OnceLock<Option<Fixture>> = OnceLock::new();
    F.get_or_init(|| {
        let root = test_data_root("h36m/poses_3d.npz", "many-bodies benchmark tests")?;
        test_data_root(
            "ansur2/ANSUR_II_MALE_Public.csv",
            "many-bodies benchmark tests",
        )?;
        let set = TrainingSet::load(&root).expect("training set loads");
        let stats = TrainingLengthStats::from_training(&set.lengths_list()).unwrap();
        let split = AnsurSplit::load(&root, &stats).unwrap();
        let h36m = H36m::load(&root, &["S9", "S11"], Parts::POSES).unwrap();
        let motions = test_motions(&h36m, &["S9", "S11"]).unwrap();
        Some(Fixture {
            root,
            set,
            split,
            motions,
        })
    })
    .as_ref()
}

fn models_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../models")
}

#[test]
fn a_tiny_benchmark_run_gives_well_formed_deterministic_rows() {
    let Some(f) = fixture() else { return };
    let cfg = BodiesConfig {
        frames: 40,
        limit: Some(6),
        ..BodiesConfig::default()
    };
    let people = f.split.held_out();
    let train = f.split.training_population(AnsurPeople::Train).unwrap();
    let stature = StatureRegression::fit_training(&f.split.everyone).unwrap();
    let input = BodiesInput {
        people: people.clone(),
        motions: f.motions.clone(),
        residuals: &f.set.residuals,
        prior: mean_body(train.people()).unwrap(),
        training_mean: mean_subject_lengths(&f.set.subject_lengths, &TRAIN_SUBJECTS).unwrap(),
        stature: Some(&stature),
        fit_set: None,
        real_check: None,
    };
    let specs = SHIPPED_MODELS;
    let weights: Vec<_> = specs
        .iter()
        .map(|(k, _, file)| blapose_model::weights::load(models_dir().join(file), *k).unwrap())
        .collect();
    let models: Vec<BenchModel<'_>> = specs
        .iter()
        .zip(&weights)
        .map(|((kind, input, file), w)| BenchModel {
            kind: *kind,
            input: *input,
            weights: w,
            path: file.to_string(),
        })
        .collect();
    let report = blapose_lab::bodies::run(&input, &models, &cfg).unwrap();
    assert_eq!(report.individuals, 6);
    assert_eq!(report.frames, 6 * 40);
    assert_eq!(report.trials.len(), 6);
    let json = serde_json::to_value(&report).unwrap();
    let rows = json["rows"].as_array().unwrap();
    let combos: Vec<(String, String)> = rows
        .iter()
        .map(|r| {
            (
                r["model"].as_str().unwrap().to_string(),
                r["input"].as_str().unwrap().to_string(),
            )
        })
        .collect();
    for want in [
        ("gru", "none"),
        ("bigru", "none"),
        ("gru", "calibration"),
        ("bigru", "calibration"),
        ("stature-regression", "height"),
        ("stature-regression", "height+sex"),
    ] {
        assert!(combos.contains(&(want.0.into(), want.1.into())), "{want:?}");
    }
    // The models' rows first, in their order; the regression's after,
    // then the two size oracles.
    assert_eq!(combos.len(), 8);
    assert!(combos[4..6].iter().all(|(m, _)| m == "stature-regression"));
    assert!(combos[6..]
        .iter()
        .all(|(m, i)| m.starts_with("oracle: ") && i == "true size"));
    assert!(report.rows[6..]
        .iter()
        .all(|r| r.input == RowInput::TrueSize));
    assert_eq!(report.rows[1].model, RowModel::BiGru);
    let prior = report.rows[0].prior_mean_bone_error_mm;
    for r in rows {
        for k in [
            "mean_bone_error_mm",
            "prior_mean_bone_error_mm",
            "ratio_to_prior",
            "size_slope",
            "at_prior_size_mm",
        ] {
            assert!(r[k].as_f64().unwrap().is_finite(), "{k}");
        }
        let per_bone = r["per_bone_mm"].as_array().unwrap();
        assert_eq!(per_bone.len(), BONE_NAMES.len());
        let e = r["mean_bone_error_mm"].as_f64().unwrap();
        let mean_of_bones = per_bone.iter().map(|v| v.as_f64().unwrap()).sum::<f64>() / 16.0;
        assert!(
            (e - mean_of_bones).abs() < 1e-6,
            "error is the mean over bones"
        );
        assert!(e > 0.0 && e < 200.0);
        assert_eq!(r["prior_mean_bone_error_mm"].as_f64().unwrap(), prior);
        assert!((r["ratio_to_prior"].as_f64().unwrap() - e / prior).abs() < 1e-9);
    }
    // Every camera framed the whole clip within the documented bounds.
    for t in &report.trials {
        let c = &t.camera;
        assert!((0.5..=3.0).contains(&c.height_m) && (2.0..=10.0).contains(&c.distance_m));
        assert!((-35.0..=15.0).contains(&c.pitch_deg) && c.roll_deg.abs() <= 5.0);
        assert!((40.0..=100.0).contains(&c.hfov_deg));
    }
    let md = blapose_lab::bodies::markdown(&report);
    assert!(md.contains("| bigru | calibration |") && md.contains("baseline: prior"));
    assert!(md.contains("| stature-regression | height+sex |"));
    // The regression reads sizes: taller individuals get longer bones.
    for r in &report.rows[4..6] {
        assert!(r.size_slope > 0.3, "{}: {}", r.input, r.size_slope);
    }
    // The oracles are given the size: slope 1, and better than the prior.
    for r in &report.rows[6..] {
        assert!((r.size_slope - 1.0).abs() < 1e-4, "{}", r.model);
        assert!(r.ratio_to_prior < 1.0, "{}", r.model);
    }
    // Without the regression the model rows are exactly the same.
    let bare = BodiesInput {
        stature: None,
        fit_set: None,
        real_check: None,
        ..input
    };
    let without = blapose_lab::bodies::run(&bare, &models, &cfg).unwrap();
    assert_eq!(without.rows.len(), 4);
    for (a, b) in without.rows.iter().zip(&report.rows) {
        assert_eq!(
            (a.mean_bone_error_mm, &a.per_bone_mm, a.size_slope),
            (b.mean_bone_error_mm, &b.per_bone_mm, b.size_slope)
        );
    }

    // Seeded: the same trials again; another seed, other cameras.
    let a = build_trials(&people, &f.motions, &f.set.residuals, &cfg).unwrap();
    let b = build_trials(&people, &f.motions, &f.set.residuals, &cfg).unwrap();
    assert!(a
        .iter()
        .zip(&b)
        .all(|(x, y)| x.plain == y.plain && x.camera == y.camera));
    let other = BodiesConfig { seed: 7, ..cfg };
    let c = build_trials(&people, &f.motions, &f.set.residuals, &other).unwrap();
    assert!(a.iter().zip(&c).any(|(x, y)| x.camera != y.camera));
    // The camera-aware models read what their contract says: the plain
    // keypoints rectified and scaled to the floor (tilted cameras move
    // them); the default pair reads them as they are.
    let camera_aware = models[2].contract().unwrap();
    assert_eq!(camera_aware.framing, Framing::LevelFloorScaled);
    assert_eq!(models[0].contract().unwrap().framing, Framing::Screen);
    for t in &a {
        assert_eq!(
            t.stream(&models[0].contract().unwrap()).unwrap().input,
            t.plain
        );
    }
    assert!(a
        .iter()
        .any(|t| t.stream(&camera_aware).unwrap().input != t.plain));
}

#[test]
fn the_real_detection_check_scores_models_beside_their_rows() {
    let Some(f) = fixture() else { return };
    let real = H36m::load(&f.root, &["S1"], Parts::ALL).unwrap();
    let lengths = f.set.subject_lengths.clone();
    let trials: Vec<EvalSequence> = eval_sequences(&real, &["S1"], InputKind::Sh, &lengths)
        .unwrap()
        .into_iter()
        .step_by(40)
        .collect();
    assert!(trials.len() >= 2);
    let camera = |s: &str, id: &str| real.cameras.get(s, id);
    let stature = StatureRegression::fit_training(&f.split.everyone).unwrap();
    let train = f.split.training_population(AnsurPeople::Train).unwrap();
    let training_mean = mean_subject_lengths(&f.set.subject_lengths, &TRAIN_SUBJECTS).unwrap();
    let input = BodiesInput {
        people: f.split.held_out(),
        motions: f.motions.clone(),
        residuals: &f.set.residuals,
        prior: mean_body(train.people()).unwrap(),
        training_mean,
        stature: Some(&stature),
        fit_set: None,
        real_check: Some(RealCheck {
            trials: trials.clone(),
            camera: &camera,
        }),
    };
    let (kind, bench_input, file) = SHIPPED_MODELS[3];
    let w = blapose_model::weights::load(models_dir().join(file), kind).unwrap();
    let models = [BenchModel {
        kind,
        input: bench_input,
        weights: &w,
        path: file.to_string(),
    }];
    let cfg = BodiesConfig {
        frames: 20,
        limit: Some(3),
        ..BodiesConfig::default()
    };
    let report = blapose_lab::bodies::run(&input, &models, &cfg).unwrap();
    let info = report.real_check.as_ref().expect("the check ran");
    assert_eq!(info.subjects, vec!["S1"]);
    assert_eq!(info.trials, trials.len());
    // The camera-aware Bi-GRU, the regression with height: checked; with
    // sex: not.
    let checked: Vec<(&str, Option<f64>)> = report
        .rows
        .iter()
        .map(|r| (r.input.name(), r.real_check_mm))
        .collect();
    assert_eq!(checked.len(), 5);
    let e = checked[0].1.expect("the model row is checked");
    assert!(e > 0.0 && e < 60.0, "{e}");
    assert!(checked[1].1.is_some() && checked[2..].iter().all(|c| c.1.is_none()));
    // The same trials scored directly give the same number.
    let direct = RealCheck {
        trials,
        camera: &camera,
    }
    .model_error(&models[0])
    .unwrap();
    assert_eq!(direct, e);
    let md = blapose_lab::bodies::markdown(&report);
    assert!(md.contains("training subjects' real SH (mm)") && md.contains("Real-detection check"));
    let json = serde_json::to_value(&report).unwrap();
    assert!(json["rows"][0]["real_check_mm"].is_f64());
    assert!(json["rows"][2].get("real_check_mm").is_none());
}

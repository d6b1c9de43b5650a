//! The training loop: the loss falls, and a resumed run continues exactly.

use std::sync::Arc;

use blapose_model::{LoadedWeights, ModelKind};
use blapose_train::adam::{Adam, AdamConfig};
use blapose_train::dataset::TrainingSet;
use blapose_train::fastnet::{FastNet, LossConfig};
use blapose_train::lengths::{LengthSampler, LengthStrategy, TrainingLengthStats};
use blapose_train::synth::SynthSource;
use blapose_train::train::{
    real_validation_batches, train, validate, validation_batches, TrainConfig, WEIGHTS_FILE,
};
use rand::{Rng, SeedableRng};

#[test]
fn loss_falls_on_a_tiny_synthetic_set() {
    for kind in [ModelKind::Gru, ModelKind::BiGru] {
        let (b, t) = (4, 8);
        let mut rng = rand::rngs::StdRng::seed_from_u64(4);
        let x: Vec<f32> = (0..b * t * 34)
            .map(|_| rng.random_range(-1.0f32..1.0))
            .collect();
        let y: Vec<f32> = (0..b * 16).map(|_| rng.random_range(0.1f32..0.5)).collect();
        let w = LoadedWeights::random(kind, 1).unwrap();
        let mut net = FastNet::from_tensors(kind, w.tensors()).unwrap();
        let mut opt = Adam::new(
            net.params.len(),
            AdamConfig {
                lr: 1e-3,
                ..Default::default()
            },
        );
        let mut grad = vec![0.0f32; net.params.len()];
        let cfg = LossConfig {
            running_mean_weight: 0.5,
            dropout: 0.0,
        };
        let first = net
            .train_step(&x, &y, b, t, cfg, &mut rng, &mut grad)
            .final_l1;
        opt.step(&mut net.params, &grad).unwrap();
        let mut last = first;
        for _ in 0..60 {
            last = net
                .train_step(&x, &y, b, t, cfg, &mut rng, &mut grad)
                .final_l1;
            opt.step(&mut net.params, &grad).unwrap();
        }
        assert!(last < 0.3 * first, "{kind}: loss {first} -> {last}");
    }
}

fn config(steps: u64) -> TrainConfig {
    TrainConfig {
        kind: "gru".into(),
        lengths: "normal".into(),
        noise: "residual".into(),
        noise_scale: 1.0,
        seq_len: 8,
        stride_min: 50.0 / 60.0,
        stride_max: 2.0,
        shift_std: 0.5,
        shift_plane: "camera".into(),
        floor_contact: false,
        detector_gain: false,
        precondition: false,
        camera_height_std: 0.0,
        camera_angle_std_deg: 0.0,
        random_yaw: false,
        decouple_size: false,
        cameras: Vec::new(),
        rectify: false,
        height_normalized: false,
        flip_prob: 0.5,
        batch: 4,
        steps,
        epoch_steps: 2,
        lr: 1e-3,
        lr_decay: 0.9,
        clip_norm: 5.0,
        per_frame_weight: 0.5,
        ansur_spread: 0.0,
        init_weights: None,
        init_output_mean: true,
        // exercised by the resume test: the average must survive a resume
        head_lr_scale: 0.1,
        ema_decay: 0.9,
        seed: 3,
        val_every: 2,
        val_samples: 8,
        val_frames: 8,
        checkpoint_secs: 3600,
    }
}

/// Every tensor of `a` equals `b`'s tensor of the same name, bit for bit.
fn assert_same_weights(a: &LoadedWeights, b: &LoadedWeights, what: &str) {
    assert_weights_within(a, b, 0.0, what);
}

/// Every value of `a` is within `tolerance x (1 + |value|)` of `b`'s value
/// in the tensor of the same name (0: equal).
fn assert_weights_within(a: &LoadedWeights, b: &LoadedWeights, tolerance: f32, what: &str) {
    for (name, t) in a.tensors() {
        let va: Vec<f32> = t.flatten_all().unwrap().to_vec1().unwrap();
        let vb: Vec<f32> = b
            .tensor(name)
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1()
            .unwrap();
        assert_eq!(va.len(), vb.len(), "tensor {name} {what}");
        let worst = va
            .iter()
            .zip(&vb)
            .map(|(x, y)| {
                if x == y {
                    0.0
                } else if x.is_nan() || y.is_nan() {
                    f32::INFINITY
                } else {
                    (x - y).abs() / (1.0 + x.abs())
                }
            })
            .fold(0.0f32, f32::max);
        assert!(worst <= tolerance, "tensor {name} {what} (by {worst})");
    }
}

/// The training set and a `normal`-strategy source over it (`None`, with a
/// skip message, when the data is absent).
fn training_source(what: &str) -> Option<(TrainingSet, Arc<SynthSource>)> {
    let root = blapose_data::test_data_root("h36m/poses_3d.npz", what)?;
    let set = TrainingSet::load(&root).unwrap();
    let stats = TrainingLengthStats::from_training(&set.lengths_list()).unwrap();
    let sampler = LengthSampler::new(LengthStrategy::Normal, stats, None).unwrap();
    let source =
        Arc::new(SynthSource::new(set.sequences.clone(), set.residuals.clone(), sampler).unwrap());
    Some((set, source))
}

#[test]
fn resume_continues_exactly() {
    let Some((set, source)) = training_source("resume test") else {
        return;
    };
    let real = &set.real_sh[..20];
    let dir = std::env::temp_dir().join(format!("blapose-train-resume-{}", std::process::id()));
    let (straight, split) = (dir.join("straight"), dir.join("split"));
    let mut quiet = |_: u64, _: u64, _: f64, _: f64| {};
    let a = train(
        &config(4),
        source.clone(),
        real,
        &straight,
        false,
        "test",
        &mut quiet,
    )
    .unwrap();
    assert_eq!(a.steps_run, 4);
    let b1 = train(
        &config(2),
        source.clone(),
        real,
        &split,
        false,
        "test",
        &mut quiet,
    )
    .unwrap();
    assert_eq!(b1.steps_run, 2);
    let b2 = train(
        &config(4),
        source.clone(),
        real,
        &split,
        true,
        "test",
        &mut quiet,
    )
    .unwrap();
    assert_eq!(b2.steps_run, 2, "resumed at step 2");
    let wa = blapose_model::weights::load(straight.join(WEIGHTS_FILE), ModelKind::Gru).unwrap();
    let wb = blapose_model::weights::load(split.join(WEIGHTS_FILE), ModelKind::Gru).unwrap();
    assert_same_weights(&wa, &wb, "differs after resume");
    assert_eq!(a.validation, b2.validation);
    // The log has one row per validation (row 0: the untrained network),
    // none duplicated by the resume.
    let log = std::fs::read_to_string(split.join("train_log.csv")).unwrap();
    assert_eq!(log.lines().count(), 4, "{log}");
    assert!(log.lines().nth(1).unwrap().starts_with("0,"), "{log}");
    // A checkpoint from another configuration is refused.
    let mut other = config(6);
    other.batch = 8;
    assert!(train(
        &other,
        source.clone(),
        real,
        &split,
        true,
        "test",
        &mut quiet
    )
    .is_err());
    // A warm start begins at the given weights: with a zero learning rate
    // the run's weights are exactly the file's.
    let mut warm = config(1);
    warm.lr = 0.0;
    warm.init_weights = Some(straight.join(WEIGHTS_FILE).display().to_string());
    let warm_dir = dir.join("warm");
    train(
        &warm,
        source.clone(),
        real,
        &warm_dir,
        false,
        "test",
        &mut quiet,
    )
    .unwrap();
    let ww = blapose_model::weights::load(warm_dir.join(WEIGHTS_FILE), ModelKind::Gru).unwrap();
    assert_same_weights(&wa, &ww, "changed by the warm start");
    warm.init_weights = Some(dir.join("missing.safetensors").display().to_string());
    assert!(train(
        &warm,
        source,
        real,
        &dir.join("warm2"),
        false,
        "test",
        &mut quiet
    )
    .is_err());
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_preconditioned_run_saves_weights_that_read_raw_coordinates() {
    let Some((set, source)) = training_source("precondition test") else {
        return;
    };
    let real = &set.real_sh[..20];
    let dir = std::env::temp_dir().join(format!("blapose-train-pre-{}", std::process::id()));
    let mut quiet = |_: u64, _: u64, _: f64, _: f64| {};
    let mut cfg = config(3);
    cfg.precondition = true;
    let run = train(&cfg, source.clone(), real, &dir, false, "test", &mut quiet).unwrap();
    // The run validated its internal network on preconditioned inputs; the
    // saved file, on the raw inputs, must score the same.
    let saved = blapose_model::weights::load(dir.join(WEIGHTS_FILE), ModelKind::Gru).unwrap();
    let net = FastNet::from_tensors(ModelKind::Gru, saved.tensors()).unwrap();
    let synth = cfg.synth().unwrap();
    let val_synth = validation_batches(
        &source,
        &synth,
        cfg.seed,
        cfg.val_samples,
        cfg.batch.min(64),
    );
    let val_real = real_validation_batches(real, cfg.val_frames, 64);
    let raw = validate(&net, &val_synth, &val_real);
    for (a, b) in [
        (raw.synth_mm, run.validation.synth_mm),
        (raw.real_sh_mm, run.validation.real_sh_mm),
        (raw.real_sh_running_mm, run.validation.real_sh_running_mm),
    ] {
        assert!((a - b).abs() < 0.01, "raw {a} mm vs preconditioned {b} mm");
    }
    // A warm start unfolds the file into the preconditioned space: with a
    // zero learning rate it saves the same weights back (up to rounding).
    let mut warm = config(1);
    warm.precondition = true;
    warm.lr = 0.0;
    warm.init_weights = Some(dir.join(WEIGHTS_FILE).display().to_string());
    train(
        &warm,
        source,
        real,
        &dir.join("warm"),
        false,
        "test",
        &mut quiet,
    )
    .unwrap();
    let back =
        blapose_model::weights::load(dir.join("warm").join(WEIGHTS_FILE), ModelKind::Gru).unwrap();
    assert_weights_within(&saved, &back, 1e-3, "moved by the warm start");
    let _ = std::fs::remove_dir_all(&dir);
}

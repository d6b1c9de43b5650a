//! The training loop: the loss falls, and a resumed run continues exactly.

use std::sync::Arc;

use blapose_model::{LoadedWeights, ModelKind};
use blapose_train::adam::{Adam, AdamConfig};
use blapose_train::dataset::TrainingSet;
use blapose_train::fastnet::{FastNet, LossConfig};
use blapose_train::lengths::{LengthSampler, LengthStrategy, TrainingLengthStats};
use blapose_train::noise::NoiseKind;
use blapose_train::synth::{ShiftPlane, SynthSource};
use blapose_train::train::{train, TrainConfig, WEIGHTS_FILE};
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
        kind: ModelKind::Gru,
        lengths: LengthStrategy::Normal,
        noise: NoiseKind::Residual,
        seq_len: 8,
        stride_min: 50.0 / 60.0,
        stride_max: 2.0,
        shift_std: 0.5,
        shift_plane: ShiftPlane::Camera,
        floor_contact: false,
        random_yaw: false,
        cameras: Vec::new(),
        rectify: false,
        floor_scaled: false,
        wide_cameras: 0.0,
        flip_prob: 0.5,
        batch: 4,
        steps,
        epoch_steps: 2,
        lr: 1e-3,
        lr_decay: 0.9,
        clip_norm: 5.0,
        per_frame_weight: 0.5,
        ansur_spread: 0.0,
        ansur_people: blapose_train::ansur_split::AnsurPeople::Train,
        init_weights: None,
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
    for (name, t) in a.tensors() {
        let va: Vec<f32> = t.flatten_all().unwrap().to_vec1().unwrap();
        let vb: Vec<f32> = b
            .tensor(name)
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1()
            .unwrap();
        let same =
            va.len() == vb.len() && va.iter().zip(&vb).all(|(x, y)| x.to_bits() == y.to_bits());
        assert!(same, "tensor {name} {what}");
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

//! The lifter pipeline on synthetic data: training lowers the loss and a
//! resumed run reproduces an uninterrupted one; flips are their own
//! inverse; eval-adjust arithmetic on a hand-made fixture.

use std::collections::BTreeMap;

use blapose_core::bones::{bone_lengths, rebuild};
use blapose_core::pose::flip_pose;
use blapose_core::{BoneDirections, BoneLengths, Pose};
use blapose_train::dataset::EvalSequence;
use blapose_train::eval_adjust::{evaluate_lifter, markdown, Adjusters};
use blapose_train::lifter::data::{average_flipped, flip_input, gather, LifterSequence, Window};
use blapose_train::lifter::objective::Objective;
use blapose_train::lifter::train::{train, LifterTrainConfig};
use blapose_train::lifter::{pose_to_target, weights, LifterArch, MlpArch, VideoPoseArch};
use blapose_train::run::{read_log_column, LOG_FILE};
use rand::{Rng, SeedableRng};

/// A plausible skeleton: fixed directions, lengths 0.1..0.4 m.
fn base_pose() -> Pose {
    let dirs: BoneDirections = std::array::from_fn(|b| {
        let v = [
            (b as f32).sin(),
            -(1.3 * b as f32).cos(),
            0.4 + 0.1 * b as f32,
        ];
        let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
        v.map(|c| c / n)
    });
    let lengths: BoneLengths = std::array::from_fn(|b| 0.1 + 0.02 * b as f32);
    rebuild([0.0; 3], &dirs, &lengths)
}

fn rotate_y(p: &Pose, a: f32) -> Pose {
    let (s, c) = a.sin_cos();
    p.map(|j| [c * j[0] + s * j[2], j[1], -s * j[0] + c * j[2]])
}

/// A camera-space stream: the base pose turning about the vertical axis,
/// seen from 5 m; input = pinhole projection.
fn stream(subject: &str, sequence: &str, frames: usize, turn: f32) -> LifterSequence {
    let target: Vec<Pose> = (0..frames)
        .map(|t| rotate_y(&base_pose(), turn * t as f32))
        .collect();
    let input = target
        .iter()
        .flat_map(|p| {
            p.iter()
                .flat_map(|j| [j[0] / (j[2] + 5.0), j[1] / (j[2] + 5.0)])
        })
        .collect();
    LifterSequence {
        trial: EvalSequence {
            subject: subject.into(),
            sequence: sequence.into(),
            camera: "c".into(),
            input,
            gt: bone_lengths(&target[0]),
        },
        target,
    }
}

fn scaled(poses: &[Pose], s: f32) -> Vec<Pose> {
    poses.iter().map(|p| p.map(|j| j.map(|v| v * s))).collect()
}

fn mean_joint_norm(p: &Pose) -> f64 {
    p.iter()
        .map(|j| f64::from(j[0] * j[0] + j[1] * j[1] + j[2] * j[2]).sqrt())
        .sum::<f64>()
        / 17.0
}

fn tiny_config(steps: u64) -> LifterTrainConfig {
    LifterTrainConfig {
        arch: LifterArch::Mlp(MlpArch {
            hidden: 64,
            blocks: 1,
            dropout: 0.1,
        }),
        every: 2,
        batch: 32,
        steps,
        epoch_steps: 20,
        lr: 3e-3,
        lr_decay: 0.9,
        clip_norm: 5.0,
        flip_prob: 0.5,
        seed: 3,
        val_every: 5,
        val_samples: 64,
        checkpoint_secs: 3600,
        objective: Objective::Mpjpe,
        direction_weight: 1.0,
        init_weights: None,
    }
}

fn tiny_set() -> Vec<LifterSequence> {
    vec![
        stream("S1", "Walking 1", 120, 0.05),
        stream("S5", "Eating", 80, -0.07),
    ]
}

fn run_dir(name: &str) -> std::path::PathBuf {
    let d = std::env::temp_dir().join(format!("blapose-lifter-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

#[test]
fn training_loss_falls_on_a_tiny_set_and_resume_is_exact() {
    let seqs = tiny_set();
    let dir = run_dir("train");
    let cfg = tiny_config(40);
    let out = train(
        &cfg,
        &seqs,
        None,
        &dir,
        false,
        "synthetic",
        &mut |_, _, _, _| {},
    )
    .unwrap();
    let loss = read_log_column(&dir.join(LOG_FILE), "train_loss_mm").unwrap();
    assert_eq!(loss.len(), 8);
    let (first, last) = (loss[0].1, loss[loss.len() - 1].1);
    assert!(last < 0.6 * first, "loss {first:.1} -> {last:.1} mm");
    let val = read_log_column(&dir.join(LOG_FILE), "val_mpjpe_flip_mm").unwrap();
    assert!(val[val.len() - 1].1 < val[0].1, "{val:?}");
    assert!(out.validation.mpjpe_flip_mm.is_finite());

    // 20 steps, then resume to 40: the same weights as 40 at once.
    let dir2 = run_dir("resume");
    train(
        &tiny_config(20),
        &seqs,
        None,
        &dir2,
        false,
        "synthetic",
        &mut |_, _, _, _| {},
    )
    .unwrap();
    let resumed = train(
        &cfg,
        &seqs,
        None,
        &dir2,
        true,
        "synthetic",
        &mut |_, _, _, _| {},
    )
    .unwrap();
    assert_eq!(resumed.steps_run, 20);
    let a = weights::load(&out.weights).unwrap();
    let b = weights::load(&resumed.weights).unwrap();
    let ta = weights::named_tensors(&a.varmap).unwrap();
    let tb = weights::named_tensors(&b.varmap).unwrap();
    assert_eq!(ta.len(), tb.len());
    for (k, v) in &ta {
        let x = v.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        let y = tb[k].flatten_all().unwrap().to_vec1::<f32>().unwrap();
        assert_eq!(x, y, "{k} differs after resume");
    }
    assert_eq!(a.metadata.arch, cfg.arch);
    assert_eq!(a.metadata.train_steps, 40);
    // A resumed run with another configuration is refused.
    let mut other = tiny_config(60);
    other.lr = 1e-2;
    assert!(train(
        &other,
        &seqs,
        None,
        &dir2,
        true,
        "synthetic",
        &mut |_, _, _, _| {}
    )
    .is_err());
    let _ = std::fs::remove_dir_all(&dir);
    let _ = std::fs::remove_dir_all(&dir2);
}

#[test]
fn temporal_training_loss_falls_centred_and_causal() {
    let seqs = tiny_set();
    for causal in [false, true] {
        let dir = run_dir(&format!("temporal-{causal}"));
        let mut cfg = tiny_config(40);
        cfg.arch = LifterArch::VideoPose(VideoPoseArch {
            filter_width: 3,
            blocks: 1,
            channels: 32,
            dropout: 0.1,
            causal,
        });
        let out = train(
            &cfg,
            &seqs,
            None,
            &dir,
            false,
            "synthetic",
            &mut |_, _, _, _| {},
        )
        .unwrap();
        let loss = read_log_column(&dir.join(LOG_FILE), "train_loss_mm").unwrap();
        let (first, last) = (loss[0].1, loss[loss.len() - 1].1);
        assert!(
            last < 0.6 * first,
            "causal={causal}: loss {first:.1} -> {last:.1} mm"
        );
        let w = weights::load(&out.weights).unwrap();
        assert_eq!(w.metadata.arch, cfg.arch);
        assert_eq!(w.net.window(), Window { frames: 9, causal });

        // The contract with the server: the file this crate writes is what
        // the serving loader reads (causal only), and it lifts the same pose.
        let served = blapose_lifters::TrainedLifter::from_file(&out.weights);
        if !causal {
            assert!(served.is_err(), "a centred lifter cannot be served online");
            let _ = std::fs::remove_dir_all(&dir);
            continue;
        }
        let served = served.unwrap();
        assert_eq!(served.name(), cfg.arch.name());
        assert_eq!(served.receptive_field(), 9);
        let mut window = served.window();
        let trial = &seqs[0].trial;
        for t in 0..9 {
            let f = &trial.input[t * 34..(t + 1) * 34];
            window.push(std::array::from_fn(|j| [f[2 * j], f[2 * j + 1]]));
        }
        let pose = served.lift(&mut window).unwrap();
        let ours = blapose_train::lifter::predict::predict_rows(
            w.net.as_ref(),
            &trial.input[..9 * 34],
            false,
        )
        .unwrap();
        for (a, b) in pose.iter().flatten().zip(ours[0].iter().flatten()) {
            assert!((a - b).abs() < 1e-4, "{a} vs {b}");
        }
        let _ = std::fs::remove_dir_all(&dir);
    }
}

#[test]
fn finetuning_starts_from_the_weights_and_lowers_the_adjusted_error() {
    let seqs = tiny_set();
    let base_dir = run_dir("ft-base");
    let base = train(
        &tiny_config(30),
        &seqs,
        None,
        &base_dir,
        false,
        "synthetic",
        &mut |_, _, _, _| {},
    )
    .unwrap();
    // Lengths 5% short of the truth, as a frozen estimator might give.
    let lengths: Vec<BoneLengths> = seqs
        .iter()
        .map(|s| bone_lengths(&s.target[0]).map(|l| 0.95 * l))
        .collect();
    let mut cfg = tiny_config(30);
    cfg.objective = Objective::Adjusted;
    cfg.init_weights = Some(base.weights.clone());
    cfg.lr = 1e-3;
    let dir = run_dir("ft");
    assert!(
        train(
            &cfg,
            &seqs,
            None,
            &dir,
            false,
            "synthetic",
            &mut |_, _, _, _| {}
        )
        .is_err(),
        "the adjusted objective without lengths is refused"
    );
    let out = train(
        &cfg,
        &seqs,
        Some(&lengths),
        &dir,
        false,
        "synthetic",
        &mut |_, _, _, _| {},
    )
    .unwrap();
    let val = read_log_column(&dir.join(LOG_FILE), "val_mpjpe_flip_mm").unwrap();
    let fresh = read_log_column(&base_dir.join(LOG_FILE), "val_mpjpe_flip_mm").unwrap();
    assert!(
        val[0].1 < fresh[0].1,
        "starts from the trained weights: {val:?} vs {fresh:?}"
    );
    assert!(
        val[val.len() - 1].1 < val[0].1,
        "adjusted error falls: {val:?}"
    );
    assert!(out.validation.mpjpe_flip_mm.is_finite());
    // Another architecture is refused.
    let mut wrong = cfg.clone();
    wrong.arch = LifterArch::Mlp(MlpArch {
        hidden: 32,
        blocks: 1,
        dropout: 0.1,
    });
    assert!(train(
        &wrong,
        &seqs,
        Some(&lengths),
        &run_dir("ft-wrong"),
        false,
        "x",
        &mut |_, _, _, _| {}
    )
    .is_err());
    let _ = std::fs::remove_dir_all(&dir);
    let _ = std::fs::remove_dir_all(&base_dir);
}

#[test]
fn flip_is_its_own_inverse() {
    let mut rng = rand::rngs::StdRng::seed_from_u64(11);
    let input: Vec<f32> = (0..3 * 34)
        .map(|_| rng.random_range(-1.0f32..1.0))
        .collect();
    assert_eq!(flip_input(&flip_input(&input)), input);
    assert_ne!(flip_input(&input), input);
    let pose: Pose =
        std::array::from_fn(|_| std::array::from_fn(|_| rng.random_range(-1.0f32..1.0)));
    assert_eq!(flip_pose(&flip_pose(&pose)), pose);

    // A mirrored sample mirrored again is the sample.
    let seqs = tiny_set();
    let plain = gather(&seqs, &[(0, 7)], Window::SINGLE_FRAME, &[false]);
    let flipped = gather(&seqs, &[(0, 7)], Window::SINGLE_FRAME, &[true]);
    assert_eq!(
        (plain.flipped.clone(), flipped.flipped.clone()),
        (vec![false], vec![true])
    );
    assert_eq!(flip_input(&flipped.inputs), plain.inputs);
    let t = seqs[0].target[7];
    assert_eq!(flipped.targets, pose_to_target(&flip_pose(&t)).to_vec());

    // Test-time flip of a mirror-equivariant prediction changes nothing,
    // and averages a non-equivariant one with its mirror image.
    let preds = vec![pose];
    assert_eq!(average_flipped(&preds, &[flip_pose(&pose)]), preds);
    let zero = [[0.0f32; 3]; 17];
    let half = average_flipped(&preds, &[zero]);
    assert_eq!(half[0][5], pose[5].map(|v| 0.5 * v));
}

#[test]
fn eval_adjust_fixture_gives_known_numbers() {
    // S9 "Walking 1": 10 frames, lifter = GT with every bone 10% long;
    // S11 "Eating": 30 frames, 20% long. Uniformly scaled bones about the
    // root scale the whole pose, so joint j's error is s|p_j|.
    let trials = vec![
        stream("S9", "Walking 1", 10, 0.1),
        stream("S11", "Eating", 30, 0.03),
    ];
    let scale = |t: &LifterSequence| if t.trial.subject == "S9" { 1.1 } else { 1.2 };
    let lift = |t: &LifterSequence| Ok(scaled(&t.target, scale(t)));
    let truth: Vec<BoneLengths> = trials.iter().map(|t| t.trial.gt).collect();
    // Online: the true lengths at every frame. Offline: 5% too long.
    let gru: Vec<Vec<BoneLengths>> = trials
        .iter()
        .map(|t| vec![t.trial.gt; t.frames()])
        .collect();
    let bigru: Vec<BoneLengths> = truth.iter().map(|l| l.map(|v| v * 1.05)).collect();
    // The constant baseline: 10% short for both subjects (same skeleton).
    assert_eq!(truth[0], truth[1]);
    let training_mean: BoneLengths = truth[0].map(|v| v * 0.9);
    let r = evaluate_lifter(
        &trials,
        &lift,
        Adjusters {
            gru: Some(&gru),
            bigru: Some(&bigru),
            training_mean: Some(&training_mean),
            motion: None,
            height: None,
        },
    )
    .unwrap();
    let norm_mm = mean_joint_norm(&base_pose()) * 1000.0;
    let len_mm = truth[0].iter().map(|&v| f64::from(v)).sum::<f64>() / 16.0 * 1000.0;
    let close = |a: f64, b: f64, what: &str| {
        assert!((a - b).abs() < 2e-3 * b.max(1.0), "{what}: {a} vs {b}")
    };
    // Mean over the two actions (not frame-weighted over trials).
    close(r.before.avg.mpjpe_mm, 0.15 * norm_mm, "MPJPE before");
    close(
        r.before.per_action["Walking"].mpjpe_mm,
        0.1 * norm_mm,
        "Walking",
    );
    close(
        r.before.per_action["Eating"].mpjpe_mm,
        0.2 * norm_mm,
        "Eating",
    );
    close(
        r.before.avg.bone_error_mm,
        0.15 * len_mm,
        "bone error before",
    );
    assert!(
        r.before.avg.p_mpjpe_mm < 1e-2,
        "P-MPJPE removes scale: {}",
        r.before.avg.p_mpjpe_mm
    );
    // MPJVE: velocity error is s times the true velocity.
    let vel_mm = |t: &LifterSequence| -> f64 {
        let mut s = 0.0;
        for k in 1..t.frames() {
            for j in 0..17 {
                let d: Vec<f64> = (0..3)
                    .map(|i| f64::from(t.target[k][j][i] - t.target[k - 1][j][i]))
                    .collect();
                s += (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
            }
        }
        s / ((t.frames() - 1) * 17) as f64 * 1000.0
    };
    close(
        r.before.avg.mpjve_mm.unwrap(),
        0.5 * (0.1 * vel_mm(&trials[0]) + 0.2 * vel_mm(&trials[1])),
        "MPJVE before",
    );
    // The true lengths recover the ground truth exactly.
    let gru_r = r.gru.as_ref().unwrap();
    for v in [
        gru_r.avg.mpjpe_mm,
        gru_r.avg.p_mpjpe_mm,
        gru_r.avg.mpjve_mm.unwrap(),
        gru_r.avg.bone_error_mm,
    ] {
        assert!(v < 1e-3, "{:?}", gru_r.avg);
    }
    // 5% long lengths: 5% of every joint distance, both actions.
    let bi = r.bigru.as_ref().unwrap();
    close(bi.avg.mpjpe_mm, 0.05 * norm_mm, "MPJPE Bi-GRU");
    close(bi.avg.bone_error_mm, 0.05 * len_mm, "bone error Bi-GRU");
    // 10% short constant lengths: 10% of every joint distance.
    let tm = r.training_mean.as_ref().unwrap();
    close(tm.avg.mpjpe_mm, 0.1 * norm_mm, "MPJPE training mean");
    close(
        tm.avg.bone_error_mm,
        0.1 * len_mm,
        "bone error training mean",
    );
    // The lifter's lengths are consistent already (10% / 20% long every
    // frame): their running median rebuilds the lifter's own poses.
    let lm = &r.lifter_median;
    close(
        lm.avg.mpjpe_mm,
        r.before.avg.mpjpe_mm,
        "MPJPE lifter median",
    );
    close(
        lm.avg.bone_error_mm,
        r.before.avg.bone_error_mm,
        "bone error lifter median",
    );
    assert_eq!((r.trials, r.frames), (2, 40));

    let mut all = BTreeMap::new();
    all.insert("mlp".to_string(), r);
    let json = serde_json::to_value(&all).unwrap();
    for m in ["before", "gru", "bigru", "training_mean", "lifter_median"] {
        assert!(json["mlp"][m]["mpjpe_mm"].is_f64(), "{m}");
        assert!(json["mlp"][m]["p_mpjpe_mm"].is_f64(), "{m}");
    }
    let md = markdown(&all);
    assert!(md.contains("| mlp | offline Bi-GRU |"), "{md}");
    assert!(
        md.contains("| mlp | baseline: constant training mean |"),
        "{md}"
    );
    assert!(
        md.contains("| mlp | baseline: lifter's own running median |"),
        "{md}"
    );
    assert!(md.contains("Walking"));
}

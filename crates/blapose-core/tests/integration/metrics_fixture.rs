//! Metric values on a small fixture against values computed independently
//! by `fixtures/metrics_reference.py` (numpy + scipy: MPJPE, N-MPJPE, MPJVE
//! and bone-length error from their definitions; P-MPJPE by numerical
//! optimisation over rotation/scale/translation, cross-checked against
//! Umeyama's closed form). The numbers below are that script's output.

use blapose_core::metrics::{
    action_name, bone_length_error, mpjpe, mpjve, n_mpjpe, p_mpjpe, pose_bone_length_error,
    ActionAggregator, BoneLengthError, MetricError, MM_PER_M,
};
use blapose_core::Pose;

/// The fixture of `metrics_reference.py`: 4 frames; frame 2's prediction is
/// mirrored (reflection fix), frame 3's is scaled by 1.2.
fn fixture() -> (Vec<Pose>, Vec<Pose>) {
    let mut gt = Vec::new();
    let mut pred = Vec::new();
    for t in 0..4 {
        let tf = t as f64;
        let mut g: Pose = [[0.0; 3]; 17];
        let mut p: Pose = [[0.0; 3]; 17];
        for j in 0..17 {
            let jf = j as f64;
            let gj = [
                (0.7 * jf + 0.3 * tf).sin() * 0.4,
                (1.3 * jf + 0.2 * tf).cos() * 0.5,
                0.1 * jf - 0.05 * tf,
            ];
            let noise = [
                0.02 * (3.0 * jf + tf).sin(),
                -0.03 * (2.0 * jf - tf).cos(),
                0.015 * (jf * tf + 1.0).sin(),
            ];
            let mut pj: [f64; 3] = std::array::from_fn(|i| gj[i] + noise[i]);
            if t == 2 {
                pj[0] = -pj[0];
            }
            if t == 3 {
                pj = pj.map(|v| v * 1.2);
            }
            g[j] = gj.map(|v| v as f32);
            p[j] = pj.map(|v| v as f32);
        }
        gt.push(g);
        pred.push(p);
    }
    (pred, gt)
}

fn close(a: f64, b: f64) {
    assert!(
        (a - b).abs() < 1e-6 * b.abs().max(1e-3),
        "{a} vs reference {b}"
    );
}

#[test]
fn metrics_match_the_independent_reference() {
    let (pred, gt) = fixture();
    close(mpjpe(&pred, &gt).unwrap(), 0.19073248049131372);
    close(p_mpjpe(&pred, &gt).unwrap(), 0.12105361556385463);
    close(n_mpjpe(&pred, &gt).unwrap(), 0.15003565425926238);
    close(mpjve(&pred, &gt).unwrap(), 0.39405182751349377);
    let reference = [
        0.05997342315957807,
        0.043278545882431796,
        0.05573015223544171,
        0.03953080917674762,
        0.03701345467724766,
        0.04225400930462375,
        0.08934320622361452,
        0.04660832456633365,
        0.05155886495691392,
        0.04283358516041081,
        0.03628417348266161,
        0.02588345856851393,
        0.06311118021381536,
        0.04526504219246988,
        0.03615940477905675,
        0.0544269559233615,
    ];
    let e = pose_bone_length_error(&pred, &gt).unwrap();
    for (a, b) in e.per_bone.iter().zip(reference) {
        close(*a, b);
    }
    close(e.mean, 0.0480784119064514);
    close(e.scaled(MM_PER_M).mean, 48.0784119064514);
}

/// Hand-computed values on f32 inputs: absolute tolerance of 1 µm.
fn near(a: f64, b: f64) {
    assert!((a - b).abs() < 1e-6, "{a} vs hand-computed {b}");
}

#[test]
fn hand_computed_small_cases() {
    // Every joint off by (3, 4, 0) mm: MPJPE 5 mm, P-MPJPE 0 (translation).
    let gt: Pose =
        std::array::from_fn(|j| [j as f32 * 0.1, (j % 3) as f32 * 0.2, (j % 5) as f32 * 0.05]);
    let pred = gt.map(|p| [p[0] + 0.003, p[1] + 0.004, p[2]]);
    near(mpjpe(&[pred], &[gt]).unwrap(), 0.005);
    assert!(p_mpjpe(&[pred], &[gt]).unwrap() < 1e-6);
    // Constant velocities that differ by (0, 0, 0.01) per frame: MPJVE 0.01.
    let seq_gt = [gt, gt, gt];
    let seq_pred = [
        gt,
        gt.map(|p| [p[0], p[1], p[2] + 0.01]),
        gt.map(|p| [p[0], p[1], p[2] + 0.02]),
    ];
    near(mpjve(&seq_pred, &seq_gt).unwrap(), 0.01);
    // Bone lengths: one bone 2 cm long, one 1 cm short, the rest exact.
    let mut l = [0.3f32; 16];
    l[2] += 0.02;
    l[12] -= 0.01;
    let e: BoneLengthError = bone_length_error(&[l], &[[0.3; 16]]).unwrap();
    near(e.per_bone[2], 0.02);
    near(e.per_bone[12], 0.01);
    near(e.mean, 0.03 / 16.0);
}

#[test]
fn bad_lengths_are_typed_errors() {
    let (pred, gt) = fixture();
    assert_eq!(
        mpjpe(&pred[..3], &gt),
        Err(MetricError::LengthMismatch { pred: 3, gt: 4 })
    );
    assert_eq!(
        p_mpjpe(&[], &[]),
        Err(MetricError::TooShort { needed: 1, got: 0 })
    );
    assert_eq!(
        mpjve(&pred[..1], &gt[..1]),
        Err(MetricError::TooShort { needed: 2, got: 1 })
    );
    assert!(bone_length_error(&[], &[]).is_err());
}

#[test]
fn degenerate_procrustes_is_defined() {
    let gt: Pose = std::array::from_fn(|j| [j as f32 * 0.1, 0.2, -0.1 * j as f32]);
    let collapsed: Pose = [[1.0, 2.0, 3.0]; 17];
    let e = p_mpjpe(&[collapsed], &[gt]).unwrap();
    assert!(e.is_finite() && e > 0.0);
    // a collapsed ground truth: everything aligns to the point
    assert!(p_mpjpe(&[gt], &[collapsed]).unwrap() < 1e-6);
    assert_eq!(
        n_mpjpe(&[[[0.0; 3]; 17]], &[gt]).unwrap(),
        mpjpe(&[[[0.0; 3]; 17]], &[gt]).unwrap()
    );
}

#[test]
fn action_aggregation_averages_per_action_then_over_actions() {
    assert_eq!(action_name("Walking 1"), "Walking");
    assert_eq!(action_name("Walking"), "Walking");
    assert_eq!(action_name("SittingDown 2"), "SittingDown");
    assert_eq!(action_name("S9/Walking 1"), "Walking");
    assert_eq!(action_name("S11/WalkDog 1/54138969"), "WalkDog");
    assert_eq!(action_name("Photo"), "Photo");
    let mut agg = ActionAggregator::new();
    agg.add_frames("S9/Walking 1", &[1.0, 1.0, 1.0]); // 3 frames at 1
    agg.add_frames("Walking", &[5.0]); // 1 frame at 5 -> Walking = 8/4 = 2
    agg.add_mean("Eating 2", 4.0, 10); // Eating = 4
    agg.add_frames("Posing", &[]); // no frames: left out
    assert_eq!(
        agg.per_action(),
        vec![("Eating".to_owned(), 4.0), ("Walking".to_owned(), 2.0)]
    );
    assert_eq!(agg.mean_over_actions(), Some(3.0));
    assert_eq!(ActionAggregator::new().mean_over_actions(), None);
}

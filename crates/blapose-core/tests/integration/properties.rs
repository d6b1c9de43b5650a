//! Property tests for the geometry: bones, flips, camera and metrics.

use blapose_core::bones::{
    adjust_pose, adjust_pose_lenient, bone_lengths, decompose, rebuild, BoneError, MIN_BONE_LENGTH,
};
use blapose_core::camera::{denormalize_screen, normalize_screen, Camera};
use blapose_core::metrics::{mpjpe, p_mpjpe, procrustes_align};
use blapose_core::pose::{flip_keypoints_normalized, flip_keypoints_pixels, flip_pose};
use blapose_core::{BoneDirections, BoneLengths, Keypoints2d, Pose, NUM_BONES};
use nalgebra::{Rotation3, Vector3};
use proptest::prelude::*;

fn coord() -> impl Strategy<Value = f32> {
    -2.0f32..2.0
}

fn any_pose() -> impl Strategy<Value = Pose> {
    prop::array::uniform17(prop::array::uniform3(coord()))
}

fn unit_dir() -> impl Strategy<Value = [f32; 3]> {
    prop::array::uniform3(-1.0f32..1.0)
        .prop_filter("non-degenerate direction", |v| {
            v.iter().map(|x| x * x).sum::<f32>() > 0.01
        })
        .prop_map(|v| {
            let n = v.iter().map(|x| x * x).sum::<f32>().sqrt();
            v.map(|x| x / n)
        })
}

fn lengths(lo: f32, hi: f32) -> impl Strategy<Value = BoneLengths> {
    prop::array::uniform16(lo..hi)
}

/// A pose built from a root, directions and lengths: bones are never
/// degenerate, like real skeletons.
fn skeleton_pose() -> impl Strategy<Value = (Pose, BoneDirections, BoneLengths)> {
    (
        prop::array::uniform3(coord()),
        prop::array::uniform16(unit_dir()),
        lengths(0.05, 0.6),
    )
        .prop_map(|(root, dirs, l)| (rebuild(root, &dirs, &l), dirs, l))
}

/// Values that break naive geometry code: NaN, infinities, huge, tiny,
/// negative, or any bit pattern at all.
fn special() -> impl Strategy<Value = f32> {
    prop_oneof![
        Just(f32::NAN),
        Just(f32::INFINITY),
        Just(f32::NEG_INFINITY),
        Just(f32::MAX),
        Just(-1e30f32),
        Just(1e-30f32),
        Just(-0.5f32),
        Just(0.0f32),
        prop::num::f32::ANY,
    ]
}

fn max_diff(a: &Pose, b: &Pose) -> f32 {
    a.iter()
        .flatten()
        .zip(b.iter().flatten())
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(512))]

    #[test]
    fn decompose_then_rebuild_is_the_identity((pose, dirs, l) in skeleton_pose()) {
        let (l2, d2) = decompose(&pose).unwrap();
        let back = rebuild(pose[0], &d2, &l2);
        prop_assert!(max_diff(&back, &pose) < 1e-5, "diff {}", max_diff(&back, &pose));
        for b in 0..NUM_BONES {
            prop_assert!((l2[b] - l[b]).abs() < 1e-5);
            for i in 0..3 {
                prop_assert!((d2[b][i] - dirs[b][i]).abs() < 1e-4);
            }
        }
    }

    #[test]
    fn random_joint_positions_round_trip_too(pose in any_pose()) {
        match decompose(&pose) {
            Ok((l, d)) => prop_assert!(max_diff(&rebuild(pose[0], &d, &l), &pose) < 1e-5),
            Err(e) => prop_assert!(matches!(e, BoneError::ZeroLengthBone { .. }), "{e}"),
        }
    }

    #[test]
    fn replacing_lengths_keeps_directions_and_root((pose, dirs, _) in skeleton_pose(), target in lengths(0.01, 0.8)) {
        let adjusted = adjust_pose(&pose, &target).unwrap();
        prop_assert_eq!(adjusted[0], pose[0]);
        let (l, d) = decompose(&adjusted).unwrap();
        for b in 0..NUM_BONES {
            prop_assert!((l[b] - target[b]).abs() < 1e-5, "bone {} length {} vs {}", b, l[b], target[b]);
            for i in 0..3 {
                prop_assert!((d[b][i] - dirs[b][i]).abs() < 1e-4, "bone {} direction", b);
            }
        }
        // adjusting to the pose's own lengths is the identity
        let same = adjust_pose(&pose, &bone_lengths(&pose)).unwrap();
        prop_assert!(max_diff(&same, &pose) < 1e-5);
    }

    #[test]
    fn nan_never_leaks_out(
        (mut pose, _, _) in skeleton_pose(),
        mut target in lengths(0.0, 0.8),
        pose_hits in prop::collection::vec((0usize..51, special()), 0..3),
        length_hits in prop::collection::vec((0usize..16, special()), 0..5),
        collapse in prop::option::of(1usize..17),
    ) {
        for (i, v) in pose_hits {
            pose[i / 3][i % 3] = v;
        }
        for (i, v) in length_hits {
            target[i] = v;
        }
        if let Some(j) = collapse {
            pose[j] = pose[blapose_core::skeleton::PARENTS[j]];
        }
        for result in [adjust_pose(&pose, &target), adjust_pose_lenient(&pose, &target)] {
            match result {
                Ok(p) => prop_assert!(p.iter().flatten().all(|v| v.is_finite()), "{:?}", p),
                Err(e) => prop_assert!(!e.to_string().is_empty()),
            }
        }
        if let Ok((l, d)) = decompose(&pose) {
            prop_assert!(l.iter().all(|v| v.is_finite() && *v >= MIN_BONE_LENGTH));
            prop_assert!(d.iter().flatten().all(|v| v.is_finite()));
        }
    }

    #[test]
    fn huge_lengths_overflow_to_an_error_not_infinity(
        (pose, _, _) in skeleton_pose(),
        target in prop::array::uniform16(prop_oneof![Just(0.3f32), Just(1e38f32), Just(f32::MAX)]),
    ) {
        match adjust_pose(&pose, &target) {
            Ok(p) => prop_assert!(p.iter().flatten().all(|v| v.is_finite())),
            Err(e) => prop_assert_eq!(e, BoneError::Overflow),
        }
    }

    #[test]
    fn lenient_adjustment_always_succeeds_on_finite_input(
        (mut pose, _, _) in skeleton_pose(),
        collapse in prop::collection::vec(1usize..17, 0..4),
        target in lengths(0.0, 0.8),
    ) {
        for j in collapse {
            pose[j] = pose[blapose_core::skeleton::PARENTS[j]];
        }
        let p = adjust_pose_lenient(&pose, &target).unwrap();
        prop_assert!(p.iter().flatten().all(|v| v.is_finite()));
    }

    #[test]
    fn p_mpjpe_is_zero_under_similarity_transforms(
        pose in any_pose(),
        axis in unit_dir(),
        angle in -3.1f32..3.1,
        scale in 0.3f32..3.0,
        shift in prop::array::uniform3(-3.0f32..3.0),
    ) {
        let r = Rotation3::from_scaled_axis(Vector3::from(axis) * angle);
        let moved: Pose = pose.map(|p| {
            let q = r * Vector3::from(p) * scale;
            [q.x + shift[0], q.y + shift[1], q.z + shift[2]]
        });
        let e = p_mpjpe(&[moved], &[pose]).unwrap();
        prop_assert!(e < 1e-4, "P-MPJPE {} after a similarity transform", e);
    }

    /// Procrustes minimises the *squared* error, so the root-mean-square
    /// joint error never grows. (The mean distance itself can grow for an
    /// outlier-dominated prediction; see `p_mpjpe_can_exceed_mpjpe_with_an_outlier`.)
    #[test]
    fn procrustes_never_increases_squared_error(pred in any_pose(), gt in any_pose()) {
        let aligned = procrustes_align(&pred, &gt);
        let sq = |p: &[[f64; 3]; 17]| -> f64 {
            p.iter().zip(&gt).map(|(a, b)| (0..3).map(|i| (a[i] - b[i] as f64).powi(2)).sum::<f64>()).sum()
        };
        let before = sq(&pred.map(|p| p.map(f64::from)));
        prop_assert!(sq(&aligned) <= before * (1.0 + 1e-9) + 1e-12);
    }

    /// For a lifter-like prediction (a rigidly moved ground truth plus noise
    /// on every joint) P-MPJPE never exceeds MPJPE.
    #[test]
    fn p_mpjpe_does_not_exceed_mpjpe_for_noisy_predictions(
        gt in any_pose(),
        noise in prop::array::uniform17(prop::array::uniform3(-0.05f32..0.05)),
        axis in unit_dir(),
        angle in 0.2f32..3.0,
        scale in 0.7f32..1.3,
    ) {
        let r = Rotation3::from_scaled_axis(Vector3::from(axis) * angle);
        let pred: Pose = std::array::from_fn(|j| {
            let q = r * Vector3::from(gt[j]) * scale;
            [q.x + noise[j][0], q.y + noise[j][1], q.z + noise[j][2]]
        });
        let p = p_mpjpe(&[pred], &[gt]).unwrap();
        let m = mpjpe(&[pred], &[gt]).unwrap();
        prop_assert!(p <= m, "P-MPJPE {} > MPJPE {}", p, m);
    }

    #[test]
    fn flips_are_involutions(pose in any_pose(), kp in prop::array::uniform17(prop::array::uniform2(0.0f32..2000.0)), w in 1u32..4000) {
        prop_assert_eq!(flip_pose(&flip_pose(&pose)), pose);
        let kn: Keypoints2d = kp.map(|p| [p[0] / 1000.0 - 1.0, p[1] / 1000.0 - 1.0]);
        prop_assert_eq!(flip_keypoints_normalized(&flip_keypoints_normalized(&kn)), kn);
        let twice = flip_keypoints_pixels(&flip_keypoints_pixels(&kp, w), w);
        for j in 0..17 {
            prop_assert!((twice[j][0] - kp[j][0]).abs() < 1e-3 && twice[j][1] == kp[j][1]);
        }
    }

    #[test]
    fn camera_flip_is_an_involution_and_mirrors_projections(
        cx in 400.0f64..600.0, p1 in -0.01f64..0.01, k1 in -0.3f64..0.3,
        point in prop::array::uniform3(-1.0f64..1.0),
    ) {
        let cam = Camera {
            id: "c".into(),
            rotation: [[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]],
            center: [0.0, -5.0, 1.0],
            focal: [1100.0, 1120.0],
            principal: [cx, 505.0],
            radial: [k1, 0.1, 0.0],
            tangential: [p1, 0.001],
            width: 1000,
            height: 1002,
        };
        let twice = cam.flipped().flipped();
        prop_assert!((twice.principal[0] - cx).abs() < 1e-9 && twice.tangential == cam.tangential && twice.rotation == cam.rotation);
        let a = cam.project_world_to_pixels(point);
        let b = cam.flipped().project_world_to_pixels(point);
        prop_assert!((b[0] - (1000.0 - a[0])).abs() < 1e-6 && (b[1] - a[1]).abs() < 1e-6);
    }

    #[test]
    fn normalized_coordinates_round_trip(x in -500.0f32..2500.0, y in -500.0f32..2500.0, w in 100u32..4000, h in 100u32..4000) {
        let n = normalize_screen([x, y], w, h);
        let back = denormalize_screen(n, w, h);
        prop_assert!((back[0] - x).abs() < 1e-2 && (back[1] - y).abs() < 1e-2);
    }

    #[test]
    fn normalized_projection_equals_normalized_pixels(point in prop::array::uniform3(-1.5f64..1.5), z in 2.0f64..8.0) {
        let cam = Camera {
            id: "c".into(),
            rotation: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            center: [0.0; 3],
            focal: [1145.0, 1143.8],
            principal: [512.5, 515.4],
            radial: [-0.207, 0.248, -0.003],
            tangential: [-0.001, -0.0014],
            width: 1000,
            height: 1002,
        };
        let p = [point[0], point[1], z];
        let px = cam.project_camera_to_pixels(p).map(|v| v as f32);
        let n = normalize_screen(px, cam.width, cam.height);
        let direct = cam.normalized_intrinsics().project(p.map(|v| v as f32));
        prop_assert!((n[0] - direct[0]).abs() < 2e-5 && (n[1] - direct[1]).abs() < 2e-5);
    }
}

#[test]
fn p_mpjpe_can_exceed_mpjpe_with_an_outlier() {
    // The "P-MPJPE never exceeds MPJPE" is true for the squared
    // error Procrustes minimises, not for the mean distance: one joint off
    // by 1 m and 16 exact joints give MPJPE = 1/17 m, but the least-squares
    // alignment spreads the error over all joints.
    let gt: Pose = std::array::from_fn(|j| {
        [
            (j as f32 * 0.37).sin(),
            (j as f32 * 0.71).cos(),
            j as f32 * 0.05,
        ]
    });
    let mut pred = gt;
    pred[16][0] += 1.0;
    let m = mpjpe(&[pred], &[gt]).unwrap();
    let p = p_mpjpe(&[pred], &[gt]).unwrap();
    assert!((m - 1.0 / 17.0).abs() < 1e-6);
    assert!(p > m, "P-MPJPE {p} vs MPJPE {m}");
}

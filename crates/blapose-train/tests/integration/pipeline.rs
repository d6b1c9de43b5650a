//! The augmentation pipeline on the real training data (skipped when
//! ../shared/data is absent): length strategies, the ANSUR calibration's
//! isolation from test subjects, flips and determinism.

#![allow(clippy::needless_range_loop)]

use std::path::PathBuf;
use std::sync::{Arc, OnceLock};

use blapose_core::skeleton::{NUM_BONES, SYMMETRIC_BONE_PAIRS};
use blapose_data::h36m::{H36m, Parts, ALL_SUBJECTS};
use blapose_data::test_data_root;
use blapose_train::ansur::{load_population, AnsurPopulation};
use blapose_train::dataset::TrainingSet;
use blapose_train::lengths::{LengthSampler, LengthStrategy, TrainingLengthStats};
use blapose_train::noise::NoiseKind;
use blapose_train::synth::{flip_input, sample_rng, SynthConfig, SynthSource, WIDE_CAMERA};

struct Fixture {
    root: PathBuf,
    set: TrainingSet,
    stats: TrainingLengthStats,
    pop: AnsurPopulation,
}

fn fixture() -> Option<&'static Fixture> {
    static F: OnceLock<Option<Fixture>> = OnceLock::new();
    F.get_or_init(|| {
        let root = test_data_root("h36m/poses_3d.npz", "pipeline tests")?;
        test_data_root("ansur2/ANSUR_II_MALE_Public.csv", "pipeline tests")?;
        let set = TrainingSet::load(&root).expect("training set loads");
        let stats = TrainingLengthStats::from_training(&set.lengths_list()).unwrap();
        let pop = load_population(&root, &stats).unwrap();
        Some(Fixture {
            root,
            set,
            stats,
            pop,
        })
    })
    .as_ref()
}

fn source(f: &Fixture, strategy: LengthStrategy) -> SynthSource {
    let pop = (strategy == LengthStrategy::Ansur).then(|| f.pop.clone());
    let sampler = LengthSampler::new(strategy, f.stats.clone(), pop).unwrap();
    SynthSource::new(f.set.sequences.clone(), f.set.residuals.clone(), sampler).unwrap()
}

#[test]
fn training_set_holds_training_subjects_only() {
    let Some(f) = fixture() else { return };
    let subjects: Vec<&str> = f.set.subject_lengths.keys().map(String::as_str).collect();
    assert_eq!(subjects, ["S1", "S5", "S6", "S7", "S8"]);
    assert!(f
        .set
        .sequences
        .iter()
        .all(|s| !["S9", "S11"].contains(&s.subject.as_str())));
    assert!(f
        .set
        .real_sh
        .iter()
        .all(|s| !["S9", "S11"].contains(&s.subject.as_str())));
    assert!(f.set.residuals.frames() > 100_000);
}

#[test]
fn sampled_lengths_are_symmetric_and_human() {
    let Some(f) = fixture() else { return };
    for strategy in LengthStrategy::ALL {
        let src = source(f, strategy);
        let mut rng = sample_rng(1, 2, 3);
        for i in 0..400 {
            let subject = &f.set.sequences[i % f.set.sequences.len()].lengths;
            let l = src.sampler().sample(subject, &mut rng);
            for &(r, le) in &SYMMETRIC_BONE_PAIRS {
                assert_eq!(l[r], l[le], "{strategy}: pair ({r},{le}) differs");
            }
            for b in 0..NUM_BONES {
                let ratio = l[b] / f.stats.mean[b];
                assert!(
                    (0.5..=1.6).contains(&ratio),
                    "{strategy}: bone {b} is {} m ({ratio:.2} x mean)",
                    l[b]
                );
            }
            // Absolute sanity: thigh 0.25-0.7 m, forearm 0.15-0.4 m.
            assert!(
                (0.25..0.7).contains(&l[1]) && (0.15..0.4).contains(&l[12]),
                "{strategy}: {l:?}"
            );
        }
    }
}

#[test]
fn ansur_population_is_aligned_and_correlated() {
    let Some(f) = fixture() else { return };
    let (mean, std) = f.pop.moments();
    for b in 0..NUM_BONES {
        assert!(
            (mean[b] - f.stats.mean[b]).abs() < 1e-4,
            "bone {b} mean not aligned"
        );
    }
    assert!(f.pop.len() > 6000);
    assert!(std[1] > 0.01, "thigh varies");
    // Correlation thigh / forearm across people is clearly positive.
    let p = f.pop.people();
    let n = p.len() as f64;
    let (mx, my) = (mean[1] as f64, mean[12] as f64);
    let cov = p
        .iter()
        .map(|l| (l[1] as f64 - mx) * (l[12] as f64 - my))
        .sum::<f64>()
        / n;
    let corr = cov / (std[1] as f64 * std[12] as f64);
    assert!(corr > 0.3, "thigh/forearm correlation {corr}");
}

/// The calibration depends on the training subjects and not on the test
/// subjects, even when the loaded data contains them.
#[test]
fn calibration_sees_training_subjects_only() {
    let Some(f) = fixture() else { return };
    let mut h = H36m::load(&f.root, &ALL_SUBJECTS, Parts::POSES).unwrap();
    let build = |h: &H36m| -> (TrainingLengthStats, AnsurPopulation) {
        let set = TrainingSet::from_h36m(h).unwrap();
        let stats = TrainingLengthStats::from_training(&set.lengths_list()).unwrap();
        let pop = load_population(&f.root, &stats).unwrap();
        (stats, pop)
    };
    let (s0, p0) = build(&h);
    assert_eq!(s0, f.stats, "S9/S11 in the loaded data change nothing");
    let scale = |h: &mut H36m, subject: &str| {
        for poses in h.poses.get_mut(subject).unwrap().values_mut() {
            for p in poses.iter_mut() {
                for j in p.iter_mut() {
                    *j = j.map(|v| v * 1.1);
                }
            }
        }
    };
    scale(&mut h, "S9");
    let (s1, p1) = build(&h);
    assert_eq!(s1, s0, "changing S9 changed the training statistics");
    assert_eq!(p1, p0, "changing S9 changed the ANSUR calibration");
    scale(&mut h, "S1");
    let (s2, p2) = build(&h);
    assert_ne!(s2, s0, "changing S1 must change the statistics");
    assert_ne!(
        p2.scale, p0.scale,
        "changing S1 must change the calibration"
    );
}

#[test]
fn flip_is_consistent() {
    let Some(f) = fixture() else { return };
    let src = source(f, LengthStrategy::Ansur);
    for noise in [NoiseKind::None, NoiseKind::Gaussian, NoiseKind::Residual] {
        let base = SynthConfig {
            seq_len: 16,
            noise,
            ..Default::default()
        };
        let plain = src.sample(
            &SynthConfig {
                flip_prob: 0.0,
                ..base
            },
            &mut sample_rng(5, 6, 7),
        );
        let flipped = src.sample(
            &SynthConfig {
                flip_prob: 1.0,
                ..base
            },
            &mut sample_rng(5, 6, 7),
        );
        assert!(!plain.flipped && flipped.flipped);
        assert_eq!(plain.target, flipped.target, "a flip keeps the targets");
        assert_eq!(
            flip_input(&plain.input),
            flipped.input,
            "{noise}: flipped sample is the mirrored sample"
        );
        assert_eq!(
            flip_input(&flip_input(&plain.input)),
            plain.input,
            "flip twice is the identity"
        );
    }
}

#[test]
fn floor_contact_moves_only_resized_people() {
    let Some(f) = fixture() else { return };
    let at = |strategy: LengthStrategy, floor_contact: bool| {
        let cfg = SynthConfig {
            seq_len: 16,
            floor_contact,
            ..Default::default()
        };
        source(f, strategy)
            .sample(&cfg, &mut sample_rng(8, 1, 2))
            .input
    };
    let max_change = |strategy: LengthStrategy| {
        let (plain, grounded) = (at(strategy, false), at(strategy, true));
        plain
            .iter()
            .zip(&grounded)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0f32, f32::max)
    };
    // `true` draws the subject's lengths (up to float rounding), which
    // already stand on the floor.
    let own = max_change(LengthStrategy::True);
    assert!(own < 1e-5, "own lengths moved by {own}");
    let drawn = max_change(LengthStrategy::Ansur);
    assert!(
        drawn > 1e-3,
        "drawn lengths are lifted onto the floor ({drawn})"
    );
}

#[test]
fn turned_windows_stay_in_the_picture_and_keep_their_lengths() {
    let Some(f) = fixture() else { return };
    let src = source(f, LengthStrategy::Ansur);
    let draw = |random_yaw: bool, i: u64| {
        let cfg = SynthConfig {
            seq_len: 32,
            random_yaw,
            ..Default::default()
        };
        src.sample(&cfg, &mut sample_rng(11, 0, i))
    };
    let mut inside = 0usize;
    let mut points = 0usize;
    let mut moved = 0usize;
    for i in 0..64 {
        let (plain, turned) = (draw(false, i), draw(true, i));
        assert_eq!(plain.target, turned.target, "the drawn body is the same");
        moved += usize::from(plain.input != turned.input);
        points += turned.input.len() / 2;
        inside += turned
            .input
            .chunks_exact(2)
            .filter(|p| p[0].abs() <= 1.1 && p[1].abs() <= 1.1)
            .count();
    }
    assert!(moved > 48, "most windows are turned ({moved} of 64)");
    assert!(inside as f64 > 0.99 * points as f64, "{inside} of {points}");
}

#[test]
fn a_camera_subset_draws_through_those_cameras_only() {
    let Some(f) = fixture() else { return };
    let cfg = SynthConfig {
        seq_len: 8,
        ..Default::default()
    };
    let all = source(f, LengthStrategy::Ansur);
    let one = source(f, LengthStrategy::Ansur)
        .with_cameras(&["58860488".to_string()])
        .unwrap();
    let camera_of = |src: &SynthSource, i: u64| {
        let s = src.sample(&cfg, &mut sample_rng(5, 0, i));
        src.sequences()[s.sequence].cameras[s.camera].id.clone()
    };
    let seen: std::collections::BTreeSet<String> = (0..64).map(|i| camera_of(&all, i)).collect();
    assert_eq!(seen.len(), 4, "all four cameras by default: {seen:?}");
    assert!((0..64).all(|i| camera_of(&one, i) == "58860488"));
    // An empty subset is every camera, drawn exactly as without one.
    let reset = source(f, LengthStrategy::Ansur).with_cameras(&[]).unwrap();
    assert_eq!(
        reset.sample(&cfg, &mut sample_rng(5, 0, 3)),
        all.sample(&cfg, &mut sample_rng(5, 0, 3))
    );
    assert!(source(f, LengthStrategy::Ansur)
        .with_cameras(&["12345678".to_string()])
        .is_err());
}

#[test]
fn wide_camera_samples_frame_the_person_and_floor_scale_by_their_camera() {
    use blapose_core::level::{MIN_FLOOR_DROP, REFERENCE_CAMERA_HEIGHT};
    let Some(f) = fixture() else { return };
    let src = source(f, LengthStrategy::Ansur);
    let plain = SynthConfig {
        seq_len: 16,
        wide_cameras: 1.0,
        flip_prob: 0.0,
        ..Default::default()
    };
    let rectified = SynthConfig {
        rectify: true,
        ..plain
    };
    let floor = SynthConfig {
        floor_scaled: true,
        ..rectified
    };
    let mut wide = 0;
    let mut heights = Vec::new();
    for i in 0..64 {
        let p = src.sample(&plain, &mut sample_rng(11, 0, i));
        let r = src.sample(&rectified, &mut sample_rng(11, 0, i));
        let fl = src.sample(&floor, &mut sample_rng(11, 0, i));
        assert_eq!(p.target, r.target);
        assert_eq!(fl.target, r.target);
        // Each floor-scaled frame is the rectified one times the camera
        // height over 1.56 m over the lowest joint's drop: one camera
        // height for every frame of the sample.
        let per_frame: Vec<f32> = r
            .input
            .chunks_exact(34)
            .zip(fl.input.chunks_exact(34))
            .map(|(a, b)| {
                let drop = (0..17)
                    .map(|j| a[2 * j + 1])
                    .fold(f32::MIN, f32::max)
                    .max(MIN_FLOOR_DROP as f32);
                let j = (0..34)
                    .max_by(|&x, &y| a[x].abs().total_cmp(&a[y].abs()))
                    .unwrap();
                b[j] / a[j] * drop * REFERENCE_CAMERA_HEIGHT as f32
            })
            .collect();
        let height = per_frame[0];
        for h in &per_frame {
            assert!((h - height).abs() <= 1e-4 * height, "{h} vs {height}");
        }
        if p.camera != WIDE_CAMERA {
            continue;
        }
        wide += 1;
        // In the picture (normalized: |x| <= 1), up to detector noise.
        assert!(p.input.iter().all(|v| v.is_finite() && v.abs() < 1.2));
        assert_ne!(p.input, r.input, "rectifying a tilted camera moves points");
        // A camera 0.5-3 m above the floor.
        assert!((0.499..=3.001).contains(&height), "{height}");
        heights.push(height);
    }
    assert!(wide >= 58, "only {wide} of 64 samples got a wide camera");
    let spread = heights.iter().cloned().fold(f32::MIN, f32::max)
        - heights.iter().cloned().fold(f32::MAX, f32::min);
    assert!(spread > 1.0, "camera heights barely vary: {spread}");
    let bad = SynthConfig {
        wide_cameras: 1.5,
        ..plain
    };
    assert!(bad.validate().is_err());
}

#[test]
fn samples_are_plausible_and_deterministic() {
    let Some(f) = fixture() else { return };
    let src = Arc::new(source(f, LengthStrategy::Uniform));
    let cfg = SynthConfig {
        seq_len: 32,
        ..Default::default()
    };
    let one = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap();
    let two = rayon::ThreadPoolBuilder::new()
        .num_threads(2)
        .build()
        .unwrap();
    let a = one.install(|| src.batch(&cfg, 9, 4, 24));
    let b = two.install(|| src.batch(&cfg, 9, 4, 24));
    assert_eq!(a, b, "batches do not depend on the thread count");
    assert_ne!(a, src.batch(&cfg, 9, 5, 24), "different steps differ");
    // In (or near) the image: normalized x within about [-1, 1].
    let inside = a
        .inputs
        .chunks_exact(2)
        .filter(|p| p[0].abs() <= 1.1 && p[1].abs() <= 1.1)
        .count();
    assert!(inside as f64 > 0.99 * (a.inputs.len() / 2) as f64);
    // Strides cover 25-60 fps.
    let mut rng = sample_rng(1, 1, 1);
    let strides: Vec<f32> = (0..200)
        .map(|_| src.sample(&cfg, &mut rng).stride)
        .collect();
    assert!(strides
        .iter()
        .all(|&s| (50.0 / 60.0 - 1e-6..=2.0).contains(&s)));
    assert!(strides.iter().any(|&s| s < 1.0) && strides.iter().any(|&s| s > 1.8));
}

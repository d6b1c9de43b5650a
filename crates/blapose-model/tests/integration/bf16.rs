//! The bf16 path (`Precision::Bf16`: bf16 weights and matrix inputs on
//! AVX512-BF16 or AMX, f32 accumulation and state) against the f32 engines.
//!
//! On a CPU without the units each test prints which feature is missing and
//! passes; on one that has them every test runs. Under `CI=true` a CPU that
//! reports a unit the process then cannot use (AMX refused by the OS) fails
//! instead of skipping.

use std::path::PathBuf;

use blapose_model::fast::Bf16Unit;
use blapose_model::weights;
use blapose_model::{
    EngineOptions, LoadedWeights, ModelError, ModelKind, OfflineBiGruEngine, OnlineGruEngine,
    Precision, INPUT_DIM, OUTPUT_DIM, STATE_DIM,
};
use rand::{rngs::StdRng, Rng, SeedableRng};

/// The bf16 units this process can run; prints why a unit is skipped.
fn units() -> Vec<Bf16Unit> {
    let weights = LoadedWeights::random(ModelKind::Gru, 1).unwrap();
    let mut out = Vec::new();
    for unit in Bf16Unit::ALL {
        if let Some(missing) = unit.missing_feature() {
            eprintln!("skipping bf16 on {unit}: this CPU lacks {missing}");
            continue;
        }
        match OnlineGruEngine::with_options(&weights, opts(1, Some(unit))) {
            Ok(_) => out.push(unit),
            Err(e) => {
                let ci = std::env::var("CI").is_ok_and(|v| v == "true");
                assert!(!ci, "the CPU has {unit} but it cannot be used: {e}");
                eprintln!("skipping bf16 on {unit}: {e}");
            }
        }
    }
    out
}

fn opts(threads: usize, unit: Option<Bf16Unit>) -> EngineOptions {
    EngineOptions {
        precision: Precision::Bf16,
        bf16_unit: unit,
        ..EngineOptions::threads(threads)
    }
}

fn random_frames(n: usize, seed: u64) -> Vec<f32> {
    let mut rng = StdRng::seed_from_u64(seed);
    (0..n * INPUT_DIM)
        .map(|_| rng.random_range(-1.0f32..1.0))
        .collect()
}

/// `steps` steps of `batch` sessions (frames `[t][b][34]`); outputs
/// `[t][b][16]` and the final states.
fn run(engine: &OnlineGruEngine, frames: &[f32], batch: usize) -> (Vec<f32>, Vec<f32>) {
    let steps = frames.len() / (batch * INPUT_DIM);
    let mut hidden = vec![0.0; batch * STATE_DIM];
    let mut scratch = engine.scratch(batch);
    let mut y = vec![0.0; batch * OUTPUT_DIM];
    let mut outs = Vec::with_capacity(steps * batch * OUTPUT_DIM);
    for x in frames.chunks_exact(batch * INPUT_DIM) {
        engine.step(x, &mut hidden, &mut y, &mut scratch).unwrap();
        outs.extend_from_slice(&y);
    }
    (outs, hidden)
}

fn max_abs_diff(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

/// Bound on the outputs' difference from f32 over 200 steps of random
/// weights and inputs (outputs up to ~0.4): bf16 keeps 8 significant bits
/// of each weight and product input (relative error 2^-9 each, largely
/// averaging out over 768-term sums); observed below 1e-4 online, 1e-5
/// offline.
const RANDOM_TOLERANCE: f32 = 1e-3;

#[test]
fn bf16_online_step_stays_close_to_f32_at_every_batch_size() {
    let units = units();
    if units.is_empty() {
        return;
    }
    let weights = LoadedWeights::random(ModelKind::Gru, 3).unwrap();
    let f32_engine = OnlineGruEngine::new(&weights, 1).unwrap();
    for batch in [1, 3, 8, 9, 16, 17, 40] {
        let frames = random_frames(200 * batch, 100 + batch as u64);
        let (want, _) = run(&f32_engine, &frames, batch);
        let scale = want.iter().fold(0.0f32, |m, v| m.max(v.abs()));
        for &unit in &units {
            for threads in [1, 2] {
                let engine =
                    OnlineGruEngine::with_options(&weights, opts(threads, Some(unit))).unwrap();
                assert_eq!(engine.precision(), Precision::Bf16);
                assert_eq!(engine.bf16_unit(), Some(unit));
                let (got, _) = run(&engine, &frames, batch);
                let err = max_abs_diff(&got, &want);
                eprintln!("bf16 {unit} batch {batch} threads {threads}: max error {err:.2e} (outputs up to {scale:.2})");
                assert!(err < RANDOM_TOLERANCE, "{unit} batch {batch}: {err}");
            }
        }
    }
}

#[test]
fn bf16_steps_are_bit_exact_across_threads_and_batch_neighbours() {
    let units = units();
    if units.is_empty() {
        return;
    }
    let weights = LoadedWeights::random(ModelKind::Gru, 5).unwrap();
    let batch = 37;
    let frames = random_frames(30 * batch, 9);
    for &unit in &units {
        let one = OnlineGruEngine::with_options(&weights, opts(1, Some(unit))).unwrap();
        let two = OnlineGruEngine::with_options(&weights, opts(2, Some(unit))).unwrap();
        let (a, ha) = run(&one, &frames, batch);
        let (b, hb) = run(&two, &frames, batch);
        assert_eq!(a, b, "{unit}: outputs depend on the thread count");
        assert_eq!(ha, hb, "{unit}: states depend on the thread count");
        if unit != Bf16Unit::Amx {
            continue;
        }
        // AMX computes each row on its own: the sessions of rows 20 and 0 stepped as a
        // batch of two match their rows in the batch of 37, bit for bit
        // (a batch of one runs on vdpbf16ps instead: kernel::AMX_MIN_ROWS).
        let pick = |v: &[f32], width: usize, rows: [usize; 2]| -> Vec<f32> {
            v.chunks_exact(batch * width)
                .flat_map(|step| {
                    rows.iter()
                        .flat_map(move |&r| &step[r * width..(r + 1) * width])
                })
                .copied()
                .collect()
        };
        let pair = pick(&frames, INPUT_DIM, [20, 0]);
        let (y2, h2) = run(&one, &pair, 2);
        assert_eq!(
            y2,
            pick(&a, OUTPUT_DIM, [20, 0]),
            "amx: outputs depend on the batch"
        );
        assert_eq!(
            h2,
            pick(&ha, STATE_DIM, [20, 0]),
            "amx: states depend on the batch"
        );
    }
}

#[test]
fn amx_and_avx512_bf16_agree_closely() {
    let units = units();
    if units.len() < 2 {
        eprintln!("skipping: needs both bf16 units (have {units:?})");
        return;
    }
    let weights = LoadedWeights::random(ModelKind::Gru, 8).unwrap();
    let batch = 24;
    let frames = random_frames(100 * batch, 4);
    let a = OnlineGruEngine::with_options(&weights, opts(1, Some(Bf16Unit::Amx))).unwrap();
    let b = OnlineGruEngine::with_options(&weights, opts(1, Some(Bf16Unit::Avx512Bf16))).unwrap();
    let err = max_abs_diff(&run(&a, &frames, batch).0, &run(&b, &frames, batch).0);
    eprintln!("amx vs avx512bf16: max difference {err:.2e}");
    // same rounded operands, only the order of the f32 sums differs
    assert!(err < 1e-3, "{err}");
}

#[test]
fn bf16_offline_bigru_stays_close_to_f32() {
    if units().is_empty() {
        return;
    }
    let weights = LoadedWeights::random(ModelKind::BiGru, 12).unwrap();
    let frames = random_frames(500, 13);
    let want = OfflineBiGruEngine::new(&weights, 2)
        .unwrap()
        .predict(&frames)
        .unwrap();
    let got = OfflineBiGruEngine::with_options(&weights, opts(2, None))
        .unwrap()
        .predict(&frames)
        .unwrap();
    let err = max_abs_diff(&got, &want);
    eprintln!("offline bf16: max error {err:.2e}");
    assert!(err < RANDOM_TOLERANCE, "{err}");
}

#[test]
fn bf16_is_refused_where_it_cannot_run() {
    let weights = LoadedWeights::random(ModelKind::Gru, 1).unwrap();
    // only the avx512 level has bf16 kernels
    let e = OnlineGruEngine::with_options(
        &weights,
        EngineOptions {
            isa: Some(blapose_model::Isa::Scalar),
            ..opts(1, None)
        },
    )
    .unwrap_err();
    assert!(
        matches!(e, ModelError::Config(ref m) if m.contains("avx512")),
        "{e}"
    );
    for unit in Bf16Unit::ALL {
        if let Some(missing) = unit.missing_feature() {
            let e = OnlineGruEngine::with_options(&weights, opts(1, Some(unit))).unwrap_err();
            assert!(e.to_string().contains(missing), "{e}");
        }
    }
    assert_eq!("bf16".parse::<Precision>().unwrap(), Precision::Bf16);
    assert_eq!(Precision::Bf16.to_string(), "bf16");
}

fn shipped(file: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../../models")
        .join(file)
}

/// A walking figure's 17 normalized keypoints (Human3.6M order) at frame
/// `t`, with a little deterministic jitter: a stand-in for a detector's
/// output over a long stream.
fn walking_frame(t: usize, rng: &mut StdRng) -> [f32; INPUT_DIM] {
    // standing pose, image-normalized (x right, y down), ~0.8 tall
    const BASE: [[f32; 2]; 17] = [
        [0.00, 0.00],   // hip
        [-0.06, 0.00],  // r hip
        [-0.07, 0.22],  // r knee
        [-0.07, 0.42],  // r foot
        [0.06, 0.00],   // l hip
        [0.07, 0.22],   // l knee
        [0.07, 0.42],   // l foot
        [0.00, -0.12],  // spine
        [0.00, -0.25],  // thorax
        [0.00, -0.30],  // neck
        [0.00, -0.37],  // head
        [0.09, -0.24],  // l shoulder
        [0.12, -0.10],  // l elbow
        [0.13, 0.02],   // l wrist
        [-0.09, -0.24], // r shoulder
        [-0.12, -0.10], // r elbow
        [-0.13, 0.02],  // r wrist
    ];
    let phase = t as f32 * std::f32::consts::TAU / 32.0;
    let (s, c) = phase.sin_cos();
    let mut out = [0.0f32; INPUT_DIM];
    for (j, p) in BASE.iter().enumerate() {
        let swing = match j {
            2 | 3 | 15 | 16 => 0.05 * s,
            5 | 6 | 12 | 13 => -0.05 * s,
            _ => 0.0,
        };
        let drift = 0.1 * (t as f32 * 0.001).sin();
        out[2 * j] = p[0] + swing + drift + rng.random_range(-0.004..0.004);
        out[2 * j + 1] = p[1] + 0.01 * c.abs() + rng.random_range(-0.004..0.004);
    }
    out
}

/// State drift: over a 10,000-frame stream the shipped online GRU's
/// per-frame lengths (and their running mean, what the server reports) on
/// bf16 stay within 0.1 mm of f32's.
#[test]
fn bf16_lengths_stay_within_a_tenth_of_a_millimetre_over_10000_frames() {
    let units = units();
    if units.is_empty() {
        return;
    }
    let weights = weights::load(shipped("bone_length_gru.safetensors"), ModelKind::Gru).unwrap();
    let mut rng = StdRng::seed_from_u64(7);
    let frames: Vec<f32> = (0..10_000)
        .flat_map(|t| walking_frame(t, &mut rng))
        .collect();
    let (want, _) = run(&OnlineGruEngine::new(&weights, 1).unwrap(), &frames, 1);
    for unit in units {
        let engine = OnlineGruEngine::with_options(&weights, opts(1, Some(unit))).unwrap();
        let (got, _) = run(&engine, &frames, 1);
        let per_frame = max_abs_diff(&got, &want);
        let mean = |v: &[f32]| -> Vec<f64> {
            let mut m = vec![0.0f64; OUTPUT_DIM];
            for row in v.chunks_exact(OUTPUT_DIM) {
                for (a, &x) in m.iter_mut().zip(row) {
                    *a += f64::from(x) / 10_000.0;
                }
            }
            m
        };
        let mean_err = mean(&got)
            .iter()
            .zip(mean(&want))
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        let last = max_abs_diff(
            &got[got.len() - OUTPUT_DIM..],
            &want[want.len() - OUTPUT_DIM..],
        );
        eprintln!(
            "{unit}: 10,000 frames: per-frame max {:.4} mm, last frame {:.4} mm, running mean {:.4} mm",
            per_frame * 1e3,
            last * 1e3,
            mean_err * 1e3
        );
        assert!(
            per_frame < 1e-4,
            "{unit}: per-frame lengths drift {per_frame} m"
        );
        assert!(mean_err < 1e-4, "{unit}: mean drifts {mean_err} m");
    }
}

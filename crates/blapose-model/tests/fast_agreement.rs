//! The fast engines against the reference candle models, and the SIMD
//! kernels against the scalar one. Its own test binary: candle reads its
//! thread count once per process, so another test's candle call could fix
//! it before `candle_single_threaded` runs.

use blapose_model::reference::{frames_tensor, GruImpl};
use blapose_model::{
    BoneLengthBiGru, BoneLengthGru, Isa, LoadedWeights, ModelError, ModelKind, OfflineBiGruEngine,
    OnlineGruEngine, INPUT_DIM, OUTPUT_DIM, STATE_DIM,
};
use rand::{rngs::StdRng, Rng, SeedableRng};

/// Run candle's element-wise ops on the calling thread. Its worker pool
/// spin-waits on barriers; on a loaded 2-core machine that spinning took
/// half the time of the 1,000-step reference runs. Every test calls this
/// first, so the variable is set before candle reads it (once).
fn candle_single_threaded() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| std::env::set_var("CANDLE_NUM_THREADS", "1"));
}

fn random_frames(n: usize, seed: u64) -> Vec<f32> {
    let mut rng = StdRng::seed_from_u64(seed);
    (0..n * INPUT_DIM)
        .map(|_| rng.random_range(-1.0f32..1.0))
        .collect()
}

/// Run `steps` online steps for `batch` sessions; frames are
/// `[b][t][34]`. Returns outputs `[b][t][16]`.
fn run_online(engine: &OnlineGruEngine, frames: &[f32], batch: usize, steps: usize) -> Vec<f32> {
    let mut hidden = vec![0.0; batch * STATE_DIM];
    let mut scratch = engine.scratch(batch);
    let mut x = vec![0.0; batch * INPUT_DIM];
    let mut y = vec![0.0; batch * OUTPUT_DIM];
    let mut outs = vec![0.0; batch * steps * OUTPUT_DIM];
    for t in 0..steps {
        for b in 0..batch {
            let src = (b * steps + t) * INPUT_DIM;
            x[b * INPUT_DIM..(b + 1) * INPUT_DIM].copy_from_slice(&frames[src..src + INPUT_DIM]);
        }
        engine.step(&x, &mut hidden, &mut y, &mut scratch).unwrap();
        for b in 0..batch {
            let dst = (b * steps + t) * OUTPUT_DIM;
            outs[dst..dst + OUTPUT_DIM].copy_from_slice(&y[b * OUTPUT_DIM..(b + 1) * OUTPUT_DIM]);
        }
    }
    outs
}

/// The reference model's per-frame predictions for `batch` sequences of
/// `steps` frames, flattened like [`run_online`]'s output.
fn reference_per_frame(
    model: &BoneLengthGru,
    frames: &[f32],
    batch: usize,
    steps: usize,
) -> Vec<f32> {
    let x = frames_tensor(frames, batch, steps).unwrap();
    model
        .forward_per_frame(&x)
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1()
        .unwrap()
}

fn max_abs_diff(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

fn online_matches_reference(batch: usize, threads: usize) {
    candle_single_threaded();
    let steps = 1000;
    let weights = LoadedWeights::random(ModelKind::Gru, 11).unwrap();
    // plain candle ops: independent of the kernels (the fused training op reuses them)
    let model = BoneLengthGru::new(weights.var_builder())
        .unwrap()
        .with_gru_impl(GruImpl::Autograd);
    let frames = random_frames(batch * steps, 5 + batch as u64);
    let expect = reference_per_frame(&model, &frames, batch, steps);
    let engine = OnlineGruEngine::new(&weights, threads).unwrap();
    let got = run_online(&engine, &frames, batch, steps);
    let err = max_abs_diff(&got, &expect);
    eprintln!(
        "batch {batch}, {threads} threads, {} (blocked: {}): max |fast - reference| = {err:.3e}",
        engine.isa(),
        engine.is_cache_blocked(batch)
    );
    if engine.isa() == Isa::Avx2 && batch == 64 {
        assert!(engine.is_cache_blocked(batch), "batch {batch} not blocked");
    }
    assert!(err < 1e-4, "max error {err}");
    // the final prediction equals the reference's final-state forward
    let last: Vec<f32> = model
        .forward(&frames_tensor(&frames, batch, steps).unwrap(), false)
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1()
        .unwrap();
    for b in 0..batch {
        let at = (b * steps + steps - 1) * OUTPUT_DIM;
        let e = max_abs_diff(
            &got[at..at + OUTPUT_DIM],
            &last[b * OUTPUT_DIM..(b + 1) * OUTPUT_DIM],
        );
        assert!(e < 1e-4, "row {b}: {e}");
    }
}

#[test]
fn online_batch1_agrees_with_reference_over_1000_steps() {
    online_matches_reference(1, 1);
}

#[test]
fn online_batch64_agrees_with_reference_over_1000_steps() {
    online_matches_reference(64, 2);
}

#[test]
fn every_isa_and_thread_count_agrees_with_scalar() {
    candle_single_threaded();
    let weights = LoadedWeights::random(ModelKind::Gru, 3).unwrap();
    let (batch, steps) = (11, 40); // 11 rows: full tiles plus remainders
    let frames = random_frames(batch * steps, 99);
    let scalar = OnlineGruEngine::with_isa(&weights, 1, Isa::Scalar).unwrap();
    let oracle = run_online(&scalar, &frames, batch, steps);
    let mut tested = 0;
    for isa in Isa::ALL.into_iter().filter(|i| i.is_available()) {
        for threads in [1, 2, 3] {
            let engine = OnlineGruEngine::with_isa(&weights, threads, isa).unwrap();
            let got = run_online(&engine, &frames, batch, steps);
            let err = max_abs_diff(&got, &oracle);
            eprintln!("{isa} x{threads}: max |simd - scalar| = {err:.3e}");
            assert!(err < 2e-5, "{isa} x{threads}: {err}");
            tested += 1;
        }
    }
    assert!(tested >= 3);
}

/// A step's bits depend on its inputs and state only: not on the thread
/// count, nor on the order the panels ran in (it alternates between
/// steps), nor on how many steps the scratch has seen. A session restored
/// from a token on another replica therefore continues bit for bit.
#[test]
fn a_step_is_bit_exact_whatever_the_threads_and_the_step_parity() {
    candle_single_threaded();
    let weights = LoadedWeights::random(ModelKind::Gru, 5).unwrap();
    let frames = random_frames(3, 7);
    let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    let mut answers = Vec::new();
    for threads in [1, 2] {
        let engine = OnlineGruEngine::new(&weights, threads).unwrap();
        for warm_steps in [0, 1] {
            let mut scratch = engine.scratch(1);
            let mut y = vec![0.0; OUTPUT_DIM];
            let mut junk = vec![0.0; STATE_DIM];
            for _ in 0..warm_steps {
                engine
                    .step(&frames[..INPUT_DIM], &mut junk, &mut y, &mut scratch)
                    .unwrap();
            }
            let mut hidden = vec![0.0; STATE_DIM];
            let mut outs = Vec::new();
            for t in 0..3 {
                let x = &frames[t * INPUT_DIM..(t + 1) * INPUT_DIM];
                engine.step(x, &mut hidden, &mut y, &mut scratch).unwrap();
                outs.extend(bits(&y));
            }
            outs.extend(bits(&hidden));
            answers.push(outs);
        }
    }
    assert!(answers.windows(2).all(|w| w[0] == w[1]));
}

#[test]
fn unavailable_or_mismatched_configs_are_refused() {
    candle_single_threaded();
    let bigru = LoadedWeights::random(ModelKind::BiGru, 1).unwrap();
    assert!(matches!(
        OnlineGruEngine::new(&bigru, 1),
        Err(ModelError::WrongKind { .. })
    ));
    let gru = LoadedWeights::random(ModelKind::Gru, 1).unwrap();
    assert!(matches!(
        OfflineBiGruEngine::new(&gru, 1),
        Err(ModelError::WrongKind { .. })
    ));
    assert!(matches!(
        OnlineGruEngine::new(&gru, 0),
        Err(ModelError::Config(_))
    ));
    let engine = OnlineGruEngine::new(&gru, 1).unwrap();
    let mut scratch = engine.scratch(2);
    let mut hidden = vec![0.0; 2 * STATE_DIM];
    let mut out = vec![0.0; 2 * OUTPUT_DIM];
    let err = engine
        .step(
            &[0.0; 2 * INPUT_DIM - 1],
            &mut hidden,
            &mut out,
            &mut scratch,
        )
        .unwrap_err();
    assert!(matches!(err, ModelError::BadLength { .. }), "{err}");
    let err = engine
        .step(
            &[0.0; 2 * INPUT_DIM],
            &mut hidden[..STATE_DIM],
            &mut out,
            &mut scratch,
        )
        .unwrap_err();
    assert!(matches!(err, ModelError::BadLength { .. }), "{err}");
}

#[test]
fn non_finite_input_leaves_every_state_untouched() {
    candle_single_threaded();
    let weights = LoadedWeights::random(ModelKind::Gru, 4).unwrap();
    for threads in [1, 2] {
        let engine = OnlineGruEngine::new(&weights, threads).unwrap();
        let batch = 6;
        let mut scratch = engine.scratch(batch);
        let mut hidden = vec![0.0; batch * STATE_DIM];
        let mut out = vec![0.0; batch * OUTPUT_DIM];
        let mut x = random_frames(batch, 8);
        // a few good steps so the state is not trivially zero
        for _ in 0..3 {
            engine
                .step(&x, &mut hidden, &mut out, &mut scratch)
                .unwrap();
        }
        let (h0, y0) = (hidden.clone(), out.clone());
        for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
            x[3 * INPUT_DIM + 7] = bad;
            let err = engine
                .step(&x, &mut hidden, &mut out, &mut scratch)
                .unwrap_err();
            assert!(
                matches!(err, ModelError::NonFiniteInput { row: 3, col: 7 }),
                "{err}"
            );
            assert_eq!(hidden, h0);
            assert_eq!(out, y0);
        }
        // finite but absurd input: either refused with states untouched, or finite results
        x[3 * INPUT_DIM + 7] = 3e38;
        x[3 * INPUT_DIM + 8] = -3e38;
        match engine.step(&x, &mut hidden, &mut out, &mut scratch) {
            Err(ModelError::NonFiniteState { row }) => {
                assert_eq!(row, 3);
                assert_eq!(hidden, h0);
                assert_eq!(out, y0);
            }
            Err(e) => panic!("unexpected error {e}"),
            Ok(()) => assert!(hidden.iter().chain(&out).all(|v| v.is_finite())),
        }
    }
}

#[test]
fn scratch_grows_for_larger_batches() {
    candle_single_threaded();
    let weights = LoadedWeights::random(ModelKind::Gru, 5).unwrap();
    let engine = OnlineGruEngine::new(&weights, 2).unwrap();
    let mut scratch = engine.scratch(1);
    for batch in [1, 9, 3] {
        let x = random_frames(batch, batch as u64);
        let mut hidden = vec![0.0; batch * STATE_DIM];
        let mut out = vec![0.0; batch * OUTPUT_DIM];
        engine
            .step(&x, &mut hidden, &mut out, &mut scratch)
            .unwrap();
        // every row equals the same frame run alone
        let mut single = engine.scratch(1);
        for b in 0..batch {
            let mut h1 = vec![0.0; STATE_DIM];
            let mut y1 = vec![0.0; OUTPUT_DIM];
            engine
                .step(
                    &x[b * INPUT_DIM..(b + 1) * INPUT_DIM],
                    &mut h1,
                    &mut y1,
                    &mut single,
                )
                .unwrap();
            assert!(max_abs_diff(&h1, &hidden[b * STATE_DIM..(b + 1) * STATE_DIM]) < 1e-6);
            assert!(max_abs_diff(&y1, &out[b * OUTPUT_DIM..(b + 1) * OUTPUT_DIM]) < 1e-6);
        }
    }
    assert!(scratch.capacity() >= 9);
}

#[test]
fn offline_agrees_with_reference() {
    candle_single_threaded();
    let weights = LoadedWeights::random(ModelKind::BiGru, 21).unwrap();
    let model = BoneLengthBiGru::new(weights.var_builder())
        .unwrap()
        .with_gru_impl(GruImpl::Autograd);
    for (steps, threads) in [(1, 1), (37, 2), (600, 2), (300, 1)] {
        let frames = random_frames(steps, steps as u64);
        let expect: Vec<f32> = model
            .forward(&frames_tensor(&frames, 1, steps).unwrap(), false)
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1()
            .unwrap();
        for isa in Isa::ALL.into_iter().filter(|i| i.is_available()) {
            let engine = OfflineBiGruEngine::with_isa(&weights, threads, isa).unwrap();
            let got = engine.predict(&frames).unwrap();
            let err = max_abs_diff(&got, &expect);
            eprintln!("offline T={steps} {isa} x{threads}: max error {err:.3e}");
            assert!(err < 1e-4, "T={steps} {isa}: {err}");
        }
    }
}

#[test]
fn offline_refuses_bad_sequences() {
    candle_single_threaded();
    let weights = LoadedWeights::random(ModelKind::BiGru, 2).unwrap();
    let engine = OfflineBiGruEngine::new(&weights, 1).unwrap();
    assert!(matches!(
        engine.predict(&[]),
        Err(ModelError::EmptySequence)
    ));
    assert!(matches!(
        engine.predict(&[0.0; INPUT_DIM + 1]),
        Err(ModelError::BadLength { .. })
    ));
    let mut frames = random_frames(10, 1);
    frames[5 * INPUT_DIM + 2] = f32::NAN;
    assert!(matches!(
        engine.predict(&frames),
        Err(ModelError::NonFiniteInput { row: 5, col: 2 })
    ));
}

/// f16 weight storage is an opt-in speed option; its error is reported,
/// and bounded loosely so a broken conversion still fails.
#[test]
fn half_precision_weights_stay_close() {
    candle_single_threaded();
    use blapose_model::{EngineOptions, Precision};
    let weights = LoadedWeights::random(ModelKind::Gru, 11).unwrap();
    let (batch, steps) = (3, 300);
    let frames = random_frames(batch * steps, 77);
    let exact = run_online(
        &OnlineGruEngine::new(&weights, 1).unwrap(),
        &frames,
        batch,
        steps,
    );
    for isa in Isa::ALL.into_iter().filter(|i| i.is_available()) {
        let opts = EngineOptions {
            isa: Some(isa),
            precision: Precision::F16,
            ..EngineOptions::threads(1)
        };
        let engine = OnlineGruEngine::with_options(&weights, opts).unwrap();
        assert_eq!(engine.precision(), Precision::F16);
        let got = run_online(&engine, &frames, batch, steps);
        let err = max_abs_diff(&got, &exact);
        let scale = exact.iter().fold(0f32, |m, v| m.max(v.abs()));
        eprintln!("online f16 {isa}: max error {err:.3e} (outputs up to {scale:.3})");
        assert!(err > 0.0 && err < 2e-3, "{isa}: {err}");
    }
    let weights = LoadedWeights::random(ModelKind::BiGru, 21).unwrap();
    let frames = random_frames(500, 5);
    let exact = OfflineBiGruEngine::new(&weights, 1)
        .unwrap()
        .predict(&frames)
        .unwrap();
    let opts = EngineOptions {
        precision: Precision::F16,
        ..EngineOptions::threads(2)
    };
    let got = OfflineBiGruEngine::with_options(&weights, opts)
        .unwrap()
        .predict(&frames)
        .unwrap();
    let err = max_abs_diff(&got, &exact);
    eprintln!("offline f16: max error {err:.3e}");
    assert!(err < 2e-3, "{err}");
}

#[test]
fn engines_can_be_shared_across_threads() {
    fn assert_send_sync<T: Send + Sync>() {}
    fn assert_send<T: Send>() {}
    assert_send_sync::<OnlineGruEngine>();
    assert_send_sync::<OfflineBiGruEngine>();
    assert_send_sync::<LoadedWeights>();
    assert_send::<blapose_model::StepScratch>();
}

/// As [`run_online`], but every session stepped alone (batch 1), which
/// never takes the cache-blocked path.
fn run_online_rowwise(
    engine: &OnlineGruEngine,
    frames: &[f32],
    batch: usize,
    steps: usize,
) -> Vec<f32> {
    assert!(!engine.is_cache_blocked(1));
    (0..batch)
        .flat_map(|b| {
            let rows = &frames[b * steps * INPUT_DIM..(b + 1) * steps * INPUT_DIM];
            run_online(engine, rows, 1, steps)
        })
        .collect()
}

/// The smallest batch that takes the cache-blocked kernel on this CPU.
fn blocked_threshold(engine: &OnlineGruEngine) -> Option<usize> {
    (1..=64).find(|&b| engine.is_cache_blocked(b))
}

#[test]
fn blocked_path_agrees_with_reference_around_its_threshold() {
    candle_single_threaded();
    let weights = LoadedWeights::random(ModelKind::Gru, 13).unwrap();
    let probe = OnlineGruEngine::new(&weights, 1).unwrap();
    let Some(min) = blocked_threshold(&probe) else {
        eprintln!("skipping: no cache-blocked kernel for {}", probe.isa());
        return;
    };
    assert!(probe.is_cache_blocked(64));
    let model = BoneLengthGru::new(weights.var_builder())
        .unwrap()
        .with_gru_impl(GruImpl::Autograd);
    let steps = 500;
    // below, at and above the threshold; odd sizes leave a 1-row tile
    for (batch, threads) in [(min - 1, 1), (min, 2), (min + 1, 1), (37, 2)] {
        let frames = random_frames(batch * steps, 40 + batch as u64);
        let expect = reference_per_frame(&model, &frames, batch, steps);
        let engine = OnlineGruEngine::new(&weights, threads).unwrap();
        assert_eq!(engine.is_cache_blocked(batch), batch >= min);
        let got = run_online(&engine, &frames, batch, steps);
        let err = max_abs_diff(&got, &expect);
        eprintln!(
            "batch {batch} x{threads} (blocked: {}): max |fast - reference| = {err:.3e}",
            batch >= min
        );
        assert!(err < 1e-4, "batch {batch}: {err}");
    }
}

/// At batch 64 the blocked kernel (f32 and f16 weights, 1 and 2 threads)
/// gives each session what stepping it alone through the plain kernel
/// gives, over a long sequence.
#[test]
fn blocked_batch64_matches_sessions_stepped_alone() {
    candle_single_threaded();
    use blapose_model::{EngineOptions, Precision};
    let weights = LoadedWeights::random(ModelKind::Gru, 17).unwrap();
    let (batch, steps) = (64, 300);
    let frames = random_frames(batch * steps, 123);
    for precision in [Precision::F32, Precision::F16] {
        for threads in [1, 2] {
            let opts = EngineOptions {
                precision,
                ..EngineOptions::threads(threads)
            };
            let engine = OnlineGruEngine::with_options(&weights, opts).unwrap();
            if !engine.is_cache_blocked(batch) {
                eprintln!("skipping: no cache-blocked kernel for {}", engine.isa());
                return;
            }
            let got = run_online(&engine, &frames, batch, steps);
            let alone = run_online_rowwise(&engine, &frames, batch, steps);
            let err = max_abs_diff(&got, &alone);
            eprintln!("batch 64 {precision:?} x{threads}: max |blocked - alone| = {err:.3e}");
            assert!(err < 1e-5, "{precision:?} x{threads}: {err}");
        }
    }
}

//! A steady-state online step allocates nothing (1 and 2 threads, a small
//! batch on the plain kernel and batch 64 on the cache-blocked one).
//! Its own test binary, because it installs a counting global allocator.

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicUsize, Ordering};

use blapose_model::{LoadedWeights, ModelKind, OnlineGruEngine, INPUT_DIM, OUTPUT_DIM, STATE_DIM};

struct Counting;

static ALLOCATIONS: AtomicUsize = AtomicUsize::new(0);

// SAFETY: forwards to the system allocator, only counting calls.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        ALLOCATIONS.fetch_add(1, Ordering::Relaxed);
        System.alloc(layout)
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        System.dealloc(ptr, layout)
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

#[test]
fn steady_state_step_does_not_allocate() {
    // one test function: the counter is global, parallel tests would pollute it
    for threads in [1, 2] {
        for batch in [5, 64] {
            check(threads, batch);
        }
    }
}

fn check(threads: usize, batch: usize) {
    let weights = LoadedWeights::random(ModelKind::Gru, 1).unwrap();
    let engine = OnlineGruEngine::new(&weights, threads).unwrap();
    let mut scratch = engine.scratch(batch);
    let x: Vec<f32> = (0..batch * INPUT_DIM)
        .map(|i| (i as f32 * 0.1).sin())
        .collect();
    let mut hidden = vec![0.0; batch * STATE_DIM];
    let mut out = vec![0.0; batch * OUTPUT_DIM];
    engine
        .step(&x, &mut hidden, &mut out, &mut scratch)
        .unwrap();
    let before = ALLOCATIONS.load(Ordering::Relaxed);
    for _ in 0..20 {
        engine
            .step(&x, &mut hidden, &mut out, &mut scratch)
            .unwrap();
    }
    let after = ALLOCATIONS.load(Ordering::Relaxed);
    assert_eq!(
        after - before,
        0,
        "{threads} threads, batch {batch}: {} allocations in 20 steps",
        after - before
    );
    // smaller batches reuse the same scratch
    engine
        .step(
            &x[..2 * INPUT_DIM],
            &mut hidden[..2 * STATE_DIM],
            &mut out[..2 * OUTPUT_DIM],
            &mut scratch,
        )
        .unwrap();
    assert_eq!(ALLOCATIONS.load(Ordering::Relaxed), after);
}

//! Criterion micro-benchmarks of the per-frame hot paths, so regressions show:
//!
//! * `adjust_frame`: the BLAPose adjustment of one pose
//!   (`blapose_core::bones::adjust_pose`);
//! * `project_batch`: projecting 100k camera-space points with the
//!   Human3.6M lens model into normalized screen coordinates (the training
//!   data synthesis hot path);
//! * `gru_step`: one fast online GRU step at batch 1 and 64, with one and
//!   two worker threads.
//!
//! Run with `cargo bench -p blapose-bench` (add `-- gru_step` to filter).
//! Measurement times are short (a few seconds per benchmark) so the whole
//! suite finishes in well under a minute.

use std::hint::black_box;
use std::time::Duration;

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion, Throughput};

use blapose_core::bones::{adjust_pose, bone_lengths};
use blapose_core::camera::Intrinsics;
use blapose_core::{BoneLengths, Pose};
use blapose_model::fast::OnlineGruEngine;
use blapose_model::{LoadedWeights, ModelKind, INPUT_DIM, OUTPUT_DIM, STATE_DIM};

/// A standing Human3.6M pose in metres (root at the origin).
const POSE: Pose = [
    [0.0, 0.0, 0.0],
    [-0.13, 0.0, 0.0],
    [-0.14, 0.44, 0.02],
    [-0.14, 0.88, 0.05],
    [0.13, 0.0, 0.0],
    [0.14, 0.44, 0.02],
    [0.14, 0.88, 0.05],
    [0.0, -0.23, -0.01],
    [0.0, -0.48, -0.02],
    [0.0, -0.58, -0.05],
    [0.0, -0.68, -0.03],
    [0.16, -0.46, 0.0],
    [0.24, -0.2, 0.03],
    [0.26, 0.05, 0.08],
    [-0.16, -0.46, 0.0],
    [-0.24, -0.2, 0.03],
    [-0.26, 0.05, 0.08],
];

fn adjust_frame(c: &mut Criterion) {
    let lengths: BoneLengths = bone_lengths(&POSE).map(|l| 1.05 * l);
    c.bench_function("adjust_frame", |b| {
        b.iter(|| adjust_pose(black_box(&POSE), black_box(&lengths)))
    });
}

fn project_batch(c: &mut Criterion) {
    const N: usize = 100_000;
    // Roughly a Human3.6M camera in normalized units, with its distortion.
    let k = Intrinsics::<f32> {
        focal: [2.29, 2.29],
        principal: [0.02, -0.01],
        radial: [-0.207, 0.248, -0.003],
        tangential: [-0.0009, -0.0012],
    };
    let points: Vec<[f32; 3]> = (0..N)
        .map(|i| {
            let t = i as f32 * 1e-3;
            [t.sin() * 0.8, t.cos() * 0.9, 4.5 + (3.0 * t).sin()]
        })
        .collect();
    let mut out = vec![[0.0f32; 2]; N];
    let mut group = c.benchmark_group("project_batch");
    group.throughput(Throughput::Elements(N as u64));
    group.bench_function("100k_points", |b| {
        b.iter(|| k.project_points(black_box(&points), &mut out))
    });
    group.finish();
}

fn gru_step(c: &mut Criterion) {
    let weights = LoadedWeights::random(ModelKind::Gru, 0).expect("random GRU weights");
    let mut group = c.benchmark_group("gru_step");
    for threads in [1, 2] {
        let engine = OnlineGruEngine::new(&weights, threads).expect("GRU engine");
        for batch in [1usize, 64] {
            let inputs: Vec<f32> = (0..batch * INPUT_DIM)
                .map(|i| ((i % 34) as f32 * 0.05).sin() * 0.5)
                .collect();
            let mut hidden = vec![0.0f32; batch * STATE_DIM];
            let mut out = vec![0.0f32; batch * OUTPUT_DIM];
            let mut scratch = engine.scratch(batch);
            group.throughput(Throughput::Elements(batch as u64));
            group.bench_with_input(
                BenchmarkId::new(format!("{threads}_threads"), format!("batch_{batch}")),
                &batch,
                |b, _| {
                    b.iter(|| {
                        engine
                            .step(black_box(&inputs), &mut hidden, &mut out, &mut scratch)
                            .expect("step")
                    })
                },
            );
        }
    }
    group.finish();
}

fn config() -> Criterion {
    Criterion::default()
        .warm_up_time(Duration::from_secs(1))
        .measurement_time(Duration::from_secs(3))
        .sample_size(30)
}

criterion_group! {
    name = benches;
    config = config();
    targets = adjust_frame, project_batch, gru_step
}
criterion_main!(benches);

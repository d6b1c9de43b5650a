use candle_core::{Device, Tensor};
use std::time::Instant;
fn main() {
    for (m, k, n) in [(81usize, 102usize, 1024usize), (27, 3072, 1024), (27, 1024, 1024), (9, 3072, 1024), (1, 3072, 1024), (1, 1024, 51)] {
        let a = Tensor::rand(-1f32, 1f32, (m, k), &Device::Cpu).unwrap();
        let b = Tensor::rand(-1f32, 1f32, (k, n), &Device::Cpu).unwrap();
        for _ in 0..3 { a.matmul(&b).unwrap(); }
        let t = Instant::now();
        let iters = 50;
        for _ in 0..iters { std::hint::black_box(a.matmul(&b).unwrap()); }
        let dt = t.elapsed().as_secs_f64() / iters as f64;
        println!("{m}x{k}x{n}: {:.3} ms, {:.1} GFLOP/s", dt * 1e3, 2.0 * (m * k * n) as f64 / dt / 1e9);
    }
}

use blapose_lifters::*;
use candle_core::{Device, Tensor};
use std::time::Instant;
fn time(iters: usize, mut f: impl FnMut()) -> f64 {
    for _ in 0..3 { f(); }
    let t = Instant::now();
    for _ in 0..iters { f(); }
    t.elapsed().as_secs_f64() / iters as f64
}
fn main() {
    let which = std::env::args().nth(1).unwrap_or_default();
    let iters: usize = std::env::args().nth(2).and_then(|s| s.parse().ok()).unwrap_or(30);
    let w243 = Tensor::rand(-1f32, 1f32, (1, 243, 17, 2), &Device::Cpu).unwrap();
    if which.is_empty() || which == "vp" {
        let vp = VideoPose3d::random(VideoPose3dConfig::receptive_field_243(), 0).unwrap();
        let d = time(iters, || { std::hint::black_box(vp.predict_frame(&w243).unwrap()); });
        println!("videopose {:.2} ms ({:.1} GFLOP/s)", d*1e3, 0.352 / d);
    }
    if which.is_empty() || which == "pf" {
        let pf = PoseFormer::random(PoseFormerConfig::frames_81(), 0).unwrap();
        let w = Tensor::rand(-1f32, 1f32, (1, 81, 17, 2), &Device::Cpu).unwrap();
        let d = time(iters, || { std::hint::black_box(pf.predict_frame(&w).unwrap()); });
        println!("poseformer {:.2} ms", d*1e3);
    }
    if which.is_empty() || which == "an" {
        let an = Anatomy3d::random(Anatomy3dConfig::receptive_field_243(), 0).unwrap();
        let l = Tensor::rand(0f32, 1f32, (1, 16), &Device::Cpu).unwrap();
        let d = time(iters, || { std::hint::black_box(an.predict_frame_with(&w243, None, &l).unwrap()); });
        println!("anatomy3d {:.2} ms", d*1e3);
    }
}

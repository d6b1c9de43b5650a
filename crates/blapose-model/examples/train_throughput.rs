//! Training throughput of the reference models: forward + backward + AdamW
//! step on random data, reported as frames per second.
//!
//! `cargo run --release -p blapose-model --example train_throughput -- [gru|bigru] B T iters`

use anyhow::Result;
use blapose_model::{BoneLengthBiGru, BoneLengthGru, ModelKind, INPUT_DIM, OUTPUT_DIM};
use candle_core::{DType, Device, Tensor};
use candle_nn::{AdamW, Optimizer, ParamsAdamW, VarBuilder, VarMap};

/// A model's training-mode forward pass.
type Forward = Box<dyn Fn(&Tensor) -> candle_core::Result<Tensor>>;

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let kind: ModelKind = args
        .get(1)
        .map(|s| s.parse())
        .transpose()?
        .unwrap_or(ModelKind::Gru);
    let batch: usize = args.get(2).map(|s| s.parse()).transpose()?.unwrap_or(64);
    let steps: usize = args.get(3).map(|s| s.parse()).transpose()?.unwrap_or(64);
    let iters: usize = args.get(4).map(|s| s.parse()).transpose()?.unwrap_or(5);
    let dev = Device::Cpu;
    let varmap = VarMap::new();
    let vb = VarBuilder::from_varmap(&varmap, DType::F32, &dev);
    let forward: Forward = match kind {
        ModelKind::Gru => {
            let m = BoneLengthGru::new(vb)?;
            Box::new(move |x| m.forward(x, true))
        }
        ModelKind::BiGru => {
            let m = BoneLengthBiGru::new(vb)?;
            Box::new(move |x| m.forward(x, true))
        }
    };
    let mut opt = AdamW::new(
        varmap.all_vars(),
        ParamsAdamW {
            lr: 1e-4,
            ..Default::default()
        },
    )?;
    let x = Tensor::rand(-1f32, 1f32, (batch, steps, INPUT_DIM), &dev)?;
    let target = Tensor::rand(0.1f32, 0.5f32, (batch, OUTPUT_DIM), &dev)?;
    let mut times = Vec::new();
    for i in 0..iters + 1 {
        let t0 = std::time::Instant::now();
        let y = forward(&x)?;
        let loss = (y - &target)?.abs()?.mean_all()?;
        let t1 = t0.elapsed();
        opt.backward_step(&loss)?;
        let dt = t0.elapsed().as_secs_f64();
        eprintln!(
            "iter {i}: fwd {:.3}s total {dt:.3}s loss {}",
            t1.as_secs_f64(),
            loss.to_scalar::<f32>()?
        );
        if i > 0 {
            times.push(dt);
        }
    }
    times.sort_by(f64::total_cmp);
    let median = times[times.len() / 2];
    println!("kind={kind} batch={batch} steps={steps} median_iter_s={median:.3}");
    println!("frames_per_second={:.0}", (batch * steps) as f64 / median);
    Ok(())
}

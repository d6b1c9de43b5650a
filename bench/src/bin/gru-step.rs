//! Throughput of the bone-length GRU kernels on random weights and inputs.
//!
//! Online: `gru-step --batch B --threads T --steps N [--path fast|reference]`
//! advances B sessions N frames, one batched step per frame.
//! Offline: `gru-step --offline --frames N [--threads T]` runs the Bi-GRU over
//! one N-frame sequence. Either way the last line is
//! `frames_per_second=<number>` (the median over `--repeats` runs).

use std::time::Instant;

use anyhow::{bail, Result};
use blapose_bench::machine::process_cpu_seconds;
use blapose_model::reference::frames_tensor;
use blapose_model::{
    BoneLengthGru, EngineOptions, Isa, LoadedWeights, ModelKind, OfflineBiGruEngine,
    OnlineGruEngine, Precision, INPUT_DIM, OUTPUT_DIM, STATE_DIM,
};
use candle_core::{Device, Tensor};
use clap::{Parser, ValueEnum};

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum PathKind {
    /// The hand-written kernels (`OnlineGruEngine` / `OfflineBiGruEngine`).
    Fast,
    /// The candle reference model, one `step` per frame.
    Reference,
}

/// Benchmark the online GRU step or the offline Bi-GRU.
#[derive(Debug, Parser)]
#[command(name = "gru-step")]
struct Args {
    /// Sessions advanced per step.
    #[arg(long, default_value_t = 1)]
    batch: usize,
    /// Worker threads.
    #[arg(long, default_value_t = 1)]
    threads: usize,
    /// Online steps per run.
    #[arg(long, default_value_t = 10_000)]
    steps: usize,
    /// Which implementation to time.
    #[arg(long, value_enum, default_value_t = PathKind::Fast)]
    path: PathKind,
    /// Time the offline Bi-GRU over one sequence instead of online steps.
    #[arg(long)]
    offline: bool,
    /// Sequence length for `--offline`.
    #[arg(long, default_value_t = 10_000)]
    frames: usize,
    /// Instruction set of the fast path (scalar, avx2, avx512); default: best available.
    #[arg(long)]
    isa: Option<String>,
    /// Storage precision of the fast path's GRU weights: auto (the
    /// default: the fastest on this CPU, as the server picks it: bf16 with
    /// AMX, else f16), f32, f16 or bf16.
    #[arg(long, default_value = "auto", value_parser = blapose_server::config::parse_precision)]
    precision: Precision,
    /// With `--precision bf16`: the bf16 unit (amx, avx512bf16); default:
    /// AMX where the CPU and OS allow it.
    #[arg(long)]
    bf16_unit: Option<String>,
    /// Timed runs; the reported number is their median.
    #[arg(long, default_value_t = 1)]
    repeats: usize,
    /// Untimed steps before each run (online).
    #[arg(long, default_value_t = 50)]
    warmup: usize,
    /// Seed of the random weights and inputs.
    #[arg(long, default_value_t = 1)]
    seed: u64,
}

/// Uniform values in [-1, 1) from a xorshift generator (inputs only; the
/// weights come from blapose-model's PyTorch-style initializer).
fn random_inputs(n: usize, seed: u64) -> Vec<f32> {
    let mut s = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
    (0..n)
        .map(|_| {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            (s >> 40) as f32 / (1u64 << 23) as f32 - 1.0
        })
        .collect()
}

fn main() -> Result<()> {
    let args = Args::parse();
    if args.batch == 0
        || args.threads == 0
        || args.steps == 0
        || args.frames == 0
        || args.repeats == 0
    {
        bail!("--batch, --threads, --steps, --frames and --repeats must be positive");
    }
    let isa = match &args.isa {
        Some(s) => s.parse::<Isa>()?,
        None => Isa::detect(),
    };
    let opts = EngineOptions {
        threads: args.threads,
        isa: Some(isa),
        precision: args.precision,
        bf16_unit: args.bf16_unit.as_deref().map(str::parse).transpose()?,
    };
    let mut rates = Vec::with_capacity(args.repeats);
    let cpu_start = process_cpu_seconds();
    let wall_start = Instant::now();
    for run in 0..args.repeats {
        let (frames, secs) = if args.offline {
            offline(&args, opts)?
        } else {
            match args.path {
                PathKind::Fast => online_fast(&args, opts)?,
                PathKind::Reference => online_reference(&args)?,
            }
        };
        let rate = frames as f64 / secs;
        println!("run {run}: {frames} frames in {secs:.4} s = {rate:.0} frames/s");
        rates.push(rate);
    }
    if let (Some(a), Some(b)) = (cpu_start, process_cpu_seconds()) {
        // On a shared machine the wall-clock rate understates the kernel's
        // speed; CPU time over wall time shows how much of the cores we got.
        let wall = wall_start.elapsed().as_secs_f64();
        println!(
            "process_cpu_seconds={:.2} wall_seconds={wall:.2} (includes setup; rayon workers spin while idle)",
            b - a
        );
    }
    rates.sort_by(f64::total_cmp);
    let median = rates[rates.len() / 2];
    if args.offline {
        println!(
            "mode=offline frames={} threads={} isa={isa} precision={} seconds={:.4}",
            args.frames,
            args.threads,
            args.precision,
            args.frames as f64 / median
        );
    } else {
        let isa_s = if args.path == PathKind::Fast {
            isa.as_str()
        } else {
            "candle"
        };
        println!(
            "mode=online path={:?} batch={} threads={} steps={} isa={isa_s} precision={}{}",
            args.path,
            args.batch,
            args.threads,
            args.steps,
            args.precision,
            bf16_note(opts)
        );
    }
    println!("frames_per_second={median:.0}");
    Ok(())
}

/// ` bf16_unit=<unit>` for bf16 runs (the unit the engine picked).
fn bf16_note(opts: EngineOptions) -> String {
    if opts.precision != Precision::Bf16 {
        return String::new();
    }
    match LoadedWeights::random(ModelKind::Gru, 1)
        .ok()
        .and_then(|w| OnlineGruEngine::with_options(&w, opts).ok())
        .and_then(|e| e.bf16_unit())
    {
        Some(unit) => format!(" bf16_unit={unit}"),
        None => String::new(),
    }
}

fn online_fast(args: &Args, opts: EngineOptions) -> Result<(usize, f64)> {
    let weights = LoadedWeights::random(ModelKind::Gru, args.seed)?;
    let engine = OnlineGruEngine::with_options(&weights, opts)?;
    let b = args.batch;
    // a pool of distinct frames, cycled through so inputs vary per step
    let pool_steps = 64;
    let inputs = random_inputs(pool_steps * b * INPUT_DIM, args.seed + 1);
    let mut hidden = vec![0.0; b * STATE_DIM];
    let mut out = vec![0.0; b * OUTPUT_DIM];
    let mut scratch = engine.scratch(b);
    let frame =
        |t: usize| &inputs[(t % pool_steps) * b * INPUT_DIM..(t % pool_steps + 1) * b * INPUT_DIM];
    for t in 0..args.warmup {
        engine.step(frame(t), &mut hidden, &mut out, &mut scratch)?;
    }
    let cpu_start = process_cpu_seconds();
    let start = Instant::now();
    for t in 0..args.steps {
        engine.step(frame(t), &mut hidden, &mut out, &mut scratch)?;
    }
    let secs = start.elapsed().as_secs_f64();
    if let (Some(a), Some(b)) = (cpu_start, process_cpu_seconds()) {
        // below `threads` on a shared machine: the rate above is then low
        println!("  cores used while timed: {:.2}", (b - a) / secs);
    }
    std::hint::black_box(&out);
    Ok((args.steps * b, secs))
}

fn online_reference(args: &Args) -> Result<(usize, f64)> {
    let weights = LoadedWeights::random(ModelKind::Gru, args.seed)?;
    let model = BoneLengthGru::new(weights.var_builder())?.stepper()?;
    let b = args.batch;
    let pool_steps = 64;
    let inputs = random_inputs(pool_steps * b * INPUT_DIM, args.seed + 1);
    let mut state = Tensor::zeros((b, STATE_DIM), candle_core::DType::F32, &Device::Cpu)?;
    let mut step = |t: usize| -> Result<Vec<f32>> {
        let x = &inputs[(t % pool_steps) * b * INPUT_DIM..(t % pool_steps + 1) * b * INPUT_DIM];
        let x = Tensor::from_slice(x, (b, INPUT_DIM), &Device::Cpu)?;
        let (h, y) = model.step(&x, &state)?;
        state = h;
        Ok(y.flatten_all()?.to_vec1::<f32>()?)
    };
    for t in 0..args.warmup.min(10) {
        step(t)?;
    }
    let start = Instant::now();
    for t in 0..args.steps {
        std::hint::black_box(step(t)?);
    }
    Ok((args.steps * b, start.elapsed().as_secs_f64()))
}

fn offline(args: &Args, opts: EngineOptions) -> Result<(usize, f64)> {
    let weights = LoadedWeights::random(ModelKind::BiGru, args.seed)?;
    if args.path == PathKind::Reference {
        let model = blapose_model::BoneLengthBiGru::new(weights.var_builder())?;
        let frames = random_inputs(args.frames * INPUT_DIM, args.seed + 2);
        let x = frames_tensor(&frames, 1, args.frames)?;
        let start = Instant::now();
        std::hint::black_box(model.forward(&x, false)?.flatten_all()?.to_vec1::<f32>()?);
        return Ok((args.frames, start.elapsed().as_secs_f64()));
    }
    let engine = OfflineBiGruEngine::with_options(&weights, opts)?;
    let frames = random_inputs(args.frames * INPUT_DIM, args.seed + 2);
    engine.predict(&frames[..INPUT_DIM * args.frames.min(64)])?; // warm up
    let start = Instant::now();
    std::hint::black_box(engine.predict(&frames)?);
    Ok((args.frames, start.elapsed().as_secs_f64()))
}

//! `fps-table`: the paper's efficiency table (Table 4) measured on this machine.
//!
//! Protocol, as in the paper: online, batch 1, one output frame per step,
//! no test-time flip, `--steps` steps per measurement (10,000 in the
//! paper). A step is everything a real-time pipeline does for one new
//! frame:
//!
//! * **lifter alone**: append the frame to the sliding window, run the
//!   lifter on the window, read the pose back. Anatomy3D also advances its
//!   own bone-length branch on the new frame (its lengths are a running
//!   attention average over the stream, the online form of its video-level
//!   prediction).
//! * **with adjustment**: the above, plus BLAPose: one online GRU step on
//!   the new frame ([`OnlineGruEngine`], batch 1), the running mean of the
//!   per-frame length predictions (the reference's online use), and the
//!   adjustment of the lifter's pose ([`adjust_pose_lenient`]: decompose
//!   into directions, rebuild with the predicted lengths).
//! * **bone-length models alone**: our GRU step (+ running mean), and
//!   Anatomy3D's bone-length branch on the new frame.
//!
//! Weights are random (timing only; PyTorch-style initialization, so the
//! arithmetic is the trained models'). Each row is measured `--runs` times,
//! alternating "alone" and "with adjustment" so both see the same machine
//! load, and the median is reported, with the process's CPU use (CPU time
//! over wall time) so that runs on a shared machine can be judged. The
//! lifters run on the CPU (dense products in blapose-lifters' packed-weight
//! kernel, everything else in candle), with rayon's and candle's default
//! thread counts unless `--threads` is given; the GRU engine uses
//! `--gru-threads`.
//!
//! The steps themselves are [`blapose_bench::online`]'s and the timing
//! protocol [`blapose_bench::timing`]'s; this file is the table: its
//! rows, the paper's figures, and the report.

use std::hint::black_box;
use std::path::PathBuf;
use std::time::Instant;

use anyhow::{bail, Context, Result};
use blapose_bench::machine::{cpu_model, load_average};
use blapose_bench::online::{synthetic_stream, Adjuster, LifterStream};
use blapose_bench::timing::{measure, median_of, Measurement};
use clap::{Parser, ValueEnum};
use serde::Serialize;

use blapose_core::bones::adjust_pose_lenient;
use blapose_core::{Keypoints2d, Pose};
use blapose_lifters::{Anatomy3d, Anatomy3dConfig, Lifter, OnlineBoneLengths, ReferenceLifter};
use blapose_model::fast::{EngineOptions, OnlineGruEngine};
use blapose_model::{Isa, Precision};
use blapose_model::{LoadedWeights, ModelKind};

mod markdown;

use markdown::markdown;

/// Reproduce the paper's FPS table (online, batch 1, one frame per step).
#[derive(Parser, Debug)]
#[command(name = "fps-table", version)]
struct Args {
    /// Timed steps per measurement (the paper uses 10,000).
    #[arg(long, default_value_t = 10_000)]
    steps: usize,
    /// Measurements per row; the table reports their median.
    #[arg(long, default_value_t = 3)]
    runs: usize,
    /// Untimed steps before each measurement (fills caches and the window).
    #[arg(long, default_value_t = 100)]
    warmup: usize,
    /// Write the table as JSON here too.
    #[arg(long)]
    json: Option<PathBuf>,
    /// Worker threads of the GRU engine (the lifters use candle's default).
    #[arg(long, default_value_t = 1)]
    gru_threads: usize,
    /// Storage precision of the GRU engine's weights: f16 (the server's
    /// default) or f32.
    #[arg(long, default_value = "f16", value_parser = blapose_server::config::parse_precision)]
    gru_precision: Precision,
    /// Instruction set of the GRU engine (scalar, avx2, avx512); default:
    /// the best this CPU supports.
    #[arg(long)]
    gru_isa: Option<Isa>,
    /// Online GRU weights (safetensors); random weights when absent.
    #[arg(long)]
    gru_weights: Option<PathBuf>,
    /// Run each frame's GRU step concurrently with the lifter
    /// (`rayon::join` on the same pool; the GRU reads only the 2D frame),
    /// then adjust the lifter's pose. Default: one after the other, the
    /// paper's protocol.
    #[arg(long)]
    overlap: bool,
    /// Use the centred (non-causal) VideoPose3D and Anatomy3D; same cost.
    #[arg(long)]
    centred: bool,
    /// Only these rows (default: all).
    #[arg(long, value_enum, value_delimiter = ',')]
    only: Vec<RowKind>,
    /// Threads for the lifters' products and candle's element-wise ops
    /// (sets RAYON_NUM_THREADS and CANDLE_NUM_THREADS); default: the
    /// libraries' own default (one per core).
    #[arg(long)]
    threads: Option<usize>,
    /// Seed of the random weights.
    #[arg(long, default_value_t = 0)]
    seed: u64,
}

/// The rows of the paper's table.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum RowKind {
    Videopose3d,
    Anatomy3d,
    Poseformer,
    AnatomyBoneLength,
    Gru,
}

impl RowKind {
    const ALL: [RowKind; 5] = [
        RowKind::Videopose3d,
        RowKind::Anatomy3d,
        RowKind::Poseformer,
        RowKind::AnatomyBoneLength,
        RowKind::Gru,
    ];

    fn label(self) -> &'static str {
        match self {
            RowKind::Videopose3d => "VideoPose3D",
            RowKind::Anatomy3d => "Chen et al. (Anatomy3D)",
            RowKind::Poseformer => "PoseFormer",
            RowKind::AnatomyBoneLength => "Chen et al. bone-length branch",
            RowKind::Gru => "BLAPose GRU (ours)",
        }
    }

    /// The paper's figures (GTX 3060 Ti): FPS alone, FPS with adjustment.
    fn paper(self) -> (f64, Option<f64>) {
        match self {
            RowKind::Videopose3d => (958.0, Some(435.0)),
            RowKind::Anatomy3d => (197.0, Some(154.0)),
            RowKind::Poseformer => (379.0, Some(252.0)),
            RowKind::AnatomyBoneLength => (715.0, None),
            RowKind::Gru => (2097.0, None),
        }
    }
}

/// One row of the output.
#[derive(Debug, Serialize)]
struct Row {
    model: String,
    frames: Option<usize>,
    params: usize,
    fps: f64,
    fps_with_adjustment: Option<f64>,
    adjustment_overhead_pct: Option<f64>,
    paper_fps: f64,
    paper_fps_with_adjustment: Option<f64>,
    paper_overhead_pct: Option<f64>,
    mpjpe_mm: Option<f64>,
    /// Median share of the with-adjustment step time spent in the
    /// adjustment (timed inside the steps), %.
    adjustment_share_pct: Option<f64>,
    /// Median steps per CPU-second alone (FPS / CPU use): what the row
    /// would reach with its threads' CPUs to itself, cache sharing aside.
    fps_per_cpu_second: Option<f64>,
    /// Median CPU use (process CPU time / wall time, %) alone.
    cpu_pct: Option<f64>,
    /// Median CPU use with the adjustment.
    cpu_pct_with_adjustment: Option<f64>,
    runs: Vec<Measurement>,
    runs_with_adjustment: Vec<Measurement>,
}

impl Row {
    fn new(
        kind: RowKind,
        frames: Option<usize>,
        params: usize,
        alone: Vec<Measurement>,
        with: Vec<Measurement>,
    ) -> Self {
        let fps = median_of(&alone, |m| Some(m.fps)).unwrap_or(f64::NAN);
        let fps_with = median_of(&with, |m| Some(m.fps));
        let (paper, paper_with) = kind.paper();
        Self {
            model: kind.label().into(),
            frames,
            params,
            fps,
            fps_with_adjustment: fps_with,
            adjustment_overhead_pct: fps_with.map(|w| overhead_pct(fps, w)),
            paper_fps: paper,
            paper_fps_with_adjustment: paper_with,
            paper_overhead_pct: paper_with.map(|w| overhead_pct(paper, w)),
            mpjpe_mm: None,
            adjustment_share_pct: median_of(&with, |m| m.adjustment_share_pct),
            fps_per_cpu_second: median_of(&alone, |m| {
                m.cpu_pct.filter(|c| *c > 0.0).map(|c| 100.0 * m.fps / c)
            }),
            cpu_pct: median_of(&alone, |m| m.cpu_pct),
            cpu_pct_with_adjustment: median_of(&with, |m| m.cpu_pct),
            runs: alone,
            runs_with_adjustment: with,
        }
    }
}

/// The run's conditions, printed above the table and saved with it.
#[derive(Debug, Serialize)]
struct Conditions {
    steps: usize,
    runs: usize,
    warmup: usize,
    cpu: String,
    logical_cpus: usize,
    candle_threads: usize,
    /// `RAYON_NUM_THREADS` / `CANDLE_NUM_THREADS` as set for the run.
    thread_env: String,
    gru_threads: usize,
    gru_isa: String,
    gru_precision: String,
    gru_weights: String,
    causal_lifters: bool,
    /// The GRU step ran concurrently with the lifter (`--overlap`).
    overlap: bool,
    load_average_before: String,
    load_average_after: String,
    /// Median time per frame of the adjustment alone (GRU step, running
    /// mean, adjust_pose), microseconds.
    adjustment_alone_us: f64,
}

#[derive(Debug, Serialize)]
struct Report {
    conditions: Conditions,
    rows: Vec<Row>,
}

/// The models under test.
struct Models {
    videopose: Option<Box<dyn Lifter>>,
    poseformer: Option<Box<dyn Lifter>>,
    anatomy: Option<Anatomy3d>,
    gru: OnlineGruEngine,
}

fn overhead_pct(alone: f64, with: f64) -> f64 {
    100.0 * (1.0 - with / alone)
}

/// Measure a lifter row: alone and with the adjustment, interleaved.
fn lifter_row(
    args: &Args,
    kind: RowKind,
    lifter: &dyn Lifter,
    anatomy: Option<&Anatomy3d>,
    gru: &OnlineGruEngine,
    stream: &[Keypoints2d],
) -> Result<Row> {
    let (mut alone, mut with) = (Vec::new(), Vec::new());
    for run in 0..args.runs {
        let measure_alone = || -> Result<Measurement> {
            let mut s = LifterStream::new(lifter, anatomy);
            measure(stream, args.warmup, args.steps, |f| {
                black_box(s.step(f)?);
                Ok(())
            })
        };
        let measure_with = || -> Result<Measurement> {
            let mut s = LifterStream::new(lifter, anatomy);
            let mut adj = Adjuster::new(gru);
            // Per-step time of the adjustment part; the last `steps` are the timed ones.
            let mut adj_secs = Vec::with_capacity(args.warmup + args.steps);
            let mut m = measure(stream, args.warmup, args.steps, |f| {
                // The timed adjustment part: the GRU step and the rebuild
                // after the lifter, or only the rebuild when they overlap.
                let (pose, lengths, t) = if args.overlap {
                    let (pose, lengths) = rayon::join(|| s.step(f), || adj.lengths(f));
                    (pose?, lengths?, Instant::now())
                } else {
                    let pose = s.step(f)?;
                    let t = Instant::now();
                    (pose, adj.lengths(f)?, t)
                };
                black_box(adjust_pose_lenient(&pose, &lengths)?);
                adj_secs.push(t.elapsed().as_secs_f64());
                Ok(())
            })?;
            let timed: f64 = adj_secs[adj_secs.len().saturating_sub(args.steps)..]
                .iter()
                .sum();
            m.adjustment_share_pct = Some(100.0 * timed * m.fps / args.steps as f64);
            Ok(m)
        };
        // Alternate the order so neither variant always runs first.
        if run % 2 == 0 {
            alone.push(measure_alone()?);
            with.push(measure_with()?);
        } else {
            with.push(measure_with()?);
            alone.push(measure_alone()?);
        }
        eprintln!(
            "  {} run {}: {:.1} FPS alone, {:.1} with adjustment",
            kind.label(),
            run + 1,
            alone[run].fps,
            with[run].fps
        );
    }
    Ok(Row::new(
        kind,
        Some(lifter.receptive_field()),
        lifter.params(),
        alone,
        with,
    ))
}

/// Measure a row that has no adjusted variant.
fn single_row<'m>(
    args: &Args,
    kind: RowKind,
    params: usize,
    mut make_step: impl FnMut() -> Box<dyn FnMut(&Keypoints2d) -> Result<()> + 'm>,
    stream: &[Keypoints2d],
) -> Result<Row> {
    let mut runs = Vec::new();
    for run in 0..args.runs {
        let step = make_step();
        runs.push(measure(stream, args.warmup, args.steps, step)?);
        eprintln!(
            "  {} run {}: {:.1} FPS",
            kind.label(),
            run + 1,
            runs[run].fps
        );
    }
    Ok(Row::new(kind, None, params, runs, Vec::new()))
}

fn build_models(args: &Args, rows: &[RowKind]) -> Result<Models> {
    let causal = !args.centred;
    let weights = match &args.gru_weights {
        Some(path) => blapose_model::weights::load(path, ModelKind::Gru)
            .with_context(|| format!("loading GRU weights {}", path.display()))?,
        None => LoadedWeights::random(ModelKind::Gru, args.seed)?,
    };
    let want = |k: RowKind| rows.contains(&k);
    Ok(Models {
        videopose: want(RowKind::Videopose3d)
            .then(|| ReferenceLifter::VideoPose3d.random(causal, args.seed))
            .transpose()?,
        poseformer: want(RowKind::Poseformer)
            .then(|| ReferenceLifter::PoseFormer.random(causal, args.seed))
            .transpose()?,
        anatomy: (want(RowKind::Anatomy3d) || want(RowKind::AnatomyBoneLength))
            .then(|| {
                Anatomy3d::random(
                    Anatomy3dConfig::receptive_field_243().with_causal(causal),
                    args.seed,
                )
            })
            .transpose()?,
        gru: OnlineGruEngine::with_options(
            &weights,
            EngineOptions {
                precision: args.gru_precision,
                isa: args.gru_isa,
                ..EngineOptions::threads(args.gru_threads)
            },
        )?,
    })
}

/// Median per-frame time of the adjustment alone, in microseconds.
fn adjustment_alone_us(args: &Args, models: &Models, stream: &[Keypoints2d]) -> Result<f64> {
    let pose: Pose = std::array::from_fn(|j| {
        let [x, y] = stream[0][j];
        [x, y, 0.1 * j as f32]
    });
    let mut runs = Vec::new();
    for _ in 0..args.runs {
        let mut adj = Adjuster::new(&models.gru);
        runs.push(measure(stream, args.warmup, args.steps, |f| {
            black_box(adj.adjust(f, &pose)?);
            Ok(())
        })?);
    }
    Ok(1e6 / median_of(&runs, |m| Some(m.fps)).unwrap_or(f64::NAN))
}

fn main() -> Result<()> {
    let args = Args::parse();
    if args.steps == 0 || args.runs == 0 {
        bail!("--steps and --runs must be at least 1");
    }
    if let Some(n) = args.threads {
        if n == 0 {
            bail!("--threads must be at least 1");
        }
        // Before anything starts a thread pool: both read these once.
        std::env::set_var("RAYON_NUM_THREADS", n.to_string());
        std::env::set_var("CANDLE_NUM_THREADS", n.to_string());
    }
    let thread_env = ["RAYON_NUM_THREADS", "CANDLE_NUM_THREADS"]
        .map(|v| {
            format!(
                "{v}={}",
                std::env::var(v).unwrap_or_else(|_| "unset".into())
            )
        })
        .join(", ");
    let rows: Vec<RowKind> = if args.only.is_empty() {
        RowKind::ALL.to_vec()
    } else {
        args.only.clone()
    };
    let load_before = load_average();
    eprintln!("building models (random weights)...");
    let models = build_models(&args, &rows)?;
    let stream = synthetic_stream(600);
    let mut out = Vec::new();
    for &kind in &rows {
        let row = match kind {
            RowKind::Videopose3d => {
                let m = models
                    .videopose
                    .as_deref()
                    .context("VideoPose3D not built")?;
                lifter_row(&args, kind, m, None, &models.gru, &stream)?
            }
            RowKind::Poseformer => {
                let m = models
                    .poseformer
                    .as_deref()
                    .context("PoseFormer not built")?;
                lifter_row(&args, kind, m, None, &models.gru, &stream)?
            }
            RowKind::Anatomy3d => {
                let m = models.anatomy.as_ref().context("Anatomy3D not built")?;
                lifter_row(&args, kind, m, Some(m), &models.gru, &stream)?
            }
            RowKind::AnatomyBoneLength => {
                let branch = models
                    .anatomy
                    .as_ref()
                    .context("Anatomy3D not built")?
                    .bone_length();
                single_row(
                    &args,
                    kind,
                    branch.params(),
                    || {
                        let mut state = OnlineBoneLengths::new();
                        Box::new(move |f: &Keypoints2d| {
                            let t = blapose_lifters::keypoints_tensor(std::slice::from_ref(f))?;
                            black_box(branch.step(&t, &mut state)?);
                            Ok(())
                        })
                    },
                    &stream,
                )?
            }
            RowKind::Gru => single_row(
                &args,
                kind,
                blapose_model::PARAMS,
                || {
                    let mut adj = Adjuster::new(&models.gru);
                    Box::new(move |f: &Keypoints2d| {
                        black_box(adj.lengths(f)?);
                        Ok(())
                    })
                },
                &stream,
            )?,
        };
        out.push(row);
    }
    let adjustment_us = adjustment_alone_us(&args, &models, &stream)?;
    let report = Report {
        conditions: Conditions {
            steps: args.steps,
            runs: args.runs,
            warmup: args.warmup,
            cpu: cpu_model(),
            logical_cpus: std::thread::available_parallelism()
                .map(|n| n.get())
                .unwrap_or(1),
            candle_threads: candle_core::utils::get_num_threads(),
            thread_env,
            gru_threads: models.gru.threads(),
            gru_isa: format!("{:?}", models.gru.isa()),
            gru_precision: format!("{:?}", models.gru.precision()),
            gru_weights: args
                .gru_weights
                .as_ref()
                .map(|p| p.display().to_string())
                .unwrap_or_else(|| format!("random (seed {})", args.seed)),
            causal_lifters: !args.centred,
            overlap: args.overlap,
            load_average_before: load_before,
            load_average_after: load_average(),
            adjustment_alone_us: adjustment_us,
        },
        rows: out,
    };
    println!("{}", markdown(&report));
    if let Some(path) = &args.json {
        let json = serde_json::to_string_pretty(&report)?;
        std::fs::write(path, json).with_context(|| format!("writing {}", path.display()))?;
        eprintln!("wrote {}", path.display());
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn m(fps: f64, cpu: Option<f64>) -> Measurement {
        Measurement::new(fps, cpu)
    }

    #[test]
    fn rows_compute_overheads_like_the_paper() {
        let row = Row::new(
            RowKind::Videopose3d,
            Some(243),
            16_952_371,
            vec![m(100.0, None)],
            vec![m(90.0, None)],
        );
        assert!((row.adjustment_overhead_pct.unwrap() - 10.0).abs() < 1e-9);
        // 958 -> 435 FPS is the paper's 54.6 % loss.
        assert!((row.paper_overhead_pct.unwrap() - 54.59).abs() < 0.01);
        let gru = Row::new(
            RowKind::Gru,
            None,
            2_390_784,
            vec![m(3000.0, Some(99.0))],
            Vec::new(),
        );
        assert_eq!((gru.fps_with_adjustment, gru.paper_fps), (None, 2097.0));
        // 3000 FPS while getting 99 % of a CPU is 3030 steps per CPU-second.
        assert!((gru.fps_per_cpu_second.unwrap() - 3030.3).abs() < 0.1);
        assert_eq!(row.fps_per_cpu_second, None);
    }

    #[test]
    fn markdown_flags_quick_runs_and_formats_numbers() {
        use crate::markdown::thousands;
        assert_eq!(thousands(59_177_580), "59,177,580");
        assert_eq!(thousands(715), "715");
        let report = Report {
            conditions: Conditions {
                steps: 100,
                runs: 1,
                warmup: 0,
                cpu: "cpu".into(),
                logical_cpus: 2,
                candle_threads: 2,
                thread_env: String::new(),
                gru_threads: 1,
                gru_isa: "Avx512".into(),
                gru_precision: "F16".into(),
                gru_weights: "random".into(),
                causal_lifters: true,
                overlap: false,
                load_average_before: "0 0 0".into(),
                load_average_after: "0 0 0".into(),
                adjustment_alone_us: 400.0,
            },
            rows: vec![Row::new(
                RowKind::Gru,
                None,
                2_390_784,
                vec![m(2500.0, Some(100.0))],
                Vec::new(),
            )],
        };
        let md = markdown(&report);
        assert!(md.contains("fewer than the paper's 10,000"));
        assert!(md.contains("| BLAPose GRU (ours) | - | 2,390,784 | 2500.0 | - | - | - | 2097 |"));
        let json = serde_json::to_value(&report).unwrap();
        assert_eq!(json["rows"][0]["paper_fps"], 2097.0);
        assert!(json["rows"][0]["frames"].is_null());
    }
}

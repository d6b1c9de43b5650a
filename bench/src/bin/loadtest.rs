//! `loadtest`: N concurrent gRPC streams against a blapose server.
//!
//! ```sh
//! cargo run --release -p blapose-bench --bin loadtest -- --spawn --streams 256 --frames 1000
//! cargo run --release -p blapose-bench --bin loadtest -- --server http://127.0.0.1:50051 \
//!     --metrics http://127.0.0.1:9090/metrics --streams 16 --frames 500 --rate 30
//! cargo run --release -p blapose-bench --bin loadtest -- --spawn --idle --streams 1024
//! ```
//!
//! Prints a markdown table, writes JSON with `--json`, and ends with one
//! machine-readable line: `frames_per_second=<number>` (or, with `--idle`,
//! `bytes_per_session=<number>`). The logic lives in
//! `blapose_bench::loadtest`; this file only maps flags onto it.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

use anyhow::{bail, Context, Result};
use blapose_bench::loadtest::driver::StreamOptions;
use blapose_bench::loadtest::spawn::SpawnOptions;
use blapose_bench::loadtest::workload::default_examples_dir;
use blapose_bench::loadtest::{LoadTest, Target, Workmode};
use clap::Parser;

/// Load-test a blapose server: concurrent sessions replaying the example
/// sequences, reporting throughput, latency percentiles, errors and the
/// server's batch sizes (or, with --idle, memory per idle session).
#[derive(Debug, Parser)]
#[command(name = "loadtest", version)]
struct Args {
    /// Start a server in this process on a loopback port, with the embedded
    /// default weights.
    #[arg(long, conflicts_with = "server", required_unless_present = "server")]
    spawn: bool,
    /// URL of a running server (e.g. http://127.0.0.1:50051).
    #[arg(long, value_name = "URL")]
    server: Option<String>,
    /// The running server's metrics page (e.g. http://127.0.0.1:9090/metrics),
    /// for the batch-size distribution; with --spawn the metrics are always read.
    #[arg(long, value_name = "URL", requires = "server")]
    metrics: Option<String>,
    /// The running server's process id: --idle then reads its resident memory.
    #[arg(long, value_name = "PID", requires = "server")]
    server_pid: Option<u32>,
    /// Concurrent streams (sessions); with --idle, the sessions to hold.
    #[arg(long, default_value_t = 16)]
    streams: usize,
    /// Frames each stream sends (cycling through its example sequence).
    #[arg(long, default_value_t = 1000)]
    frames: u64,
    /// Frames per second per stream; default: as fast as the window allows.
    #[arg(long, value_name = "FPS")]
    rate: Option<f64>,
    /// Frames a stream may have sent but not yet seen answered.
    #[arg(long, default_value_t = 8)]
    inflight: usize,
    /// HTTP/2 connections the streams are spread over (default: one per 32
    /// streams, at most 16).
    #[arg(long)]
    connections: Option<usize>,
    /// Deadline for the whole run, seconds (it never waits longer, even if
    /// the server hangs or dies).
    #[arg(long, default_value_t = 120.0)]
    timeout: f64,
    /// Hold --streams idle sessions open and report the resident memory per
    /// session instead of streaming frames.
    #[arg(long)]
    idle: bool,
    /// With --idle: seconds to hold the sessions before the second reading.
    #[arg(long, default_value_t = 1.0)]
    hold: f64,
    /// Open every session with the causal motion stage (smoothed directions,
    /// the pelvis placed): its cost against a run without.
    #[arg(long)]
    motion: bool,
    /// Directory of .npz replay files to send (default: the workspace's examples/).
    #[arg(long, value_name = "DIR")]
    examples: Option<PathBuf>,
    /// Write the report as JSON here too.
    #[arg(long, value_name = "PATH")]
    json: Option<PathBuf>,
    /// With --spawn: metrics listen address (port 0: any free port).
    #[arg(long, default_value = "127.0.0.1:0")]
    metrics_addr: SocketAddr,
    /// With --spawn: most frames per batched GRU step.
    #[arg(long, requires = "spawn")]
    max_batch: Option<usize>,
    /// With --spawn: longest wait for a fuller batch, microseconds.
    #[arg(long, requires = "spawn")]
    max_queue_delay_us: Option<u64>,
    /// With --spawn: threads of one batched GRU step.
    #[arg(long, requires = "spawn")]
    compute_threads: Option<usize>,
    /// With --spawn: storage precision of the GRU weights (f32, f16, bf16 or
    /// auto; default: auto, as the server's).
    #[arg(long, requires = "spawn", value_parser = blapose_server::config::parse_precision)]
    weight_precision: Option<blapose_model::Precision>,
}

fn main() -> Result<()> {
    let args = Args::parse();
    let test = load_test(&args)?;
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("cannot start the tokio runtime")?;
    let result = runtime.block_on(test.run());
    // Never wait on a stuck task at exit.
    runtime.shutdown_timeout(Duration::from_secs(1));
    let report = result?;
    print!("{}", report.markdown());
    if let Some(path) = &args.json {
        let json = serde_json::to_string_pretty(&report)?;
        std::fs::write(path, json + "\n")
            .with_context(|| format!("cannot write {}", path.display()))?;
    }
    println!("{}", report.summary_line());
    Ok(())
}

fn load_test(args: &Args) -> Result<LoadTest> {
    if args.streams == 0 || args.inflight == 0 || (!args.idle && args.frames == 0) {
        bail!("--streams, --frames and --inflight must be positive");
    }
    if args.rate.is_some_and(|r| !(r.is_finite() && r > 0.0)) {
        bail!("--rate must be a positive number of frames per second");
    }
    if !(args.timeout.is_finite() && args.timeout > 0.0) || args.hold.is_nan() || args.hold < 0.0 {
        bail!("--timeout must be positive and --hold non-negative");
    }
    let target = if args.spawn {
        let mut options = SpawnOptions {
            metrics_addr: Some(args.metrics_addr),
            ..SpawnOptions::default()
        };
        if let Some(b) = args.max_batch {
            options.max_batch = b;
        }
        if let Some(us) = args.max_queue_delay_us {
            options.max_queue_delay = Duration::from_micros(us);
        }
        if let Some(t) = args.compute_threads {
            options.compute_threads = t;
        }
        if let Some(p) = args.weight_precision {
            options.weight_precision = p;
        }
        Target::Spawn(options)
    } else {
        let url = args
            .server
            .clone()
            .context("pass --spawn or --server URL")?;
        Target::Remote {
            url,
            metrics_url: args.metrics.clone(),
            server_pid: args.server_pid,
        }
    };
    let mode = if args.idle {
        Workmode::Idle {
            sessions: args.streams,
            hold: Duration::from_secs_f64(args.hold),
        }
    } else {
        Workmode::Stream(StreamOptions {
            streams: args.streams,
            frames: args.frames,
            rate: args.rate,
            inflight: args.inflight,
        })
    };
    Ok(LoadTest {
        target,
        mode,
        connections: args
            .connections
            .unwrap_or_else(|| args.streams.div_ceil(32).clamp(1, 16))
            .clamp(1, args.streams),
        timeout: Duration::from_secs_f64(args.timeout),
        examples: args.examples.clone().unwrap_or_else(default_examples_dir),
        motion: args.motion,
    })
}

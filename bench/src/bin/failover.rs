//! `failover`: sessions through a load balancer while a replica goes away.
//!
//! ```sh
//! failover --server http://127.0.0.1:50060 --sessions 32 --fps 40 \
//!     --victim-pid 1234 --signal kill --json kill.json
//! failover --server http://127.0.0.1:50060 --sessions 32 --throughput
//! ```
//!
//! Without `--throughput` it streams the sessions twice, undisturbed and
//! then with `--signal` sent to `--victim-pid` once `--at` of all frames
//! were answered, and reports lost, duplicated and changed frames and the
//! longest gap (`blapose_bench::failover`); it exits non-zero unless every
//! frame was answered exactly once with the reference's bone lengths
//! (within `--tolerance`). With `--throughput` it streams the sessions once,
//! unpaced, and reports frames per second. `deploy/failover-test.sh` runs
//! both against three replicas behind HAProxy.

use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Instant;

use anyhow::{bail, ensure, Context, Result};
use blapose_bench::failover::{compare, frames_per_second, run_sessions};
use blapose_bench::loadtest::workload::{default_examples_dir, replay_files};
use blapose_client::{Client, ClientConfig, ReplayOptions, Sequence};
use clap::{Parser, ValueEnum};

/// Stream sessions through a balancer while one replica is killed or
/// drained, and check that every session carries on exactly.
#[derive(Debug, Parser)]
#[command(name = "failover", version)]
struct Args {
    /// The balancer's (or one server's) URL.
    #[arg(long, value_name = "URL")]
    server: String,
    /// Concurrent sessions; session i replays example i mod n.
    #[arg(long, default_value_t = 32)]
    sessions: usize,
    /// Directory of replay files (.npz) to stream.
    #[arg(long, value_name = "DIR")]
    examples: Option<PathBuf>,
    /// Frames per second each session sends (both runs).
    #[arg(long, default_value_t = 40.0)]
    fps: f64,
    /// Frames in flight per session at most.
    #[arg(long, default_value_t = 8)]
    window: usize,
    /// The process to signal mid-stream (a replica).
    #[arg(long, value_name = "PID", required_unless_present = "throughput")]
    victim_pid: Option<u32>,
    /// The signal: kill (SIGKILL, a crash) or term (SIGTERM, a drain).
    #[arg(long, value_enum, default_value_t = Signal::Kill)]
    signal: Signal,
    /// Send the signal once this share of all frames was answered.
    #[arg(long, default_value_t = 0.3)]
    at: f64,
    /// Largest bone-length difference from the reference run, in metres,
    /// that still passes.
    #[arg(long, default_value_t = 1e-6)]
    tolerance: f64,
    /// Only measure frames per second: unpaced runs (--rounds), no signal.
    #[arg(long)]
    throughput: bool,
    /// With --throughput: runs to take the median frames per second of.
    #[arg(long, default_value_t = 9)]
    rounds: usize,
    /// Write the report as JSON.
    #[arg(long, value_name = "PATH")]
    json: Option<PathBuf>,
}

#[derive(Debug, Clone, Copy, ValueEnum)]
enum Signal {
    Kill,
    Term,
}

impl Signal {
    fn name(self) -> &'static str {
        match self {
            Signal::Kill => "KILL",
            Signal::Term => "TERM",
        }
    }
}

fn load_sequences(dir: &std::path::Path) -> Result<Vec<Arc<Sequence>>> {
    replay_files(dir)?
        .iter()
        .map(|p| {
            let mut seq = Sequence::load(p, None)?;
            // The default model serves every session alike.
            seq.camera = None;
            Ok(Arc::new(seq))
        })
        .collect()
}

fn send_signal(pid: u32, signal: Signal) -> Result<()> {
    let status = std::process::Command::new("kill")
        .args(["-s", signal.name(), &pid.to_string()])
        .status()
        .context("running kill")?;
    ensure!(status.success(), "kill -s {} {pid} failed", signal.name());
    Ok(())
}

fn write_json(path: &std::path::Path, value: &serde_json::Value) -> Result<()> {
    std::fs::write(path, serde_json::to_string_pretty(value)? + "\n")
        .with_context(|| format!("writing {}", path.display()))
}

#[tokio::main]
async fn main() -> Result<()> {
    let args = Args::parse();
    ensure!(args.sessions > 0, "--sessions must be at least 1");
    ensure!(
        (0.0..1.0).contains(&args.at),
        "--at must be in [0, 1), got {}",
        args.at
    );
    let dir = args.examples.clone().unwrap_or_else(default_examples_dir);
    let sequences = load_sequences(&dir)?;
    let client = Client::connect(ClientConfig::new(args.server.clone())).await?;
    let total: usize = (0..args.sessions)
        .map(|i| sequences[i % sequences.len()].len())
        .sum();
    let no_progress: Arc<dyn Fn(usize) + Send + Sync> = Arc::new(|_| {});

    if args.throughput {
        let options = ReplayOptions {
            window: args.window,
            ..ReplayOptions::default()
        };
        let mut rates = Vec::with_capacity(args.rounds.max(1));
        let mut failed = 0;
        for _ in 0..args.rounds.max(1) {
            let started = Instant::now();
            let runs = run_sessions(
                &client,
                &sequences,
                args.sessions,
                &options,
                no_progress.clone(),
            )
            .await;
            rates.push(frames_per_second(&runs, started.elapsed()));
            failed += runs.iter().filter(|r| r.result.is_err()).count();
        }
        rates.sort_by(f64::total_cmp);
        let fps = rates[rates.len() / 2];
        println!(
            "{} sessions, {total} frames, unpaced (window {}), median of {} runs: {fps:.0} frames/s (min {:.0}, max {:.0}), {failed} sessions failed",
            args.sessions,
            args.window,
            rates.len(),
            rates[0],
            rates[rates.len() - 1]
        );
        if let Some(path) = &args.json {
            write_json(
                path,
                &serde_json::json!({"sessions": args.sessions, "frames": total,
                    "rounds": rates.len(), "frames_per_second": fps,
                    "frames_per_second_all": rates, "sessions_failed": failed}),
            )?;
        }
        ensure!(failed == 0, "{failed} sessions failed");
        return Ok(());
    }

    let options = ReplayOptions {
        fps: Some(args.fps),
        window: args.window,
        ..ReplayOptions::default()
    };
    println!(
        "reference: {} sessions, {total} frames at {} fps each, undisturbed",
        args.sessions, args.fps
    );
    let reference = run_sessions(&client, &sequences, args.sessions, &options, no_progress).await;
    if let Some(bad) = reference.iter().find_map(|r| r.result.as_ref().err()) {
        bail!("the undisturbed reference run failed: {bad}");
    }

    let Some(pid) = args.victim_pid else {
        bail!("--victim-pid is required without --throughput");
    };
    let signal = args.signal;
    let threshold = ((total as f64) * args.at).ceil() as usize;
    let fired = Arc::new(AtomicBool::new(false));
    let signalled_at = Arc::new(std::sync::Mutex::new(None));
    let on_progress: Arc<dyn Fn(usize) + Send + Sync> = {
        let fired = fired.clone();
        let signalled_at = signalled_at.clone();
        Arc::new(move |answered| {
            if answered >= threshold && !fired.swap(true, Ordering::SeqCst) {
                let result = send_signal(pid, signal);
                *signalled_at.lock().unwrap_or_else(|e| e.into_inner()) =
                    Some((answered, result.map_err(|e| e.to_string())));
            }
        })
    };
    println!(
        "disturbed: the same, with SIG{} to process {pid} after {threshold} answered frames",
        signal.name()
    );
    let runs = run_sessions(&client, &sequences, args.sessions, &options, on_progress).await;
    let signalled = signalled_at
        .lock()
        .unwrap_or_else(|e| e.into_inner())
        .clone();
    match &signalled {
        Some((_, Err(e))) => bail!("sending the signal failed: {e}"),
        None => bail!("the run ended before {threshold} frames were answered; no signal was sent"),
        Some((_, Ok(()))) => {}
    }
    let report = compare(&reference, &runs);
    println!("| sessions | resumed | failed | frames | lost | duplicated | max length diff (m) | max pose diff (m) | longest gap (ms) | reference longest gap (ms) |");
    println!("|---|---|---|---|---|---|---|---|---|---|");
    println!(
        "| {} | {} | {} | {} | {} | {} | {:.1e} | {:.1e} | {:.0} | {:.0} |",
        report.sessions,
        report.sessions_resumed,
        report.sessions_failed,
        report.frames,
        report.frames_lost,
        report.frames_duplicated,
        report.max_length_diff_m,
        report.max_pose_diff_m,
        report.gap_ms_max,
        report.reference_gap_ms_max
    );
    if let Some(e) = &report.first_error {
        println!("first error: {e}");
    }
    if let Some(path) = &args.json {
        let mut value = serde_json::to_value(&report)?;
        value["signal"] = format!("SIG{}", signal.name()).into();
        value["signalled_after_frames"] = signalled.map(|s| s.0).into();
        write_json(path, &value)?;
    }
    ensure!(
        report.sessions_resumed > 0,
        "no session was resumed: the signalled replica served none of them"
    );
    ensure!(
        report.frames_lost == 0 && report.frames_duplicated == 0 && report.sessions_failed == 0,
        "frames were lost ({}) or duplicated ({}), or sessions failed ({})",
        report.frames_lost,
        report.frames_duplicated,
        report.sessions_failed
    );
    ensure!(
        report.max_length_diff_m <= args.tolerance,
        "bone lengths differ from the undisturbed run by {:.3e} m (> {:.1e})",
        report.max_length_diff_m,
        args.tolerance
    );
    println!("failover ok");
    Ok(())
}

//! The `loadtest` binary end to end: a small run against a server it
//! spawns in its own process (so the process-global metrics recorder is its
//! own), checking that every frame was answered, nothing failed, and the
//! JSON report has the agreed fields with sane values. No timing is
//! asserted: the machine may be busy.

use std::path::PathBuf;
use std::process::Command;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;

use blapose_server::backend::{Backend, BackendError, SequenceBackend};
use blapose_server::{Family, ModelProvider, WeightsProvider};

use serde_json::Value;

fn temp_json(name: &str) -> PathBuf {
    std::env::temp_dir().join(format!(
        "blapose-loadtest-{name}-{}.json",
        std::process::id()
    ))
}

fn run(args: &[&str]) -> (String, String, bool) {
    let out = Command::new(env!("CARGO_BIN_EXE_loadtest"))
        .args(args)
        .output()
        .expect("run loadtest");
    (
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
        out.status.success(),
    )
}

#[test]
fn four_streams_of_fifty_frames_are_all_answered() {
    let json = temp_json("streams");
    let (stdout, stderr, ok) = run(&[
        "--spawn",
        "--streams",
        "4",
        "--frames",
        "50",
        "--inflight",
        "4",
        "--timeout",
        "60",
        "--json",
        json.to_str().unwrap(),
    ]);
    assert!(ok, "loadtest failed\nstdout:\n{stdout}\nstderr:\n{stderr}");
    let last = stdout.lines().last().unwrap_or_default();
    let fps: f64 = last
        .strip_prefix("frames_per_second=")
        .unwrap_or_else(|| panic!("last line {last:?}"))
        .parse()
        .unwrap();
    assert!(fps > 0.0);
    assert!(stdout.contains("| streams |"), "{stdout}");

    let v: Value = serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    std::fs::remove_file(&json).ok();
    assert_eq!(v["streams"], 4);
    assert_eq!(v["frames"], 200, "{v:#}");
    assert_eq!(v["frames_sent"], 200);
    assert_eq!(v["errors"], serde_json::json!({}), "{v:#}");
    assert!(v["frames_per_second"].as_f64().unwrap() > 0.0);
    let lat = &v["latency_ms"];
    let (p50, p90, p99, max) = (
        lat["p50"].as_f64().unwrap(),
        lat["p90"].as_f64().unwrap(),
        lat["p99"].as_f64().unwrap(),
        lat["max"].as_f64().unwrap(),
    );
    assert!(0.0 < p50 && p50 <= p90 && p90 <= p99 && p99 <= max, "{lat}");
    // Every frame went through a batched step; the server ran at least
    // frames / streams steps (one frame per session per step).
    let b = &v["batch_sizes"];
    let steps = b["steps"].as_u64().unwrap();
    assert!((50..=200).contains(&steps), "{b}");
    let mean = b["mean"].as_f64().unwrap();
    assert!((200.0 / steps as f64 - mean).abs() < 1e-6, "{b}");
    let bucketed: u64 = b["buckets"]
        .as_array()
        .unwrap()
        .iter()
        .map(|x| x["steps"].as_u64().unwrap())
        .sum();
    assert_eq!(bucketed, steps);
}

#[test]
fn idle_mode_reports_memory_per_session() {
    let json = temp_json("idle");
    let (stdout, stderr, ok) = run(&[
        "--spawn",
        "--idle",
        "--streams",
        "32",
        "--hold",
        "0.1",
        "--timeout",
        "60",
        "--json",
        json.to_str().unwrap(),
    ]);
    assert!(ok, "loadtest failed\nstdout:\n{stdout}\nstderr:\n{stderr}");
    assert!(
        stdout
            .lines()
            .last()
            .unwrap()
            .starts_with("bytes_per_session="),
        "{stdout}"
    );
    let v: Value = serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    std::fs::remove_file(&json).ok();
    assert_eq!(v["mode"], "idle");
    assert_eq!(v["errors"], serde_json::json!({}), "{v:#}");
    let idle = &v["idle"];
    assert_eq!(idle["sessions"], 32);
    // Gauges set concurrently by many streams: present and in range
    // (their exact value is informational).
    for gauge in ["server_sessions", "server_streams"] {
        let g = idle[gauge]
            .as_f64()
            .unwrap_or_else(|| panic!("{gauge}: {idle}"));
        assert!((0.0..=32.0).contains(&g), "{gauge}: {idle}");
    }
    if std::path::Path::new("/proc/self/status").exists() {
        assert!(idle["bytes_per_session"].is_f64(), "{idle}");
    }
}

#[test]
fn an_unreachable_server_is_a_clear_error() {
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let url = format!("http://127.0.0.1:{port}");
    let (stdout, stderr, ok) = run(&["--server", &url, "--streams", "1", "--frames", "1"]);
    assert!(!ok, "{stdout}");
    assert!(stderr.contains(&url), "{stderr}");
    assert!(!stderr.contains("panicked"), "{stderr}");
}

/// A server that shuts down mid-run: the run ends with the streams' status
/// counted (not a hang until the deadline, not a panic).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_server_that_goes_away_mid_run_is_counted_not_waited_for() {
    use std::time::Duration;

    use blapose_bench::loadtest::driver::StreamOptions;
    use blapose_bench::loadtest::workload::default_examples_dir;
    use blapose_bench::loadtest::{LoadTest, Target, Workmode};

    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let config = blapose_server::ServerConfig {
        shutdown_grace: Duration::from_secs(1),
        ..Default::default()
    };
    let steps = Arc::new(AtomicUsize::new(0));
    let provider = WeightsProvider::load(
        Family::Default,
        &config.weights,
        &config.bigru_weights,
        config.compute_threads,
        config.weight_precision,
    )
    .unwrap();
    let provider = Counted {
        inner: Arc::new(provider),
        steps: steps.clone(),
    };
    let handle = blapose_server::spawn_with_provider(config, listener, Arc::new(provider))
        .await
        .unwrap();
    let warm_up = steps.load(Ordering::SeqCst);
    let test = LoadTest {
        target: Target::Remote {
            url: format!("http://{}", handle.local_addr()),
            metrics_url: None,
            server_pid: None,
        },
        // Far more frames than could be sent before the shutdown below.
        mode: Workmode::Stream(StreamOptions {
            streams: 4,
            frames: 1_000_000,
            rate: Some(200.0),
            inflight: 2,
        }),
        connections: 1,
        timeout: Duration::from_secs(120),
        examples: default_examples_dir(),
        motion: false,
    };
    let run = tokio::spawn(async move { test.run().await });
    // Shut down once the streams are under way: the model has run steps
    // beyond its warm-up (polled; bounded by a count, not timed).
    for poll in 0.. {
        if steps.load(Ordering::SeqCst) > warm_up + 4 {
            break;
        }
        assert!(poll < 100_000, "the load test never sent a frame");
        tokio::time::sleep(Duration::from_millis(2)).await;
    }
    handle.shutdown().await.unwrap();
    let report = run
        .await
        .unwrap()
        .expect("a report despite the server going away");
    assert!(report.frames < 4_000_000);
    assert!(report.error_count() > 0, "{:?}", report.errors);
    assert!(
        !report.errors.contains_key("client:deadline"),
        "waited for the deadline: {:?}",
        report.errors
    );
    assert!(
        report.errors.keys().any(|k| k.starts_with("status:")),
        "{:?}",
        report.errors
    );
}

/// The server's own models, counting the online steps they run, so a test
/// knows when frames are being served without sleeping on it.
struct Counted {
    inner: Arc<dyn ModelProvider>,
    steps: Arc<AtomicUsize>,
}

struct CountedStep {
    inner: Box<dyn Backend>,
    steps: Arc<AtomicUsize>,
}

impl Backend for CountedStep {
    fn step(
        &mut self,
        inputs: &[f32],
        hidden: &mut [f32],
        lengths_out: &mut [f32],
        batch: usize,
    ) -> Result<(), BackendError> {
        self.steps.fetch_add(1, Ordering::SeqCst);
        self.inner.step(inputs, hidden, lengths_out, batch)
    }
}

impl ModelProvider for Counted {
    fn online(&self) -> Result<Box<dyn Backend>, BackendError> {
        Ok(Box::new(CountedStep {
            inner: self.inner.online()?,
            steps: self.steps.clone(),
        }))
    }
    fn offline(&self) -> Result<Box<dyn SequenceBackend>, BackendError> {
        self.inner.offline()
    }
    fn describe(&self) -> Vec<blapose_proto::v1::ModelDescription> {
        self.inner.describe()
    }
    fn camera_aware(&self) -> Option<Arc<dyn ModelProvider>> {
        self.inner.camera_aware()
    }
    fn model_input(&self) -> blapose_server::ModelInput {
        self.inner.model_input()
    }
}

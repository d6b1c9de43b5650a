//! The gRPC load test behind the `loadtest` binary.
//!
//! It answers the operator's questions about a blapose server: how many
//! frames per second it sustains for N concurrent streams, at what
//! per-frame latency, whether anything fails under load, how full its
//! batches get, and what an idle session costs in memory. Everything goes
//! through the real stack (the client library, HTTP/2, tonic, the server's
//! stream tasks and batcher), against either a server started in this
//! process ([`Target::Spawn`], no set-up) or a running one
//! ([`Target::Remote`]).
//!
//! Modules: [`workload`] (the example sequences sent), [`driver`] (the
//! streams), [`prom`] (reading the server's Prometheus page), [`stats`]
//! (percentiles), [`report`] (markdown and JSON), [`spawn`] (the
//! in-process server).

pub mod driver;
pub mod prom;
pub mod report;
pub mod spawn;
pub mod stats;
pub mod workload;

use std::path::PathBuf;
use std::time::{Duration, Instant};

use blapose_client::ClientError;
use blapose_server::metrics::{BATCH_SIZE, SESSIONS, STREAMS};
use blapose_server::ServerError;

use crate::machine::process_cpu_seconds;
use driver::{StreamOptions, StreamStats};
use prom::Histogram;
use report::{BatchSizes, IdleMemory, Mode, Report};
use spawn::SpawnOptions;
use stats::LatencyMs;
use workload::{Workload, WorkloadError};

/// Which server to load.
#[derive(Debug, Clone)]
pub enum Target {
    /// Start one in this process (loopback, embedded weights).
    Spawn(SpawnOptions),
    /// A running server.
    Remote {
        /// gRPC URL, e.g. `http://127.0.0.1:50051`.
        url: String,
        /// Its metrics page, e.g. `http://127.0.0.1:9090/metrics`.
        metrics_url: Option<String>,
        /// Its process id, for idle-mode memory.
        server_pid: Option<u32>,
    },
}

/// What to measure.
#[derive(Debug, Clone)]
pub enum Workmode {
    /// Streams sending frames.
    Stream(StreamOptions),
    /// `sessions` sessions held open, without frames, for `hold`.
    Idle {
        /// Sessions to open.
        sessions: usize,
        /// How long to hold them before the second memory reading.
        hold: Duration,
    },
}

/// One load-test run.
#[derive(Debug, Clone)]
pub struct LoadTest {
    /// The server.
    pub target: Target,
    /// Stream or idle.
    pub mode: Workmode,
    /// HTTP/2 connections the sessions are spread over (>= 1).
    pub connections: usize,
    /// Deadline for the whole run (connect, open, stream, close).
    pub timeout: Duration,
    /// Directory of `.npz` replay files to send.
    pub examples: PathBuf,
    /// Open every session with the causal motion stage (at the clips' own
    /// rate).
    pub motion: bool,
}

/// Why a run could not produce a report. Failures *during* the run (a
/// refused frame, a dead stream) are counted in the report instead.
#[derive(Debug, thiserror::Error)]
pub enum LoadTestError {
    /// The example sequences could not be loaded.
    #[error(transparent)]
    Workload(#[from] WorkloadError),
    /// The in-process server did not start.
    #[error("cannot start the in-process server: {0}")]
    Spawn(#[source] ServerError),
    /// The server could not be reached.
    #[error("cannot reach the blapose server at {url}: {source}")]
    Connect {
        /// The URL.
        url: String,
        /// The cause.
        #[source]
        source: ClientError,
    },
    /// The deadline passed before the run could start.
    #[error("the --timeout deadline ({0:?}) passed while connecting")]
    Deadline(Duration),
}

/// Idle sessions opened and closed before the first memory reading, so
/// lazily allocated buffers and allocator arenas are in place already.
const IDLE_WARM_UP_SESSIONS: usize = 16;
/// Deadline for each metrics page.
const METRICS_TIMEOUT: Duration = Duration::from_secs(5);

impl LoadTest {
    /// Run it.
    pub async fn run(&self) -> Result<Report, LoadTestError> {
        let started = Instant::now();
        let deadline = started + self.timeout;
        let mut workload = Workload::from_dir(&self.examples)?;
        workload.motion = self.motion;
        let machine = report::machine();

        let (spawned, url, metrics_url, server_label) = match &self.target {
            Target::Spawn(options) => {
                let mut options = options.clone();
                options.max_sessions = options.max_sessions.max(self.sessions() + 64);
                let s = spawn::spawn(&options).await.map_err(LoadTestError::Spawn)?;
                let (url, metrics) = (s.url.clone(), s.metrics_url.clone());
                (Some(s), url, metrics, "spawned in-process".to_string())
            }
            Target::Remote {
                url, metrics_url, ..
            } => (None, url.clone(), metrics_url.clone(), url.clone()),
        };

        let result = async {
            let clients =
                tokio::time::timeout_at(deadline.into(), driver::connect(&url, self.connections))
                    .await
                    .map_err(|_| LoadTestError::Deadline(self.timeout))?
                    .map_err(|source| LoadTestError::Connect {
                        url: url.clone(),
                        source,
                    })?;
            let before = match &metrics_url {
                Some(m) => Some(prom::fetch_text(m, METRICS_TIMEOUT).await),
                None => None,
            };
            let mut report = Report {
                mode: Mode::Stream,
                server: server_label,
                streams: match &self.mode {
                    Workmode::Stream(o) => o.streams,
                    Workmode::Idle { sessions, .. } => *sessions,
                },
                connections: clients.len(),
                frames_per_stream: 0,
                inflight: 0,
                rate: None,
                frames: 0,
                frames_sent: 0,
                seconds: 0.0,
                frames_per_second: 0.0,
                latency_ms: None,
                errors: Default::default(),
                first_error: None,
                batch_sizes: None,
                metrics_error: None,
                process_cpu_pct: None,
                idle: None,
                machine,
            };
            let mut stats = match &self.mode {
                Workmode::Stream(options) => {
                    report.frames_per_stream = options.frames;
                    report.inflight = options.inflight.max(1);
                    report.rate = options.rate;
                    let (sessions, mut stats) =
                        driver::open_sessions(&clients, &workload, options.streams, deadline).await;
                    let cpu0 = process_cpu_seconds();
                    let start = Instant::now();
                    stats.merge(driver::run_streams(sessions, &workload, options, deadline).await);
                    let end = stats.last_answer.unwrap_or_else(Instant::now);
                    let wall = end.saturating_duration_since(start).as_secs_f64();
                    report.process_cpu_pct = cpu0
                        .zip(process_cpu_seconds())
                        .map(|(a, b)| 100.0 * (b - a) / start.elapsed().as_secs_f64());
                    report.seconds = wall;
                    report.frames_per_second = if wall > 0.0 {
                        stats.answered as f64 / wall
                    } else {
                        0.0
                    };
                    report.latency_ms = LatencyMs::from_nanos(&mut stats.latencies_ns);
                    stats
                }
                Workmode::Idle { sessions, hold } => {
                    report.mode = Mode::Idle;
                    let (idle, stats) = self
                        .idle(
                            &clients,
                            &workload,
                            *sessions,
                            *hold,
                            metrics_url.as_deref(),
                            deadline,
                        )
                        .await;
                    report.idle = Some(idle);
                    stats
                }
            };
            report.frames = stats.answered;
            report.frames_sent = stats.sent;
            report.errors = std::mem::take(&mut stats.errors);
            report.first_error = stats.first_error.take();
            // Idle sessions run no batches: nothing to report there.
            if report.mode == Mode::Stream {
                match &metrics_url {
                    Some(m) => {
                        let after = prom::fetch_text(m, METRICS_TIMEOUT).await;
                        match batch_sizes(before, after) {
                            Ok(b) => report.batch_sizes = Some(b),
                            Err(e) => report.metrics_error = Some(e),
                        }
                    }
                    None => report.metrics_error = Some("no metrics URL (pass --metrics)".into()),
                }
            }
            Ok::<_, LoadTestError>(report)
        }
        .await;

        if let Some(s) = spawned {
            // Bounded by the server's own grace period; a failure to shut
            // down cleanly does not invalidate what was measured.
            let _ = tokio::time::timeout(Duration::from_secs(5), s.shutdown()).await;
        }
        result
    }

    /// Sessions this run opens, warm-up included.
    fn sessions(&self) -> usize {
        match &self.mode {
            Workmode::Stream(o) => o.streams,
            Workmode::Idle { sessions, .. } => *sessions + IDLE_WARM_UP_SESSIONS,
        }
    }

    /// Open `n` idle sessions, read the memory before and after, close them.
    async fn idle(
        &self,
        clients: &[blapose_client::Client],
        workload: &Workload,
        n: usize,
        hold: Duration,
        metrics_url: Option<&str>,
        deadline: Instant,
    ) -> (IdleMemory, StreamStats) {
        let (pid, scope) = match &self.target {
            Target::Spawn(_) => (
                None,
                "server and client together (one process, --spawn)".to_string(),
            ),
            Target::Remote {
                server_pid: Some(p),
                ..
            } => (Some(*p), format!("server process {p}")),
            Target::Remote { .. } => (None, "this client only (pass --server-pid)".to_string()),
        };
        let (warm, mut stats) =
            driver::open_sessions(clients, workload, IDLE_WARM_UP_SESSIONS.min(n), deadline).await;
        stats.merge(driver::close_sessions(warm, deadline).await);
        tokio::time::sleep(Duration::from_millis(200)).await;
        let before = driver::resident_bytes(pid);
        let (sessions, opened) = driver::open_sessions(clients, workload, n, deadline).await;
        stats.merge(opened);
        tokio::time::sleep(hold.min(deadline.saturating_duration_since(Instant::now()))).await;
        let after = driver::resident_bytes(pid);
        let page = match metrics_url {
            Some(m) => prom::fetch_text(m, METRICS_TIMEOUT).await.ok(),
            None => None,
        };
        let held = sessions.len() as u64;
        stats.merge(driver::close_sessions(sessions, deadline).await);
        let idle = IdleMemory {
            sessions: held,
            rss_before_bytes: before,
            rss_after_bytes: after,
            bytes_per_session: before
                .zip(after)
                .filter(|_| held > 0)
                .map(|(b, a)| (a as f64 - b as f64) / held as f64),
            scope,
            server_sessions: page.as_deref().and_then(|p| prom::value(p, SESSIONS)),
            server_streams: page.as_deref().and_then(|p| prom::value(p, STREAMS)),
        };
        (idle, stats)
    }
}

/// The batch-size histogram's increase between two metrics pages.
fn batch_sizes(
    before: Option<Result<String, prom::MetricsError>>,
    after: Result<String, prom::MetricsError>,
) -> Result<BatchSizes, String> {
    let after = after.map_err(|e| e.to_string())?;
    let earlier = match before {
        Some(Ok(text)) => Histogram::parse(&text, BATCH_SIZE),
        Some(Err(e)) => return Err(format!("before the run: {e}")),
        None => None,
    };
    let now = Histogram::parse(&after, BATCH_SIZE)
        .ok_or_else(|| format!("the metrics page has no {BATCH_SIZE} histogram"))?;
    Ok(BatchSizes::from_histogram(&now.since(earlier.as_ref())))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn batch_sizes_are_the_runs_increase() {
        let page = |ones: u64, fours: u64| {
            format!(
                "blapose_batch_size_bucket{{le=\"1\"}} {ones}\nblapose_batch_size_bucket{{le=\"4\"}} {}\nblapose_batch_size_bucket{{le=\"+Inf\"}} {}\nblapose_batch_size_sum {}\nblapose_batch_size_count {}\n",
                ones + fours,
                ones + fours,
                ones + 4 * fours,
                ones + fours
            )
        };
        let b = batch_sizes(Some(Ok(page(5, 1))), Ok(page(6, 4))).unwrap();
        assert_eq!(b.steps, 4);
        assert_eq!(b.mean, Some(13.0 / 4.0));
        let b = batch_sizes(None, Ok(page(1, 0))).unwrap();
        assert_eq!(b.steps, 1);
        assert!(batch_sizes(None, Ok("up 1\n".into()))
            .unwrap_err()
            .contains(BATCH_SIZE));
    }

    #[test]
    fn cpu_time_is_readable() {
        if std::path::Path::new("/proc/self/stat").exists() {
            assert!(process_cpu_seconds().is_some());
        }
    }
}

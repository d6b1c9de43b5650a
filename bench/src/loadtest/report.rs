//! The load test's result: one serializable [`Report`], printed as a
//! markdown table and optionally written as JSON.
//!
//! The JSON keeps the field names the issue fixes (`streams`, `frames`,
//! `frames_per_second`, `latency_ms.{p50,p90,p99,max}`, `errors`,
//! `batch_sizes`) so scripts and CI can compare runs; everything else
//! (conditions, idle memory) is extra fields beside them.

use std::fmt::Write as _;

use serde::Serialize;

use super::driver::ErrorCounts;
use super::prom::Histogram;
use super::stats::LatencyMs;

/// What was measured.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Mode {
    /// Streams sending frames.
    Stream,
    /// Sessions held open without frames (memory per session).
    Idle,
}

/// The server's batch-size histogram over this run.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct BatchSizes {
    /// Batched steps run.
    pub steps: u64,
    /// Mean frames per step.
    pub mean: Option<f64>,
    /// Upper bound of the bucket holding the median step.
    pub p50_at_most: Option<f64>,
    /// Upper bound of the bucket holding the 99th-percentile step.
    pub p99_at_most: Option<f64>,
    /// Steps per bucket of sizes, ascending.
    pub buckets: Vec<BatchBucket>,
}

/// Steps whose size fell in one bucket.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct BatchBucket {
    /// The sizes, e.g. `"1"`, `"3-4"`, `">4096"`.
    pub sizes: String,
    /// Upper bound (inclusive); `null` for the overflow bucket.
    pub le: Option<f64>,
    /// Steps.
    pub steps: u64,
}

impl BatchSizes {
    /// From the histogram's increase over the run; empty buckets dropped.
    pub fn from_histogram(h: &Histogram) -> Self {
        let mut lower = 1.0;
        let mut buckets = Vec::new();
        for b in h.bucket_counts() {
            let sizes = if b.le.is_infinite() {
                format!(">{}", lower - 1.0)
            } else if b.le <= lower {
                format!("{}", b.le)
            } else {
                format!("{lower}-{}", b.le)
            };
            if b.count > 0 {
                buckets.push(BatchBucket {
                    sizes,
                    le: b.le.is_finite().then_some(b.le),
                    steps: b.count,
                });
            }
            lower = b.le.floor() + 1.0;
        }
        let finite = |v: Option<f64>| v.filter(|x| x.is_finite());
        BatchSizes {
            steps: h.count,
            mean: h.mean(),
            p50_at_most: finite(h.quantile_upper_bound(0.5)),
            p99_at_most: finite(h.quantile_upper_bound(0.99)),
            buckets,
        }
    }
}

/// Idle-mode memory measurement.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct IdleMemory {
    /// Sessions held open at the second reading.
    pub sessions: u64,
    /// Resident memory before opening them, bytes.
    pub rss_before_bytes: Option<u64>,
    /// Resident memory with them open, bytes.
    pub rss_after_bytes: Option<u64>,
    /// (after - before) / sessions.
    pub bytes_per_session: Option<f64>,
    /// Whose memory: the in-process server and client together, or the
    /// server process given by `--server-pid`.
    pub scope: String,
    /// The server's `blapose_sessions` gauge while they were held.
    pub server_sessions: Option<f64>,
    /// The server's `blapose_streams_attached` gauge while they were held.
    pub server_streams: Option<f64>,
}

/// The machine and its load, so runs on a shared machine can be judged.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Machine {
    /// CPU model.
    pub cpu: String,
    /// Logical CPUs.
    pub logical_cpus: usize,
    /// `/proc/loadavg` (1, 5, 15 min) before the run.
    pub load_average: String,
}

/// Everything one run measured.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Report {
    /// Stream or idle.
    pub mode: Mode,
    /// `spawned` or the server URL.
    pub server: String,
    /// Concurrent streams (sessions) requested.
    pub streams: usize,
    /// HTTP/2 connections the streams were spread over.
    pub connections: usize,
    /// Frames each stream was to send.
    pub frames_per_stream: u64,
    /// Frames in flight per stream, at most.
    pub inflight: usize,
    /// Frames per second per stream (`null`: as fast as possible).
    pub rate: Option<f64>,
    /// Frames answered with an adjusted pose.
    pub frames: u64,
    /// Frames sent.
    pub frames_sent: u64,
    /// From the first frame sent to the last answer, seconds.
    pub seconds: f64,
    /// `frames / seconds`.
    pub frames_per_second: f64,
    /// Send-to-answer latency of the answered frames.
    pub latency_ms: Option<LatencyMs>,
    /// Failures by kind: `status:CODE` (stream ended with a gRPC status),
    /// `frame:CODE` (in-band FrameError), `client:KIND`.
    pub errors: ErrorCounts,
    /// The first failure's message.
    pub first_error: Option<String>,
    /// The server's batch sizes during the run (`null` without metrics).
    pub batch_sizes: Option<BatchSizes>,
    /// Why `batch_sizes` is missing, if it is.
    pub metrics_error: Option<String>,
    /// This process's CPU time over the timed phase / its wall time, %
    /// (with `--spawn` the server and the client together).
    pub process_cpu_pct: Option<f64>,
    /// Idle-mode memory (`null` in stream mode).
    pub idle: Option<IdleMemory>,
    /// Where it ran.
    pub machine: Machine,
}

impl Report {
    /// Total failures.
    pub fn error_count(&self) -> u64 {
        self.errors.values().sum()
    }

    /// The machine-readable last line of stdout.
    pub fn summary_line(&self) -> String {
        match (&self.mode, &self.idle) {
            (Mode::Idle, Some(idle)) => format!(
                "bytes_per_session={}",
                idle.bytes_per_session
                    .map_or("nan".to_string(), |b| format!("{b:.0}"))
            ),
            _ => format!("frames_per_second={:.0}", self.frames_per_second),
        }
    }

    /// The human-readable report.
    pub fn markdown(&self) -> String {
        let mut s = String::new();
        let _ = writeln!(
            s,
            "blapose loadtest: server {}, {} ({} logical CPUs), load average before {}\n",
            self.server, self.machine.cpu, self.machine.logical_cpus, self.machine.load_average
        );
        let ms = |f: fn(&LatencyMs) -> f64| {
            self.latency_ms
                .as_ref()
                .map_or("-".to_string(), |l| format!("{:.2}", f(l)))
        };
        let cpu = self
            .process_cpu_pct
            .map_or("-".to_string(), |c| format!("{c:.0}%"));
        match self.mode {
            Mode::Stream => {
                let rate = self.rate.map_or("max".to_string(), |r| format!("{r}/s"));
                s.push_str("| streams | connections | in flight | rate per stream | frames | seconds | frames/s | p50 ms | p90 ms | p99 ms | max ms | errors | mean batch | CPU |\n");
                s.push_str(
                    "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n",
                );
                let _ = writeln!(
                    s,
                    "| {} | {} | {} | {} | {}/{} | {:.2} | {:.0} | {} | {} | {} | {} | {} | {} | {} |",
                    self.streams,
                    self.connections,
                    self.inflight,
                    rate,
                    self.frames,
                    self.frames_per_stream * self.streams as u64,
                    self.seconds,
                    self.frames_per_second,
                    ms(|l| l.p50),
                    ms(|l| l.p90),
                    ms(|l| l.p99),
                    ms(|l| l.max),
                    self.error_count(),
                    self.batch_sizes
                        .as_ref()
                        .and_then(|b| b.mean)
                        .map_or("-".to_string(), |m| format!("{m:.1}")),
                    cpu,
                );
            }
            Mode::Idle => {
                let mib = |b: Option<u64>| {
                    b.map_or("-".to_string(), |b| format!("{:.1}", b as f64 / 1048576.0))
                };
                if let Some(idle) = &self.idle {
                    s.push_str("| idle sessions | RSS before MiB | RSS after MiB | bytes per session | server sessions | memory of |\n");
                    s.push_str("|---:|---:|---:|---:|---:|---|\n");
                    let _ = writeln!(
                        s,
                        "| {} | {} | {} | {} | {} | {} |",
                        idle.sessions,
                        mib(idle.rss_before_bytes),
                        mib(idle.rss_after_bytes),
                        idle.bytes_per_session
                            .map_or("-".to_string(), |b| format!("{b:.0}")),
                        idle.server_sessions
                            .map_or("-".to_string(), |v| format!("{v:.0}")),
                        idle.scope
                    );
                }
            }
        }
        if let Some(b) = &self.batch_sizes {
            if b.steps > 0 {
                let _ = writeln!(
                    s,
                    "\nServer batch sizes during the run: {} steps, mean {:.1}\n",
                    b.steps,
                    b.mean.unwrap_or(f64::NAN)
                );
                s.push_str("| frames per step | steps |\n|---:|---:|\n");
                for bucket in &b.buckets {
                    let _ = writeln!(s, "| {} | {} |", bucket.sizes, bucket.steps);
                }
            }
        } else if let Some(e) = &self.metrics_error {
            let _ = writeln!(s, "\nServer batch sizes unavailable: {e}");
        }
        if !self.errors.is_empty() {
            s.push_str("\n| error | count |\n|---|---:|\n");
            for (k, v) in &self.errors {
                let _ = writeln!(s, "| {k} | {v} |");
            }
            if let Some(first) = &self.first_error {
                let _ = writeln!(s, "\nfirst error: {first}");
            }
        }
        s
    }
}

/// CPU model and logical CPU count from `/proc`, and the load average.
pub fn machine() -> Machine {
    Machine {
        cpu: crate::machine::cpu_model(),
        logical_cpus: std::thread::available_parallelism().map_or(1, |n| n.get()),
        load_average: crate::machine::load_average(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> Report {
        let h = Histogram {
            buckets: vec![
                (1.0, 2),
                (2.0, 2),
                (4.0, 10),
                (8.0, 10),
                (f64::INFINITY, 11),
            ],
            sum: 40.0,
            count: 11,
        };
        Report {
            mode: Mode::Stream,
            server: "spawned".into(),
            streams: 4,
            connections: 1,
            frames_per_stream: 50,
            inflight: 8,
            rate: None,
            frames: 200,
            frames_sent: 200,
            seconds: 0.5,
            frames_per_second: 400.0,
            latency_ms: Some(LatencyMs {
                p50: 1.0,
                p90: 2.0,
                p99: 3.0,
                max: 4.0,
            }),
            errors: [("frame:RESOURCE_EXHAUSTED".to_string(), 2)].into(),
            first_error: Some("busy".into()),
            batch_sizes: Some(BatchSizes::from_histogram(&h)),
            metrics_error: None,
            process_cpu_pct: Some(150.0),
            idle: None,
            machine: Machine {
                cpu: "cpu".into(),
                logical_cpus: 2,
                load_average: "0 0 0".into(),
            },
        }
    }

    #[test]
    fn batch_buckets_are_named_by_their_sizes() {
        let b = sample().batch_sizes.unwrap();
        let named: Vec<(&str, u64)> = b
            .buckets
            .iter()
            .map(|b| (b.sizes.as_str(), b.steps))
            .collect();
        assert_eq!(named, vec![("1", 2), ("3-4", 8), (">8", 1)]);
        assert_eq!(b.buckets[2].le, None);
        assert_eq!(b.p50_at_most, Some(4.0));
        assert_eq!(b.p99_at_most, None, "the overflow bucket has no bound");
        assert!((b.mean.unwrap() - 40.0 / 11.0).abs() < 1e-12);
    }

    #[test]
    fn json_has_the_agreed_shape() {
        let v = serde_json::to_value(sample()).unwrap();
        assert_eq!(v["streams"], 4);
        assert_eq!(v["frames"], 200);
        assert_eq!(v["frames_per_second"], 400.0);
        for k in ["p50", "p90", "p99", "max"] {
            assert!(v["latency_ms"][k].is_f64(), "{k}");
        }
        assert_eq!(v["errors"]["frame:RESOURCE_EXHAUSTED"], 2);
        assert_eq!(v["batch_sizes"]["steps"], 11);
        assert_eq!(v["batch_sizes"]["buckets"][0]["sizes"], "1");
        assert_eq!(v["mode"], "stream");
        assert!(v["rate"].is_null());
        assert!(v["idle"].is_null());
    }

    #[test]
    fn markdown_and_summary_line() {
        let r = sample();
        let md = r.markdown();
        assert!(md.contains("| 4 | 1 | 8 | max | 200/200 | 0.50 | 400 | 1.00 | 2.00 | 3.00 | 4.00 | 2 | 3.6 | 150% |"), "{md}");
        assert!(md.contains("| 3-4 | 8 |"));
        assert!(md.contains("| frame:RESOURCE_EXHAUSTED | 2 |"));
        assert_eq!(r.summary_line(), "frames_per_second=400");
        let idle = Report {
            mode: Mode::Idle,
            idle: Some(IdleMemory {
                sessions: 1024,
                rss_before_bytes: Some(10 << 20),
                rss_after_bytes: Some(20 << 20),
                bytes_per_session: Some(10240.0),
                scope: "server and client (one process)".into(),
                server_sessions: Some(1024.0),
                server_streams: Some(1024.0),
            }),
            ..r
        };
        assert!(idle
            .markdown()
            .contains("| 1024 | 10.0 | 20.0 | 10240 | 1024 |"));
        assert_eq!(idle.summary_line(), "bytes_per_session=10240");
    }
}

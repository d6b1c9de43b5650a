//! Driving N concurrent sessions through the client library.
//!
//! Each stream is one [`blapose_client::Session`], split into its sending
//! and receiving halves and run as one tokio task. The sender keeps at most
//! `inflight` frames unanswered (optionally paced to `rate` frames/s); the
//! receiver matches each answer to its send time. The server answers every
//! stream's frames in order, so send times travel from sender to receiver
//! through a bounded channel whose capacity *is* the in-flight window: the
//! sender reserves a slot (waiting while the window is full), stamps the
//! time, sends the frame; the receiver pops one time per answer. Latency is
//! therefore send-to-answer as the client sees it, queueing in the client's
//! own buffers included.
//!
//! Nothing here can hang: every stream runs under the run's deadline, a
//! stream whose server goes away ends with the transport's status, and a
//! failure is counted by gRPC status code (`status:UNAVAILABLE`), in-band
//! frame error code (`frame:RESOURCE_EXHAUSTED`) or client-side kind
//! (`client:deadline`), never propagated as a panic.

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use blapose_client::{Client, ClientConfig, ClientError, Session, SessionEvent, SessionOptions};
use blapose_proto::v1 as pb;
use blapose_server::metrics::code_name;
use tokio::sync::mpsc;
use tokio::task::JoinSet;
use tokio::time::MissedTickBehavior;

use super::workload::Workload;

/// How to load the server.
#[derive(Debug, Clone)]
pub struct StreamOptions {
    /// Concurrent streams (sessions).
    pub streams: usize,
    /// Frames each stream sends.
    pub frames: u64,
    /// Frames per second per stream; `None`: as fast as the window allows.
    pub rate: Option<f64>,
    /// Frames one stream may have sent but not yet seen answered (>= 1).
    pub inflight: usize,
}

/// Error counts by kind (`status:CODE`, `frame:CODE`, `client:KIND`).
pub type ErrorCounts = BTreeMap<String, u64>;

/// What one or more streams did.
#[derive(Debug, Default)]
pub struct StreamStats {
    /// Frames sent.
    pub sent: u64,
    /// Frames answered with an adjusted pose.
    pub answered: u64,
    /// Send-to-answer latency of every adjusted frame, nanoseconds.
    pub latencies_ns: Vec<u64>,
    /// Failures by kind.
    pub errors: ErrorCounts,
    /// The first failure's message, for the report.
    pub first_error: Option<String>,
    /// When the last answer arrived.
    pub last_answer: Option<Instant>,
    /// Sessions that ended with the server's `SessionClosed`.
    pub closed: u64,
}

impl StreamStats {
    /// Count one failure.
    pub fn error(&mut self, kind: String, message: impl FnOnce() -> String) {
        *self.errors.entry(kind).or_default() += 1;
        if self.first_error.is_none() {
            self.first_error = Some(message());
        }
    }

    /// Count a client-library error.
    pub fn client_error(&mut self, e: &ClientError) {
        self.error(error_kind(e), || e.to_string());
    }

    /// Fold `other` into `self`.
    pub fn merge(&mut self, other: StreamStats) {
        self.sent += other.sent;
        self.answered += other.answered;
        self.latencies_ns.extend(other.latencies_ns);
        for (k, v) in other.errors {
            *self.errors.entry(k).or_default() += v;
        }
        if self.first_error.is_none() {
            self.first_error = other.first_error;
        }
        self.last_answer = self.last_answer.max(other.last_answer);
        self.closed += other.closed;
    }

    /// Total failures.
    pub fn error_count(&self) -> u64 {
        self.errors.values().sum()
    }
}

/// The key a client error is counted under.
pub fn error_kind(e: &ClientError) -> String {
    match e {
        ClientError::Status(s) => format!("status:{}", code_name(s.code())),
        ClientError::FrameRejected { code, .. } => format!("frame:{}", code_name(*code)),
        ClientError::Connect { .. } | ClientError::InvalidEndpoint { .. } => {
            "client:connect".into()
        }
        ClientError::Timeout { .. } => "client:timeout".into(),
        ClientError::Protocol(_) => "client:protocol".into(),
        ClientError::StreamEnded { .. } => "client:stream_ended".into(),
        _ => "client:other".into(),
    }
}

/// Connect `connections` clients to `url` (streams are spread over them:
/// each client is one HTTP/2 connection).
pub async fn connect(url: &str, connections: usize) -> Result<Vec<Client>, ClientError> {
    let mut config = ClientConfig::new(url);
    config.connect_attempts = 3;
    config.connect_timeout = Duration::from_secs(3);
    config.request_timeout = Duration::from_secs(30);
    let mut clients = Vec::with_capacity(connections.max(1));
    for _ in 0..connections.max(1) {
        clients.push(Client::connect(config.clone()).await?);
    }
    Ok(clients)
}

/// Open `n` sessions concurrently, session `i` on client `i % clients` with
/// clip `i`'s input format. Returns the sessions that opened (by index) and
/// the failures. Gives up at `deadline`.
pub async fn open_sessions(
    clients: &[Client],
    workload: &Workload,
    n: usize,
    deadline: Instant,
) -> (Vec<(usize, Session)>, StreamStats) {
    let mut tasks = JoinSet::new();
    for i in 0..n {
        let client = clients[i % clients.len()].clone();
        let format = workload.clip(i).input_format;
        let motion = workload.motion.then_some(0.0);
        tasks.spawn(async move {
            let label = format!("loadtest-{i}");
            let options = SessionOptions {
                label: Some(&label),
                motion,
                ..Default::default()
            };
            (i, client.open_session_with(format, &options).await)
        });
    }
    let mut opened = Vec::with_capacity(n);
    let mut failed = StreamStats::default();
    let collect = async {
        while let Some(joined) = tasks.join_next().await {
            match joined {
                Ok((i, Ok(session))) => opened.push((i, session)),
                Ok((_, Err(e))) => failed.client_error(&e),
                Err(e) => failed.error("client:task".into(), || e.to_string()),
            }
        }
    };
    if tokio::time::timeout_at(deadline.into(), collect)
        .await
        .is_err()
    {
        let missing = tasks.len();
        tasks.abort_all();
        for _ in 0..missing {
            failed.error("client:deadline".into(), || {
                "the deadline passed while sessions were opening".into()
            });
        }
    }
    opened.sort_by_key(|(i, _)| *i);
    (opened, failed)
}

/// Run every opened session as a stream to completion (or `deadline`) and
/// return the merged statistics. Each session is closed at the end.
pub async fn run_streams(
    sessions: Vec<(usize, Session)>,
    workload: &Workload,
    options: &StreamOptions,
    deadline: Instant,
) -> StreamStats {
    let mut tasks = JoinSet::new();
    for (i, session) in sessions {
        let clip = workload.clip(i).clone();
        let options = options.clone();
        tasks.spawn(drive(session, clip, options, deadline));
    }
    let mut total = StreamStats::default();
    // Streams stop themselves at the deadline; the grace covers a task that
    // is slow to notice (the runtime is shared with the server).
    let grace = deadline + Duration::from_secs(5);
    loop {
        match tokio::time::timeout_at(grace.into(), tasks.join_next()).await {
            Ok(Some(Ok(stats))) => total.merge(stats),
            Ok(Some(Err(e))) => total.error("client:task".into(), || e.to_string()),
            Ok(None) => break,
            Err(_) => {
                for _ in 0..tasks.len() {
                    total.error("client:deadline".into(), || {
                        "a stream did not stop at the deadline".into()
                    });
                }
                tasks.abort_all();
                break;
            }
        }
    }
    total
}

/// One stream: send `options.frames` frames of `clip`, read every answer,
/// close the session.
async fn drive(
    session: Session,
    clip: super::workload::Clip,
    options: StreamOptions,
    deadline: Instant,
) -> StreamStats {
    let (_info, sender, mut receiver) = session.split();
    let (times_tx, mut times_rx) = mpsc::channel::<Instant>(options.inflight.max(1));
    let mut stats = StreamStats::default();
    let mut sent = 0u64;
    let frames = options.frames;

    let send = async {
        let mut ticker = options.rate.filter(|r| r.is_finite() && *r > 0.0).map(|r| {
            let mut t = tokio::time::interval(Duration::from_secs_f64(1.0 / r));
            t.set_missed_tick_behavior(MissedTickBehavior::Delay);
            t
        });
        for i in 0..frames {
            if let Some(t) = ticker.as_mut() {
                t.tick().await;
            }
            // Waits while `inflight` frames are unanswered; fails once the
            // receiver has stopped.
            let Ok(slot) = times_tx.reserve().await else {
                break;
            };
            let request = pb::StreamRequest {
                kind: Some(pb::stream_request::Kind::Frame(clip.frame(i))),
            };
            slot.send(Instant::now());
            if sender.send_raw(request).await.is_err() {
                break;
            }
            sent += 1;
        }
        // Ask for the close; the server answers every frame first.
        let _ = sender.close().await;
        drop(sender);
    };

    let receive = async {
        let mut expected = 0u64;
        loop {
            match receiver.next().await {
                Ok(Some(SessionEvent::Adjusted(frame))) => {
                    let now = Instant::now();
                    let Some(sent_at) = times_rx.recv().await else {
                        stats.error("client:protocol".into(), || {
                            "an answer for a frame that was never sent".into()
                        });
                        break;
                    };
                    if frame.frame_index != expected {
                        stats.error("client:out_of_order".into(), || {
                            format!(
                                "answer for frame {} when frame {expected} was due",
                                frame.frame_index
                            )
                        });
                    }
                    expected = frame.frame_index + 1;
                    stats.answered += 1;
                    stats
                        .latencies_ns
                        .push(now.duration_since(sent_at).as_nanos() as u64);
                    stats.last_answer = Some(now);
                }
                Ok(Some(SessionEvent::Rejected(r))) => {
                    let _ = times_rx.recv().await;
                    expected = r.frame_index + 1;
                    stats.error(format!("frame:{}", code_name(r.code)), || {
                        format!(
                            "frame {} rejected ({}): {}",
                            r.frame_index, r.code, r.message
                        )
                    });
                }
                Ok(Some(SessionEvent::Closed(_))) => {
                    stats.closed += 1;
                    break;
                }
                Ok(None) => {
                    stats.error("client:stream_ended".into(), || {
                        "the server ended the stream without closing the session".into()
                    });
                    break;
                }
                Err(e) => {
                    stats.client_error(&e);
                    break;
                }
            }
        }
        // Unblocks the sender if it still waits for a window slot.
        times_rx.close();
    };

    let work = async { tokio::join!(send, receive) };
    let timed_out = tokio::time::timeout_at(deadline.into(), work)
        .await
        .is_err();
    stats.sent = sent;
    if timed_out {
        stats.error("client:deadline".into(), || {
            "the run's deadline passed before every frame was answered".into()
        });
    }
    stats
}

/// Close idle sessions (each stream sends `close` and waits for
/// `SessionClosed`), until `deadline`.
pub async fn close_sessions(sessions: Vec<(usize, Session)>, deadline: Instant) -> StreamStats {
    let mut tasks = JoinSet::new();
    for (_, session) in sessions {
        tasks.spawn(async move { session.close().await });
    }
    let mut stats = StreamStats::default();
    let collect = async {
        while let Some(joined) = tasks.join_next().await {
            match joined {
                Ok(Ok(_)) => stats.closed += 1,
                Ok(Err(e)) => stats.client_error(&e),
                Err(e) => stats.error("client:task".into(), || e.to_string()),
            }
        }
    };
    if tokio::time::timeout_at(deadline.into(), collect)
        .await
        .is_err()
    {
        stats.error("client:deadline".into(), || {
            "the deadline passed while sessions were closing".into()
        });
        tasks.abort_all();
    }
    stats
}

/// Resident memory (`VmRSS`) of process `pid` (`None`: this process), in
/// bytes; `None` where `/proc` is unavailable.
pub fn resident_bytes(pid: Option<u32>) -> Option<u64> {
    let path = match pid {
        Some(p) => format!("/proc/{p}/status"),
        None => "/proc/self/status".to_string(),
    };
    parse_vm_rss(&std::fs::read_to_string(path).ok()?)
}

/// `VmRSS` from the text of `/proc/PID/status`, in bytes.
pub fn parse_vm_rss(status: &str) -> Option<u64> {
    let line = status.lines().find(|l| l.starts_with("VmRSS:"))?;
    let mut parts = line["VmRSS:".len()..].split_whitespace();
    let value: u64 = parts.next()?.parse().ok()?;
    match parts.next() {
        Some("kB") | None => Some(value * 1024),
        Some(_) => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::Path;

    #[test]
    fn vm_rss_parsing() {
        let status = "Name:\tx\nVmPeak:\t  9000 kB\nVmRSS:\t   1234 kB\nThreads:\t3\n";
        assert_eq!(parse_vm_rss(status), Some(1234 * 1024));
        assert_eq!(parse_vm_rss("Name: x\n"), None);
        assert_eq!(parse_vm_rss("VmRSS: lots kB\n"), None);
        assert!(resident_bytes(None).is_some_and(|b| b > 0) || !Path::new("/proc").exists());
    }

    #[test]
    fn errors_are_keyed_by_code() {
        let status = ClientError::Status(tonic::Status::unavailable("gone"));
        assert_eq!(error_kind(&status), "status:UNAVAILABLE");
        let frame = ClientError::FrameRejected {
            frame_index: 3,
            code: tonic::Code::ResourceExhausted,
            message: "busy".into(),
        };
        assert_eq!(error_kind(&frame), "frame:RESOURCE_EXHAUSTED");
        assert_eq!(
            error_kind(&ClientError::Protocol("x".into())),
            "client:protocol"
        );
        let mut stats = StreamStats::default();
        stats.client_error(&status);
        stats.client_error(&status);
        let mut other = StreamStats {
            answered: 2,
            latencies_ns: vec![5, 6],
            ..StreamStats::default()
        };
        other.client_error(&frame);
        stats.merge(other);
        assert_eq!(stats.errors["status:UNAVAILABLE"], 2);
        assert_eq!(stats.errors["frame:RESOURCE_EXHAUSTED"], 1);
        assert_eq!(stats.error_count(), 3);
        assert_eq!(stats.answered, 2);
        assert!(stats.first_error.unwrap().contains("gone"));
    }

    #[tokio::test]
    async fn connection_refused_names_the_url() {
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .unwrap()
            .local_addr()
            .unwrap()
            .port();
        let url = format!("http://127.0.0.1:{port}");
        let err = connect(&url, 1).await.unwrap_err();
        assert!(err.to_string().contains(&url), "{err}");
    }
}

//! The memory budget: what the server holds for its clients, accounted by
//! the server itself, and new work refused once it would pass the budget.
//!
//! Per-connection and per-client limits each hold, yet many sources
//! together did not: 512 connections x 1,000 HEADERS-only streams from one
//! address grew the server from 118 MB to 3.8 GB in 20 s (and kept it).
//! So, as Envoy's overload manager does for its heap, the server counts
//! what it holds (open streams, sessions, queued frames, remembered ended
//! sessions) at a measured cost each, and once the sum reaches
//! `--memory-budget` refuses new work: connections are closed at accept,
//! new streams answered RESOURCE_EXHAUSTED at once (before any handler
//! runs), new sessions RESOURCE_EXHAUSTED, frames a FrameError
//! RESOURCE_EXHAUSTED. Work already admitted goes on, so the server stops
//! growing instead of failing its clients. Every refusal counts in
//! `blapose_limited_total{limit="memory_budget"}`; the sum is the
//! `blapose_memory_accounted_bytes` gauge.
//!
//! Open streams are counted live (and per address, across connections:
//! `--max-streams-per-peer`, except for `--trusted-proxies`, whose streams
//! are many clients'); so are connections, each at what it may hold before
//! the stream layer sees a stream: h2 takes up to `--max-concurrent-streams`
//! HEADERS on a connection before any handler runs (512 connections x
//! 1,000 refused streams still grew the server by 0.7-1.0 GB with every
//! admitted stream in the budget). The rest is sampled every 100 ms from
//! the session store and the batcher.

use std::collections::HashMap;
use std::net::IpAddr;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};

/// An open stream (HTTP/2 state, its request and handler task; measured
/// 118 MB -> 3.8 GB for 512,000 HEADERS-only streams: about 7.3 KB).
pub const STREAM_BYTES: usize = 8 << 10;
/// A session: GRU state (4 KB), running sums, held joints, a motion
/// stage's filters, a lifter window (3.7 KB), bookkeeping.
pub const SESSION_BYTES: usize = 16 << 10;
/// A queued frame: its keypoints, pose and reply channel.
pub const FRAME_BYTES: usize = 1 << 10;
/// A connection's own state: the socket, hyper's and h2's buffers and
/// tables, the frame meter (TLS adds its buffers).
pub const CONNECTION_BYTES: usize = 64 << 10;
/// A stream h2 has taken but the stream layer has not yet admitted or
/// refused (measured: 512 connections x 1,000 refused HEADERS-only streams
/// held 0.7-1.0 GB, about 1.9 KB a stream).
pub const PENDING_STREAM_BYTES: usize = 2 << 10;

/// What one HTTP/2 connection may hold before its streams are admitted:
/// itself and `max_concurrent_streams` pending streams.
pub fn http2_connection_bytes(max_concurrent_streams: u32) -> usize {
    CONNECTION_BYTES + max_concurrent_streams as usize * PENDING_STREAM_BYTES
}

/// What one WebSocket connection may hold: itself and its one stream.
pub const WEBSOCKET_CONNECTION_BYTES: usize = CONNECTION_BYTES + STREAM_BYTES;

/// `max_connections`, lowered so that connections of `per_connection`
/// bytes hold at most half of `budget`. Past the budget every new
/// connection is refused, whoever sends it; below half of it the
/// connection table's fair shares decide (an address holds at most
/// `total / (k + 1)` with k addresses connected), so a few addresses that
/// open all they may cannot fill the budget and lock out the next client
/// (measured with `--memory-budget 256M`: 8 addresses x 512 connections
/// took it all and a new client's connection was refused), and the other
/// half stays for sessions and frames.
pub fn connections_within(budget: usize, max_connections: usize, per_connection: usize) -> usize {
    max_connections.min((budget / 2 / per_connection.max(1)).max(1))
}

/// The smallest default budget.
pub const MIN_DEFAULT_BUDGET: usize = 256 << 20;

/// Why new work was refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum BudgetError {
    /// The memory budget is reached.
    #[error("the server is at its memory budget ({accounted} of {budget} bytes accounted, --memory-budget); retry later")]
    Memory {
        /// Bytes accounted.
        accounted: usize,
        /// The budget.
        budget: usize,
    },
    /// The address has its limit of open streams.
    #[error("this address already has {limit} streams open across its connections (--max-streams-per-peer, or its fair share of the streams --memory-budget allows); finish or cancel some first")]
    PeerStreams {
        /// The limit.
        limit: usize,
    },
}

impl BudgetError {
    /// The gRPC status a client sees.
    pub fn to_status(&self) -> tonic::Status {
        tonic::Status::resource_exhausted(self.to_string())
    }
}

/// The server's accounted memory and its budget.
#[derive(Debug)]
pub struct Budget {
    budget: usize,
    per_peer: usize,
    stream_capacity: usize,
    exempt: Vec<IpAddr>,
    streams: AtomicUsize,
    connections: AtomicUsize,
    sampled: AtomicUsize,
    peers: Mutex<HashMap<IpAddr, usize>>,
}

impl Budget {
    /// A budget of `budget` bytes, with at most `per_peer` open streams
    /// per address but those in `exempt` (the trusted proxies: a balancer
    /// carries many clients' streams, and has limits of its own), and no
    /// more than a fair share ([`crate::quota::admit`]) of the streams a
    /// quarter of the budget holds: connections may take half of it
    /// ([`connections_within`]), so a few addresses holding all the streams
    /// they may still leave a newcomer its share, and the last quarter to
    /// sessions and frames.
    pub fn new(budget: usize, per_peer: usize, exempt: Vec<IpAddr>) -> Arc<Self> {
        Arc::new(Self {
            budget,
            per_peer: per_peer.max(1),
            stream_capacity: (budget / 4 / STREAM_BYTES).max(1),
            exempt: exempt.into_iter().map(|ip| ip.to_canonical()).collect(),
            streams: AtomicUsize::new(0),
            connections: AtomicUsize::new(0),
            sampled: AtomicUsize::new(0),
            peers: Mutex::new(HashMap::new()),
        })
    }

    /// The budget in bytes.
    pub fn budget(&self) -> usize {
        self.budget
    }

    /// Bytes accounted now.
    pub fn accounted(&self) -> usize {
        self.streams.load(Ordering::Relaxed) * STREAM_BYTES
            + self.connections.load(Ordering::Relaxed)
            + self.sampled.load(Ordering::Relaxed)
    }

    /// Record the parts sampled from the store and the batcher.
    pub fn sample(&self, sessions: usize, queued_frames: usize, ended_bytes: usize) {
        let bytes = sessions * SESSION_BYTES + queued_frames * FRAME_BYTES + ended_bytes;
        self.sampled.store(bytes, Ordering::Relaxed);
        crate::metrics::memory_accounted(self.accounted());
    }

    /// `Ok` if `bytes` more fit in the budget; a refusal counted otherwise.
    pub fn admit(&self, bytes: usize) -> Result<(), BudgetError> {
        let accounted = self.accounted();
        if accounted.saturating_add(bytes) > self.budget {
            crate::metrics::limited("memory_budget");
            return Err(BudgetError::Memory {
                accounted,
                budget: self.budget,
            });
        }
        Ok(())
    }

    /// Admit a new connection that may hold `bytes` (for example
    /// [`http2_connection_bytes`]); they count until the guard drops.
    pub fn connection(self: &Arc<Self>, bytes: usize) -> Result<BudgetConnection, BudgetError> {
        self.admit(bytes)?;
        self.connections.fetch_add(bytes, Ordering::Relaxed);
        Ok(BudgetConnection {
            budget: self.clone(),
            bytes,
        })
    }

    /// Admit a new stream from `peer`: within the budget and the address's
    /// share; it counts until the guard drops.
    pub fn stream(self: &Arc<Self>, peer: Option<IpAddr>) -> Result<BudgetStream, BudgetError> {
        self.admit(STREAM_BYTES)?;
        let peer = peer.filter(|ip| !self.exempt.contains(ip));
        if let Some(ip) = peer {
            let mut peers = self.peers.lock().unwrap_or_else(|p| p.into_inner());
            let held = peers.get(&ip).copied().unwrap_or(0);
            let used = self.streams.load(Ordering::Relaxed);
            let admitted =
                crate::quota::admit(self.per_peer, self.stream_capacity, used, peers.len(), held);
            if let Err(limit) = admitted {
                crate::metrics::limited("streams_per_peer");
                return Err(BudgetError::PeerStreams { limit });
            }
            *peers.entry(ip).or_default() += 1;
        }
        self.streams.fetch_add(1, Ordering::Relaxed);
        Ok(BudgetStream {
            budget: self.clone(),
            peer,
        })
    }
}

/// An admitted connection's bytes; released when dropped.
#[derive(Debug)]
pub struct BudgetConnection {
    budget: Arc<Budget>,
    bytes: usize,
}

impl Drop for BudgetConnection {
    fn drop(&mut self) {
        self.budget
            .connections
            .fetch_sub(self.bytes, Ordering::Relaxed);
    }
}

/// An admitted stream; released when dropped.
#[derive(Debug)]
pub struct BudgetStream {
    budget: Arc<Budget>,
    peer: Option<IpAddr>,
}

impl Drop for BudgetStream {
    fn drop(&mut self) {
        self.budget.streams.fetch_sub(1, Ordering::Relaxed);
        if let Some(ip) = self.peer {
            let mut peers = self.budget.peers.lock().unwrap_or_else(|p| p.into_inner());
            if let Some(n) = peers.get_mut(&ip) {
                *n -= 1;
                if *n == 0 {
                    peers.remove(&ip);
                }
            }
        }
    }
}

/// The default budget: half the memory this process may use (the cgroup's
/// limit, else the machine's), at least [`MIN_DEFAULT_BUDGET`].
pub fn default_budget() -> usize {
    let machine = std::fs::read_to_string("/proc/meminfo").ok().and_then(|m| {
        m.lines()
            .find_map(|l| l.strip_prefix("MemTotal:"))
            .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<usize>().ok())
            .map(|kb| kb * 1024)
    });
    let cgroup = std::fs::read_to_string("/sys/fs/cgroup/memory.max")
        .ok()
        .and_then(|v| v.trim().parse::<usize>().ok());
    let available = match (machine, cgroup) {
        (Some(m), Some(c)) => m.min(c),
        (m, c) => m.or(c).unwrap_or(2 * MIN_DEFAULT_BUDGET),
    };
    (available / 2).max(MIN_DEFAULT_BUDGET)
}

/// Parse a size: bytes, or with a binary suffix `K`, `M`, `G`, `T`
/// (`512M`, `4G`; an optional trailing `B` or `iB`).
pub fn parse_bytes(text: &str) -> Result<usize, String> {
    let t = text.trim();
    let t = t
        .strip_suffix("iB")
        .or_else(|| t.strip_suffix('B'))
        .unwrap_or(t);
    let (num, scale) = match t.chars().last().map(|c| c.to_ascii_uppercase()) {
        Some('K') => (&t[..t.len() - 1], 1usize << 10),
        Some('M') => (&t[..t.len() - 1], 1 << 20),
        Some('G') => (&t[..t.len() - 1], 1 << 30),
        Some('T') => (&t[..t.len() - 1], 1 << 40),
        _ => (t, 1),
    };
    let value: f64 = num
        .trim()
        .parse()
        .map_err(|_| format!("{text:?}: expected a size such as 512M or 4G"))?;
    if !(value.is_finite() && value >= 1.0) {
        return Err(format!("{text:?}: the size must be at least 1 byte"));
    }
    Ok((value * scale as f64) as usize)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_parse_with_binary_suffixes() {
        assert_eq!(parse_bytes("512M").unwrap(), 512 << 20);
        assert_eq!(parse_bytes("4G").unwrap(), 4 << 30);
        assert_eq!(parse_bytes("1.5GiB").unwrap(), 3 << 29);
        assert_eq!(parse_bytes("1000").unwrap(), 1000);
        assert!(parse_bytes("lots").is_err());
        assert!(parse_bytes("0").is_err());
        assert!(default_budget() >= MIN_DEFAULT_BUDGET);
    }

    #[test]
    fn work_past_the_budget_or_the_peer_share_is_refused_and_freed() {
        let b = Budget::new(40 * STREAM_BYTES, 4, vec!["10.0.0.9".parse().unwrap()]);
        let a: IpAddr = "10.0.0.1".parse().unwrap();
        let held: Vec<_> = (0..4).map(|_| b.stream(Some(a)).unwrap()).collect();
        assert!(matches!(
            b.stream(Some(a)),
            Err(BudgetError::PeerStreams { limit: 4 })
        ));
        let proxy: IpAddr = "10.0.0.9".parse().unwrap();
        let other: Vec<_> = (0..36).map(|_| b.stream(Some(proxy)).unwrap()).collect();
        assert!(matches!(b.stream(None), Err(BudgetError::Memory { .. })));
        drop(other);
        b.sample(0, 0, 35 * STREAM_BYTES);
        assert!(b.stream(None).is_ok(), "one fits");
        assert!(b.admit(2 * STREAM_BYTES).is_err());
        drop(held);
        assert!(b.stream(Some(a)).is_ok());
        let e = BudgetError::PeerStreams { limit: 4 };
        assert_eq!(e.to_status().code(), tonic::Code::ResourceExhausted);
    }

    #[test]
    fn addresses_holding_all_they_may_leave_a_newcomer_streams() {
        // A quarter of the budget holds 64 streams; each address may hold
        // 4,096 but gets no more than its fair share.
        let b = Budget::new(4 * 64 * STREAM_BYTES, 4096, vec![]);
        let mut held = Vec::new();
        for a in 1..=3u8 {
            let ip = IpAddr::from([10, 0, 0, a]);
            while let Ok(s) = b.stream(Some(ip)) {
                held.push(s);
                assert!(held.len() <= 64, "address {a} was never refused");
            }
        }
        assert!(held.len() < 64, "{} streams held", held.len());
        // The next address is served (the reserve kept for a client that
        // holds none), and so is one after it.
        for a in 4..=5u8 {
            held.push(
                b.stream(Some(IpAddr::from([10, 0, 0, a])))
                    .expect("a newcomer's stream"),
            );
        }
    }

    #[test]
    fn connections_hold_at_most_half_the_budget() {
        let each = http2_connection_bytes(100);
        assert_eq!(connections_within(12 << 30, 4096, each), 4096);
        assert_eq!(connections_within(256 << 20, 4096, each), 496);
        assert_eq!(connections_within(1 << 10, 4096, each), 1);
    }

    #[test]
    fn connections_count_what_they_may_hold_until_they_close() {
        let per_connection = http2_connection_bytes(100);
        assert_eq!(
            per_connection,
            CONNECTION_BYTES + 100 * PENDING_STREAM_BYTES
        );
        let b = Budget::new(3 * per_connection + STREAM_BYTES, 8, vec![]);
        let held: Vec<_> = (0..3)
            .map(|_| b.connection(per_connection).unwrap())
            .collect();
        assert_eq!(b.accounted(), 3 * per_connection);
        assert!(matches!(
            b.connection(per_connection),
            Err(BudgetError::Memory { .. })
        ));
        assert!(b.stream(None).is_ok(), "a stream still fits");
        drop(held);
        assert_eq!(b.accounted(), 0);
        assert!(b.connection(WEBSOCKET_CONNECTION_BYTES).is_ok());
    }
}

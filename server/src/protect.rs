//! The settings that protect the server from many sources at once:
//! connections kept without use, connections kept for ever, control-frame
//! floods (and, with them, the flags that set each). Kept apart from
//! [`crate::config`] because they are one concern, how long and how hard a
//! connection may hold the server, and because each is enforced in one
//! place ([`crate::connection`], [`crate::frames`]).
//!
//! Why these defaults:
//! * `--max-connection-idle` 5 min: a connection with no open stream is
//!   sent GOAWAY and closed after it. HTTP/2 PINGs keep a TCP connection
//!   alive but prove nobody uses it; 8 addresses x 512 such connections
//!   held all of `--max-connections` for as long as they liked. Five
//!   minutes keeps the connection (and its TLS handshake) of a client that
//!   pauses between sessions, and hands back an abandoned or hostile one
//!   within minutes; clients (tonic, grpcio) reconnect on GOAWAY by
//!   themselves. gRPC servers default to no limit; Envoy's idle timeout is
//!   1 h; a server whose clients hold long pauses may raise it.
//! * `--max-connection-age` off, `--max-connection-age-grace` 30 s: as in
//!   gRPC (`MAX_CONNECTION_AGE`): set it behind a balancer to spread
//!   long-lived connections over new replicas; streams still open after
//!   the grace period are cut.
//! * `--max-control-frames-per-second` 10,000: PING, SETTINGS,
//!   WINDOW_UPDATE, RST_STREAM and PRIORITY frames one connection may send
//!   per second. Clients send a few per second (a WINDOW_UPDATE per 32 KB
//!   received per stream, a keepalive PING every 30 s, an RST_STREAM per
//!   cancelled call), bursts of a few hundred; a flood sends millions.
//! * `--memory-budget`: half the memory the process may use (its cgroup's
//!   limit, else the machine's), at least 256 MB ([`crate::budget`]);
//!   `--max-streams-per-peer` 4,096: open streams of one address across
//!   all its connections (the load test's 1,024 streams from one client
//!   fit), about 32 MB, and no more than a fair share of a quarter of the
//!   budget's streams.
//! * `--max-ended-sessions` 100,000 (a sixteenth, at least 1,024, per
//!   client): ended sessions remembered so that their tokens do not revive
//!   them, about 100 bytes each (10 MB); past it the oldest go and a floor
//!   on token issue times keeps them ended ([`crate::session::retired`]).

use std::time::Duration;

use clap::builder::TypedValueParser;
use clap::Args;

use crate::duration::parse_duration;

/// How long connections may live, and how many control frames they send.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Protection {
    /// A connection with no open stream this long is closed (GOAWAY);
    /// `None`: never.
    pub max_connection_idle: Option<Duration>,
    /// A connection this old is sent GOAWAY; `None`: never.
    pub max_connection_age: Option<Duration>,
    /// After GOAWAY (age or idle), how long its open streams may finish
    /// before the connection is cut.
    pub max_connection_age_grace: Duration,
    /// Control frames one connection may send per second; more: GOAWAY and
    /// closed.
    pub max_control_frames_per_second: u32,
    /// Ended sessions remembered at once (a sixteenth per client).
    pub max_ended_sessions: usize,
    /// The memory budget in bytes; `None`: sized from the machine.
    pub memory_budget: Option<usize>,
    /// Open streams one address may have across its connections.
    pub max_streams_per_peer: usize,
}

/// Default `--max-streams-per-peer`.
pub const DEFAULT_MAX_STREAMS_PER_PEER: usize = 4096;

/// Default `--max-connection-idle`.
pub const DEFAULT_MAX_CONNECTION_IDLE: Duration = Duration::from_secs(300);
/// Default `--max-connection-age-grace`.
pub const DEFAULT_MAX_CONNECTION_AGE_GRACE: Duration = Duration::from_secs(30);
/// Default `--max-control-frames-per-second`.
pub const DEFAULT_MAX_CONTROL_FRAMES_PER_SECOND: u32 = 10_000;

impl Default for Protection {
    fn default() -> Self {
        Self {
            max_connection_idle: Some(DEFAULT_MAX_CONNECTION_IDLE),
            max_connection_age: None,
            max_connection_age_grace: DEFAULT_MAX_CONNECTION_AGE_GRACE,
            max_control_frames_per_second: DEFAULT_MAX_CONTROL_FRAMES_PER_SECOND,
            max_ended_sessions: crate::session::DEFAULT_MAX_ENDED,
            memory_budget: None,
            max_streams_per_peer: DEFAULT_MAX_STREAMS_PER_PEER,
        }
    }
}

/// The flags of [`Protection`] (flattened into `blapose-server`'s).
#[derive(Debug, Clone, Args)]
pub struct ProtectionArgs {
    /// A connection with no open stream for this long is sent GOAWAY and closed (keepalive
    /// PINGs do not keep it); 0 = never.
    #[arg(long, env = "BLAPOSE_MAX_CONNECTION_IDLE", default_value = "5m", value_parser = parse_duration)]
    pub max_connection_idle: Duration,

    /// A connection this old is sent GOAWAY (clients reconnect); 0 = never.
    #[arg(long, env = "BLAPOSE_MAX_CONNECTION_AGE", default_value = "0", value_parser = parse_duration)]
    pub max_connection_age: Duration,

    /// After an age or idle GOAWAY, how long open streams may finish before the connection is
    /// cut.
    #[arg(long, env = "BLAPOSE_MAX_CONNECTION_AGE_GRACE", default_value = "30s", value_parser = parse_duration)]
    pub max_connection_age_grace: Duration,

    /// Control frames (PING, SETTINGS, WINDOW_UPDATE, RST_STREAM, PRIORITY) one connection may
    /// send per second; more: GOAWAY and closed.
    #[arg(long, env = "BLAPOSE_MAX_CONTROL_FRAMES_PER_SECOND",
          default_value_t = DEFAULT_MAX_CONTROL_FRAMES_PER_SECOND,
          value_parser = clap::value_parser!(u32).range(1..))]
    pub max_control_frames_per_second: u32,

    /// Ended sessions remembered (so that their tokens cannot revive them), all clients; a
    /// sixteenth (at least 1,024) per client. Past it the oldest are forgotten and tokens issued
    /// before them refused.
    #[arg(long, env = "BLAPOSE_MAX_ENDED_SESSIONS", default_value_t = crate::session::DEFAULT_MAX_ENDED,
          value_parser = clap::value_parser!(u32).range(1..).map(|v| v as usize))]
    pub max_ended_sessions: usize,

    /// Memory the server may account for its clients (streams, sessions, queued frames, ended
    /// sessions), e.g. 4G; past it new connections, streams, sessions and frames are refused.
    /// Default: half of the cgroup's or the machine's memory, at least 256M.
    #[arg(long, env = "BLAPOSE_MEMORY_BUDGET", value_name = "BYTES", value_parser = crate::budget::parse_bytes)]
    pub memory_budget: Option<usize>,

    /// Open streams one IP address may have across all its connections; more: RESOURCE_EXHAUSTED.
    #[arg(long, env = "BLAPOSE_MAX_STREAMS_PER_PEER", default_value_t = DEFAULT_MAX_STREAMS_PER_PEER,
          value_parser = clap::value_parser!(u32).range(1..).map(|v| v as usize))]
    pub max_streams_per_peer: usize,
}

impl From<ProtectionArgs> for Protection {
    fn from(a: ProtectionArgs) -> Self {
        let nonzero = |d: Duration| (!d.is_zero()).then_some(d);
        Self {
            max_connection_idle: nonzero(a.max_connection_idle),
            max_connection_age: nonzero(a.max_connection_age),
            max_connection_age_grace: a.max_connection_age_grace,
            max_control_frames_per_second: a.max_control_frames_per_second,
            max_ended_sessions: a.max_ended_sessions,
            memory_budget: a.memory_budget,
            max_streams_per_peer: a.max_streams_per_peer,
        }
    }
}

impl Protection {
    /// Export the settings as `blapose_limit{limit}` gauges (durations in
    /// ms, 0 = off).
    pub fn export(&self) {
        let ms = |d: Option<Duration>| {
            d.map_or(0, |d| usize::try_from(d.as_millis()).unwrap_or(usize::MAX))
        };
        crate::metrics::limit("max_connection_idle_ms", ms(self.max_connection_idle));
        crate::metrics::limit("max_connection_age_ms", ms(self.max_connection_age));
        crate::metrics::limit(
            "max_connection_age_grace_ms",
            ms(Some(self.max_connection_age_grace)),
        );
        crate::metrics::limit(
            "max_control_frames_per_second",
            self.max_control_frames_per_second as usize,
        );
        let ended = crate::session::EndedLimits::with_max(self.max_ended_sessions);
        crate::metrics::limit("max_ended_sessions", ended.max);
        crate::metrics::limit("max_ended_sessions_per_client", ended.per_client);
        crate::metrics::limit("max_streams_per_peer", self.max_streams_per_peer);
    }
}

//! `abuse`: the server's limits under abuse, each case asserting its limit
//! (`tests/abuse/run.sh` starts the servers and runs every case; loopback
//! only, bounded, under three minutes together; `tests/abuse/full-scale.sh`
//! runs some at full scale, by hand).
//!
//! ```sh
//! abuse streams  --server URL --server-pid PID --streams 400 --limit 64
//! abuse sessions --server URL --server-pid PID --header x-blapose-client --limit 8
//! abuse token    --server URL --replica URL --token-ttl 4
//! abuse bomb     --out bomb.npz
//! abuse dirbomb  --out dirbomb.npz --entries 200000
//! abuse pending  --server URL --server-pid PID --addresses 4 --connections 4 --streams 500 --limit 1000
//! abuse shares   --server URL --server-pid PID --addresses 8 --max-sessions 256
//! abuse churn    --server URL --server-pid PID --sessions 20000
//! abuse proxy6   --server URL --server-pid PID --header x-blapose-client --limit 8
//! abuse headers  --server URL --server-pid PID --count 120000
//! abuse preface  --server URL --server-pid PID --connections 2000
//! abuse idle     --server URL --server-pid PID --connections 400 --addresses 8 --idle 2
//! abuse flood    --server URL --server-pid PID
//! ```
//!
//! Every case that has a victim measures a *healthy client*: its own
//! connection and session, one frame at a time, its round trips timed
//! alone (the baseline) and again while the abuse runs; its p99 must stay
//! within 2x of the baseline's, with a 5 ms floor (loopback round trips
//! are a fraction of a millisecond, and a busy two-core machine puts a 4-5
//! ms p99 into runs with or without abuse: server/README.md), in one of up
//! to three measurements; a new connection and session each time, so a new
//! client must be served ([`client::Victim`]). The server's resident
//! memory (VmRSS from /proc, its peak sampled every 20 ms) may grow at most
//! 64 MB over a case unless the case takes another bound.
//!
//! - `streams`: one HTTP/2 connection opens many streams, each a session;
//!   at most `--limit` (the server's `--max-concurrent-streams`) may be
//!   open at once.
//! - `sessions`: one client (by `--header`, the server's `--client-header`
//!   from a trusted proxy) opens sessions as fast as it can while another
//!   streams; it may hold at most `--limit` (`--max-sessions-per-client`),
//!   the rest RESOURCE_EXHAUSTED.
//! - `token`: a session token resumed on two replicas sharing the key, as
//!   server/README.md's token rules say: one live copy per replica (a
//!   second resume takes the session over, the first stream ends ABORTED),
//!   the token of a closed session refused where it closed, and after the
//!   first token's TTL neither it nor the token the other replica's copy
//!   issued (the chain) restores the closed session anywhere. A copy on
//!   each replica is allowed (bounded by `--token-ttl`) and reported.
//! - `bomb`: writes a replay file with a 2 GiB zero member deflated to
//!   about 2 MB (used as `pose_3d`), for the script to run the client on.
//! - `dirbomb`: writes the example replay file with `--entries` central
//!   directory entries more ([`files`]), for the script to run
//!   `blapose-client` and Python's `load_replay` on.
//! - `pending`, `shares` ([`sources`]): HEADERS-only streams from several
//!   addresses over many connections; several addresses each holding all
//!   the sessions they can, then reading slowly.
//! - `churn` ([`churn`]): one client opening and closing sessions as fast
//!   as it can; `proxy6` ([`proxy`]): the balancer's header on a `[::]`
//!   listener.
//! - `headers` (by hand, not in the script): one raw HTTP/2 connection
//!   sends HEADERS frames for the stream method as fast as the socket takes
//!   them, ignoring SETTINGS_MAX_CONCURRENT_STREAMS ([`raw`]).
//! - `preface` (by hand, not in the script): TCP connections from
//!   127.0.0.2-9 that never send the HTTP/2 preface (the server closes them
//!   at its `--handshake-timeout`); the healthy client comes from 127.0.0.1.
//! - `idle`: connections from several addresses that send the preface and
//!   then only answer keepalive PINGs; each must get GOAWAY within the
//!   server's `--max-connection-idle` + 10 s.
//! - `flood`: one connection flooding WINDOW_UPDATE frames must get GOAWAY
//!   within a second (`--max-control-frames-per-second`).
//!
//! A limit the server does not enforce fails the case with "not enforced".

use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{ensure, Result};
use clap::{Parser, Subcommand};
use tokio::sync::mpsc;
use tonic::Code;

mod churn;
mod client;
mod connections;
mod files;
mod proxy;
mod raw;
mod sources;
mod token;

use client::{connect, frames, open, opened, round_trip, start, Victim, MAX_RSS_GROWTH};

/// Abuse cases against a running blapose server.
#[derive(Debug, Parser)]
#[command(name = "abuse", version)]
struct Args {
    #[command(subcommand)]
    case: Case,
}

/// The server a case abuses.
#[derive(Debug, clap::Args)]
struct Target {
    /// The server (http://IP:PORT; a `[::]` listener is reached on
    /// 127.0.0.1, a `--session-key` one remembers ended sessions).
    #[arg(long)]
    server: String,
    /// Its process id (for its memory).
    #[arg(long)]
    server_pid: u32,
}

#[derive(Debug, Subcommand)]
enum Case {
    /// Many streams on one connection.
    Streams {
        #[command(flatten)]
        target: Target,
        /// Streams to open on the one connection.
        #[arg(long, default_value_t = 400)]
        streams: usize,
        /// The server's --max-concurrent-streams.
        #[arg(long)]
        limit: usize,
    },
    /// Rapid session opening from one client while another streams.
    Sessions {
        #[command(flatten)]
        target: Target,
        /// The header naming the client (the server's --client-header).
        #[arg(long)]
        header: String,
        /// Sessions to try to open at least (it goes on while the healthy
        /// client streams).
        #[arg(long, default_value_t = 200)]
        attempts: usize,
        /// The server's --max-sessions-per-client.
        #[arg(long)]
        limit: usize,
    },
    /// A session token resumed on two replicas.
    Token {
        /// The replica the session is opened on.
        #[arg(long)]
        server: String,
        /// A second replica with the same --session-key.
        #[arg(long)]
        replica: String,
        /// The replicas' --token-ttl, in seconds.
        #[arg(long, default_value_t = 4.0)]
        token_ttl: f64,
    },
    /// PING-only connections from several addresses.
    Idle {
        #[command(flatten)]
        target: Target,
        /// Connections to open.
        #[arg(long, default_value_t = 400)]
        connections: usize,
        /// Loopback addresses they come from (127.0.0.2 and up).
        #[arg(long, default_value_t = 8)]
        addresses: usize,
        /// The server's --max-connection-idle, in seconds.
        #[arg(long)]
        idle: f64,
    },
    /// One connection flooding WINDOW_UPDATE frames.
    Flood {
        #[command(flatten)]
        target: Target,
    },
    /// Write the zip-bomb replay file.
    Bomb {
        /// Where.
        #[arg(long)]
        out: PathBuf,
    },
    /// HEADERS frames on one raw connection, past the stream limit.
    Headers {
        #[command(flatten)]
        target: Target,
        /// HEADERS frames to send.
        #[arg(long, default_value_t = 120_000)]
        count: u32,
    },
    /// HEADERS-only streams from several addresses over many connections.
    Pending {
        #[command(flatten)]
        target: Target,
        /// Loopback addresses (127.0.0.2 and up).
        #[arg(long, default_value_t = 4)]
        addresses: usize,
        /// Connections from each address.
        #[arg(long, default_value_t = 4)]
        connections: usize,
        /// HEADERS-only streams on each connection.
        #[arg(long, default_value_t = 500)]
        streams: u32,
        /// The server's --max-streams-per-peer, checked per address.
        #[arg(long)]
        limit: Option<u64>,
        /// Bound on the server's peak memory growth, MB.
        #[arg(long, default_value_t = 64)]
        max_growth_mb: u64,
    },
    /// Several addresses each holding as many sessions as they can.
    Shares {
        #[command(flatten)]
        target: Target,
        /// Loopback addresses (127.0.0.2 and up).
        #[arg(long, default_value_t = 2)]
        addresses: usize,
        /// The server's --max-sessions.
        #[arg(long)]
        max_sessions: usize,
        /// The least p99 bound for the healthy client, ms: the slow
        /// readers' frames keep the server's one batcher busy, and a new
        /// client's frame waits for the batch in progress and runs in the
        /// next (sources::shares).
        #[arg(long, default_value_t = 5)]
        p99_floor_ms: u64,
    },
    /// One client opening and closing sessions as fast as it can.
    Churn {
        #[command(flatten)]
        target: Target,
        /// Sessions to open and close.
        #[arg(long, default_value_t = 20_000)]
        sessions: u64,
        /// Connections churning at once (one session each at a time):
        /// two keep a 2-core machine's server busy (about 5,000 a second)
        /// while leaving the healthy client a core's share; more measure
        /// the CPU, not the memory this case bounds.
        #[arg(long, default_value_t = 2)]
        parallel: usize,
        /// Bound on the server's peak memory growth, MB.
        #[arg(long, default_value_t = 64)]
        max_growth_mb: u64,
    },
    /// The client header from a trusted proxy on a [::] listener.
    Proxy6 {
        #[command(flatten)]
        target: Target,
        /// The server's --client-header.
        #[arg(long)]
        header: String,
        /// The server's --max-sessions-per-client.
        #[arg(long)]
        limit: usize,
    },
    /// Write a central-directory bomb replay file.
    Dirbomb {
        /// Where.
        #[arg(long)]
        out: PathBuf,
        /// Directory entries beyond the valid replay file's.
        #[arg(long, default_value_t = 200_000)]
        entries: u64,
    },
    /// Connections that never send the HTTP/2 preface.
    Preface {
        #[command(flatten)]
        target: Target,
        /// Connections to open.
        #[arg(long, default_value_t = 2000)]
        connections: u32,
    },
}

async fn streams(url: &str, pid: u32, n: usize, limit: usize) -> Result<()> {
    println!("case streams: {n} streams on one connection (limit {limit})");
    let (format, frames) = frames()?;
    let victim = Victim::before(url, None, pid).await?;
    let client = connect(url).await?;
    let mut tasks = Vec::new();
    let (done_tx, _) = tokio::sync::broadcast::channel::<()>(1);
    let (opened_tx, mut opened_rx) = mpsc::unbounded_channel::<bool>();
    for _ in 0..n {
        let mut client = client.clone();
        let frame = frames[0].clone();
        let mut done = done_tx.subscribe();
        let opened_tx = opened_tx.clone();
        tasks.push(tokio::spawn(async move {
            let Ok(mut stream) = start(&mut client, open(&format, false), None).await else {
                let _ = opened_tx.send(false);
                return;
            };
            let ok = opened(&mut stream).await.is_ok();
            let _ = opened_tx.send(ok);
            if ok {
                // Hold the session open, sending a frame now and then.
                loop {
                    tokio::select! {
                        _ = done.recv() => break,
                        _ = tokio::time::sleep(Duration::from_millis(200)) => {
                            if round_trip(&mut stream, &frame).await.is_err() { break; }
                        }
                    }
                }
            }
        }));
    }
    drop(opened_tx);
    // Give the server time to answer every stream it accepts.
    let deadline = Instant::now() + Duration::from_secs(5);
    let (mut open_now, mut refused) = (0usize, 0usize);
    while let Ok(Some(ok)) = tokio::time::timeout_at(deadline.into(), opened_rx.recv()).await {
        if ok {
            open_now += 1;
        } else {
            refused += 1;
        }
    }
    let latency = victim.during().await;
    let _ = done_tx.send(());
    for t in &tasks {
        t.abort();
    }
    println!(
        "  sessions open at once on the connection: {open_now} (refused {refused}, waiting {})",
        n - open_now - refused
    );
    victim.check(latency, MAX_RSS_GROWTH)?;
    ensure!(
        open_now <= limit,
        "not enforced: {open_now} streams open at once on one connection, limit {limit}"
    );
    Ok(())
}

async fn sessions(url: &str, pid: u32, header: &str, attempts: usize, limit: usize) -> Result<()> {
    println!("case sessions: one client opens sessions as fast as it can while another streams (limit {limit})");
    let (format, _) = frames()?;
    let victim = Victim::before(url, Some(header), pid).await?;
    let url_owned = url.to_owned();
    let header_owned = header.to_owned();
    let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let stop_attack = stop.clone();
    let attacker = tokio::spawn(async move {
        let mut client = connect(&url_owned).await?;
        let (mut held, mut exhausted, mut other) = (Vec::new(), 0usize, 0usize);
        // At least `attempts`, and on until the healthy client is done.
        let mut tried = 0;
        while tried < attempts || !stop_attack.load(std::sync::atomic::Ordering::Relaxed) {
            tried += 1;
            let result = match start(
                &mut client,
                open(&format, false),
                Some((&header_owned, "attacker")),
            )
            .await
            {
                Ok(mut stream) => opened(&mut stream).await.map(|_| stream),
                Err(status) => Err(status),
            };
            match result {
                Ok(stream) => held.push(stream),
                Err(s) if s.code() == Code::ResourceExhausted => exhausted += 1,
                Err(s) => {
                    other += 1;
                    if other == 1 {
                        println!("  attacker refused otherwise: {s}");
                    }
                }
            }
        }
        anyhow::Ok((held, exhausted, other, tried))
    });
    let latency = victim.during().await;
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    let (held, exhausted, other, attempts) = attacker.await??;
    println!(
        "  attacker tried {attempts} opens: holds {} sessions, {exhausted} RESOURCE_EXHAUSTED, {other} other refusals",
        held.len()
    );
    drop(held);
    victim.check(latency, MAX_RSS_GROWTH)?;
    ensure!(
        exhausted > 0 && attempts - exhausted - other <= limit,
        "not enforced: one client opened {} sessions, limit {limit}",
        attempts - exhausted - other
    );
    Ok(())
}

#[tokio::main]
async fn main() -> Result<()> {
    let args = Args::parse();
    let start = Instant::now();
    match &args.case {
        Case::Streams {
            target: Target { server, server_pid },
            streams: n,
            limit,
        } => streams(server, *server_pid, *n, *limit).await?,
        Case::Sessions {
            target: Target { server, server_pid },
            header,
            attempts,
            limit,
        } => sessions(server, *server_pid, header, *attempts, *limit).await?,
        Case::Token {
            server,
            replica,
            token_ttl,
        } => token::token(server, replica, Duration::from_secs_f64(*token_ttl)).await?,
        Case::Bomb { out } => files::bomb(out)?,
        Case::Dirbomb { out, entries } => files::dirbomb(out, *entries)?,
        Case::Pending {
            target: Target { server, server_pid },
            addresses,
            connections,
            streams,
            limit,
            max_growth_mb,
        } => {
            let bound = max_growth_mb << 20;
            sources::pending(
                server,
                *server_pid,
                *addresses,
                *connections,
                *streams,
                *limit,
                bound,
            )
            .await?
        }
        Case::Shares {
            target: Target { server, server_pid },
            addresses,
            max_sessions,
            p99_floor_ms,
        } => {
            let floor = Duration::from_millis(*p99_floor_ms);
            sources::shares(server, *server_pid, *addresses, *max_sessions, floor).await?
        }
        Case::Churn {
            target: Target { server, server_pid },
            sessions,
            parallel,
            max_growth_mb,
        } => {
            churn::churn(
                server,
                *server_pid,
                *sessions,
                *parallel,
                max_growth_mb << 20,
            )
            .await?
        }
        Case::Proxy6 {
            target: Target { server, server_pid },
            header,
            limit,
        } => proxy::proxy6(server, *server_pid, header, *limit).await?,
        Case::Headers {
            target: Target { server, server_pid },
            count,
        } => raw::headers(server, *server_pid, *count).await?,
        Case::Preface {
            target: Target { server, server_pid },
            connections,
        } => raw::preface(server, *server_pid, *connections).await?,
        Case::Idle {
            target: Target { server, server_pid },
            connections: n,
            addresses,
            idle,
        } => {
            let idle = Duration::from_secs_f64(*idle);
            connections::idle(server, *server_pid, *n, *addresses, idle).await?
        }
        Case::Flood {
            target: Target { server, server_pid },
        } => connections::flood(server, *server_pid).await?,
    }
    println!("  ok ({:.1} s)", start.elapsed().as_secs_f64());
    Ok(())
}

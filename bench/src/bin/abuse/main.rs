//! `abuse`: the server's limits under abuse, each case asserting its limit
//! (`tests/abuse/run.sh` starts the servers and runs every case; loopback
//! only, bounded, well under two minutes together).
//!
//! ```sh
//! abuse streams  --server URL --server-pid PID --streams 400 --limit 64
//! abuse sessions --server URL --server-pid PID --header x-blapose-client --limit 8
//! abuse token    --server URL --replica URL --token-ttl 4
//! abuse bomb     --out bomb.npz
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
//! to three measurements. The server's resident memory (VmRSS from /proc)
//! must grow at most 64 MB during one connection's abuse.
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
//!   the token of a closed session refused where it closed, an expired one
//!   refused everywhere. A copy on each replica is allowed (bounded by
//!   `--token-ttl`) and reported.
//! - `bomb`: writes a replay file with a 2 GiB zero member deflated to
//!   about 2 MB (used as `pose_3d`), for the script to run the client on.
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

use std::io::Write;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{ensure, Context, Result};
use blapose_proto::v1 as pb;
use clap::{Parser, Subcommand};
use pb::pose_adjustment_client::PoseAdjustmentClient;
use pb::stream_request::Kind as Req;
use pb::stream_response::Kind as Resp;
use tokio::sync::mpsc;
use tonic::transport::Channel;
use tonic::Code;

mod client;
mod connections;
mod raw;

use client::{
    check_growth, check_latency, connect, frames, healthy, open, opened, round_trip, rss,
    rss_growth, start, Stream, HEALTHY_FRAMES,
};

/// Abuse cases against a running blapose server.
#[derive(Debug, Parser)]
#[command(name = "abuse", version)]
struct Args {
    #[command(subcommand)]
    case: Case,
}

#[derive(Debug, Subcommand)]
enum Case {
    /// Many streams on one connection.
    Streams {
        /// The server.
        #[arg(long)]
        server: String,
        /// Its process id (for its memory).
        #[arg(long)]
        server_pid: u32,
        /// Streams to open on the one connection.
        #[arg(long, default_value_t = 400)]
        streams: usize,
        /// The server's --max-concurrent-streams.
        #[arg(long)]
        limit: usize,
    },
    /// Rapid session opening from one client while another streams.
    Sessions {
        /// The server.
        #[arg(long)]
        server: String,
        /// Its process id (for its memory).
        #[arg(long)]
        server_pid: u32,
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
        /// The server.
        #[arg(long)]
        server: String,
        /// Its process id (for its memory).
        #[arg(long)]
        server_pid: u32,
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
        /// The server.
        #[arg(long)]
        server: String,
        /// Its process id (for its memory).
        #[arg(long)]
        server_pid: u32,
    },
    /// Write the zip-bomb replay file.
    Bomb {
        /// Where.
        #[arg(long)]
        out: PathBuf,
    },
    /// HEADERS frames on one raw connection, past the stream limit.
    Headers {
        /// The server.
        #[arg(long)]
        server: String,
        /// Its process id (for its memory).
        #[arg(long)]
        server_pid: u32,
        /// HEADERS frames to send.
        #[arg(long, default_value_t = 120_000)]
        count: u32,
    },
    /// Connections that never send the HTTP/2 preface.
    Preface {
        /// The server.
        #[arg(long)]
        server: String,
        /// Its process id (for its memory).
        #[arg(long)]
        server_pid: u32,
        /// Connections to open.
        #[arg(long, default_value_t = 2000)]
        connections: u32,
    },
}

async fn streams(url: &str, pid: u32, n: usize, limit: usize) -> Result<()> {
    println!("case streams: {n} streams on one connection (limit {limit})");
    let (format, frames) = frames()?;
    let baseline = healthy(url, None, HEALTHY_FRAMES).await?;
    let rss_before = rss(pid)?;
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
    let latency = check_latency(url, None, &baseline).await;
    let rss_after = rss(pid)?;
    let _ = done_tx.send(());
    for t in &tasks {
        t.abort();
    }
    println!(
        "  sessions open at once on the connection: {open_now} (refused {refused}, waiting {})",
        n - open_now - refused
    );
    let growth = rss_growth(rss_before, rss_after);
    latency?;
    check_growth(growth)?;
    ensure!(
        open_now <= limit,
        "not enforced: {open_now} streams open at once on one connection, limit {limit}"
    );
    Ok(())
}

async fn sessions(url: &str, pid: u32, header: &str, attempts: usize, limit: usize) -> Result<()> {
    println!("case sessions: one client opens sessions as fast as it can while another streams (limit {limit})");
    let (format, _) = frames()?;
    let baseline = healthy(url, Some(header), HEALTHY_FRAMES).await?;
    let rss_before = rss(pid)?;
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
    let latency = check_latency(url, Some(header), &baseline).await;
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    let (held, exhausted, other, attempts) = attacker.await??;
    let rss_after = rss(pid)?;
    println!(
        "  attacker tried {attempts} opens: holds {} sessions, {exhausted} RESOURCE_EXHAUSTED, {other} other refusals",
        held.len()
    );
    let growth = rss_growth(rss_before, rss_after);
    drop(held);
    latency?;
    check_growth(growth)?;
    ensure!(
        exhausted > 0 && attempts - exhausted - other <= limit,
        "not enforced: one client opened {} sessions, limit {limit}",
        attempts - exhausted - other
    );
    Ok(())
}

/// Resume `id` with `token` on `client`; the stream and its opening.
async fn resume(
    client: &mut PoseAdjustmentClient<Channel>,
    id: &str,
    token: &[u8],
) -> Result<(Stream, pb::SessionOpened), tonic::Status> {
    let first = Req::Resume(pb::ResumeSession {
        session_id: id.to_owned(),
        session_token: token.to_vec(),
        session_tokens: true,
    });
    let mut stream = start(client, first, None).await?;
    let o = opened(&mut stream).await?;
    Ok((stream, o))
}

/// Whether `stream` still answers a frame; the status it ended with if not.
async fn answers(stream: &mut Stream, frame: &pb::Frame) -> Result<(), tonic::Status> {
    round_trip(stream, frame)
        .await
        .map(|_| ())
        .map_err(|e| match e.downcast::<tonic::Status>() {
            Ok(status) => status,
            Err(e) => tonic::Status::unknown(e.to_string()),
        })
}

/// The token rules of server/README.md under abuse: one live copy per
/// replica (a second resume of the same token takes the session over, the
/// first stream ends ABORTED), a closed session's token refused where it
/// was closed, and an expired token refused on every replica. Two replicas
/// may each restore one copy (documented, bounded by --token-ttl).
async fn token(url: &str, replica: &str, ttl: Duration) -> Result<()> {
    println!("case token: one session token resumed on two replicas (token TTL {ttl:?})");
    let (format, frames) = frames()?;
    let mut a = connect(url).await?;
    let mut stream = start(&mut a, open(&format, true), None).await?;
    let session = opened(&mut stream).await?;
    let issued = Instant::now();
    let id = session.session_id.clone();
    for frame in &frames[..10] {
        round_trip(&mut stream, frame).await?;
    }
    stream
        .tx
        .send(pb::StreamRequest {
            kind: Some(Req::TokenRequest(pb::TokenRequest {})),
        })
        .await?;
    let mut token = Vec::new();
    while let Some(r) = stream.rx.message().await? {
        if let Some(Resp::Token(t)) = r.kind {
            token = t.token;
            break;
        }
    }
    ensure!(
        !token.is_empty(),
        "no session token: start the replicas with --session-key"
    );
    drop(stream);
    tokio::time::sleep(Duration::from_millis(100)).await;

    // The token on both replicas at once, then again on the origin.
    let mut b = connect(replica).await?;
    let mut a1 = connect(url).await?;
    let mut a2 = connect(url).await?;
    let (on_b, on_a) = tokio::join!(resume(&mut b, &id, &token), resume(&mut a1, &id, &token));
    let (mut on_b, _) = on_b.context("resume on the replica")?;
    let (mut first_a, _) = on_a.context("resume on the origin")?;
    answers(&mut on_b, &frames[10]).await?;
    answers(&mut first_a, &frames[10]).await?;
    println!("  resumed on both replicas (one copy each, as documented: bounded by the token TTL)");
    let (mut second_a, _) = resume(&mut a2, &id, &token)
        .await
        .context("second resume on the origin")?;
    answers(&mut second_a, &frames[10]).await?;
    let mut failures = Vec::new();
    match answers(&mut first_a, &frames[11]).await {
        Err(s) if s.code() == Code::Aborted => {
            println!("  a second resume on the origin took the session over: the first stream ended ABORTED")
        }
        other => failures.push(format!(
            "not enforced: two live copies on one replica (the first stream: {other:?})"
        )),
    }

    // Close it on the origin: its token is refused there afterwards.
    second_a
        .tx
        .send(pb::StreamRequest {
            kind: Some(Req::Close(pb::CloseSession {})),
        })
        .await?;
    while let Ok(Some(r)) = second_a.rx.message().await {
        if matches!(r.kind, Some(Resp::Closed(_))) {
            break;
        }
    }
    let mut a3 = connect(url).await?;
    match resume(&mut a3, &id, &token).await {
        Err(s) if s.code() == Code::FailedPrecondition => {
            println!(
                "  after close, the token is refused on the origin: {}",
                s.message()
            )
        }
        Err(s) => failures.push(format!(
            "after close, the origin refused with {} (expected FAILED_PRECONDITION): {}",
            s.code(),
            s.message()
        )),
        Ok(_) => failures.push("not enforced: a closed session was restored from its token".into()),
    }

    // Expired: refused on every replica.
    tokio::time::sleep(
        (issued + ttl + Duration::from_millis(500)).saturating_duration_since(Instant::now()),
    )
    .await;
    drop(on_b);
    for (name, url) in [("replica", replica), ("origin", url)] {
        let mut c = connect(url).await?;
        match resume(&mut c, &id, &token).await {
            Err(s) if s.code() == Code::FailedPrecondition => {
                println!("  expired token refused on the {name}: {}", s.message())
            }
            Err(s) => failures.push(format!(
                "the expired token on the {name}: {} {}",
                s.code(),
                s.message()
            )),
            Ok(_) => failures.push(format!(
                "not enforced: an expired token restored the session on the {name}"
            )),
        }
    }
    for f in &failures {
        println!("  FAIL: {f}");
    }
    ensure!(
        failures.is_empty(),
        "{} token rule(s) do not hold",
        failures.len()
    );
    Ok(())
}

/// The zip-bomb replay file: a valid replay file whose `pose_3d` is a
/// right header followed by 2 GiB of zeros (about 2 MB deflated).
fn bomb(out: &PathBuf) -> Result<()> {
    let (_, frames) = frames()?;
    let t = frames.len();
    let file = std::fs::File::create(out)?;
    let mut zip = zip::ZipWriter::new(std::io::BufWriter::new(file));
    let options = zip::write::SimpleFileOptions::default()
        .compression_method(zip::CompressionMethod::Deflated);
    let npy = |shape: String| {
        let header = format!("{{'descr': '<f4', 'fortran_order': False, 'shape': {shape}, }}\n");
        let mut out = b"\x93NUMPY\x01\x00".to_vec();
        out.extend_from_slice(&(header.len() as u16).to_le_bytes());
        out.extend_from_slice(header.as_bytes());
        out
    };
    zip.start_file("keypoints_2d.npy", options)?;
    zip.write_all(&npy(format!("({t}, 17, 2)")))?;
    for f in &frames {
        for v in &f.keypoints_2d {
            zip.write_all(&v.to_le_bytes())?;
        }
    }
    zip.start_file("image_size.npy", options)?;
    zip.write_all(&npy("(2,)".into()))?;
    for v in [1920f32, 1080.0] {
        zip.write_all(&v.to_le_bytes())?;
    }
    zip.start_file("pose_3d.npy", options)?;
    zip.write_all(&npy(format!("({t}, 17, 3)")))?;
    let zeros = vec![0u8; 1 << 20];
    for _ in 0..2048 {
        zip.write_all(&zeros)?;
    }
    zip.finish()?.flush()?;
    println!(
        "bomb: {} ({} bytes; pose_3d inflates to 2 GiB)",
        out.display(),
        std::fs::metadata(out)?.len()
    );
    Ok(())
}

#[tokio::main]
async fn main() -> Result<()> {
    let args = Args::parse();
    let start = Instant::now();
    match &args.case {
        Case::Streams {
            server,
            server_pid,
            streams: n,
            limit,
        } => streams(server, *server_pid, *n, *limit).await?,
        Case::Sessions {
            server,
            server_pid,
            header,
            attempts,
            limit,
        } => sessions(server, *server_pid, header, *attempts, *limit).await?,
        Case::Token {
            server,
            replica,
            token_ttl,
        } => token(server, replica, Duration::from_secs_f64(*token_ttl)).await?,
        Case::Bomb { out } => bomb(out)?,
        Case::Headers {
            server,
            server_pid,
            count,
        } => raw::headers(server, *server_pid, *count).await?,
        Case::Preface {
            server,
            server_pid,
            connections,
        } => raw::preface(server, *server_pid, *connections).await?,
        Case::Idle {
            server,
            server_pid,
            connections: n,
            addresses,
            idle,
        } => {
            let idle = Duration::from_secs_f64(*idle);
            connections::idle(server, *server_pid, *n, *addresses, idle).await?
        }
        Case::Flood { server, server_pid } => connections::flood(server, *server_pid).await?,
    }
    println!("  ok ({:.1} s)", start.elapsed().as_secs_f64());
    Ok(())
}

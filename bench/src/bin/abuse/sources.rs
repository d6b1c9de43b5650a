//! Abuse from many sources at once, each a loopback address of its own
//! (127.0.0.2 and up; the healthy client is 127.0.0.1):
//!
//! - `pending`: every address opens connections and sends HEADERS-only
//!   streams on them (no message ever follows), as many as the socket
//!   takes. `--max-streams-per-peer` holds each address, `--memory-budget`
//!   all of them: the server's memory stays bounded and a new client is
//!   served.
//! - `shares`: every address opens sessions as fast as it can and holds
//!   them, then floods frames on them without reading an answer (slow
//!   readers). The fair shares (`total / (k + 1)` with k clients holding
//!   some) leave room for a new client, the per-client frame queue keeps
//!   the slow readers' frames from filling the queue, and the batcher's
//!   turns between clients put its frames in the next batch.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{ensure, Result};
use blapose_proto::v1 as pb;
use pb::stream_request::Kind as Req;

use crate::client::{
    abuser, connect_from, frames, hold_sessions, socket_addr, Stream, Victim, MAX_RSS_GROWTH,
};
use crate::raw::{flood_headers, Tally};

/// `addresses` x `connections` x `streams` HEADERS-only streams
/// ([`flood_headers`]) beside the healthy client: its latency, the
/// server's peak memory growth within `bound` bytes, and with `per_peer`
/// (the server's `--max-streams-per-peer`) no address holding more.
pub(crate) async fn pending(
    url: &str,
    pid: u32,
    addresses: usize,
    connections: usize,
    streams: u32,
    per_peer: Option<u64>,
    bound: u64,
) -> Result<()> {
    println!(
        "case pending: {addresses} addresses x {connections} connections x {streams} HEADERS-only streams"
    );
    let to = socket_addr(url).await?;
    let victim = Victim::before(url, None, pid).await?;
    let stop = Arc::new(AtomicBool::new(false));
    let tallies: Vec<Arc<Tally>> = (0..addresses).map(|_| Arc::default()).collect();
    let started = Instant::now();
    let mut tasks = Vec::new();
    for (a, tally) in tallies.iter().enumerate() {
        for _ in 0..connections {
            tasks.push(tokio::spawn(flood_headers(
                to,
                abuser(a),
                streams,
                stop.clone(),
                tally.clone(),
            )));
        }
    }
    // Until every frame is written, or the writing stalls for a second
    // (the server closed or stopped reading connections).
    let target = (addresses * connections) as u64 * u64::from(streams);
    let sent = || tallies.iter().map(|t| Tally::get(&t.sent)).sum::<u64>();
    let (mut last, mut last_change) = (0, Instant::now());
    while sent() < target && last_change.elapsed() < Duration::from_secs(1) {
        tokio::time::sleep(Duration::from_millis(50)).await;
        if sent() != last {
            (last, last_change) = (sent(), Instant::now());
        }
    }
    println!(
        "  {} of {target} HEADERS written in {:.1} s",
        sent(),
        started.elapsed().as_secs_f64()
    );
    // The server's answers to the last of them.
    tokio::time::sleep(Duration::from_millis(500)).await;
    let latency = victim.during().await;
    let mut over = Vec::new();
    for (a, t) in tallies.iter().enumerate() {
        let (sent, refused, held) = (Tally::get(&t.sent), Tally::get(&t.refused), t.held());
        println!(
            "  {}: {} connections accepted ({} closed by the server), {sent} streams sent, {refused} refused at once, {} ended with their connection, {held} held",
            abuser(a),
            Tally::get(&t.connected),
            Tally::get(&t.closed),
            Tally::get(&t.released),
        );
        if per_peer.is_some_and(|limit| held > limit) {
            over.push(format!("{} holds {held}", abuser(a)));
        }
    }
    stop.store(true, Ordering::Relaxed);
    for t in tasks {
        let _ = t.await;
    }
    victim.check(latency, bound)?;
    ensure!(
        over.is_empty(),
        "not enforced: {} (--max-streams-per-peer {})",
        over.join(", "),
        per_peer.unwrap_or_default()
    );
    Ok(())
}

/// `addresses` clients, each holding as many sessions as it can and then
/// sending frames on them without reading, beside the healthy client (a
/// new client, which must open its session and keep its latency);
/// `total` is the server's `--max-sessions`: each address must be refused
/// at some point and all of them together leave room.
pub(crate) async fn shares(
    url: &str,
    pid: u32,
    addresses: usize,
    total: usize,
    p99_floor: Duration,
) -> Result<()> {
    println!(
        "case shares: {addresses} addresses each hold as many of {total} sessions as they can, then read slowly"
    );
    let victim = Victim::before(url, None, pid).await?.with_floor(p99_floor);
    let frames = Arc::new(frames()?.1);
    let stop = Arc::new(AtomicBool::new(false));
    let mut attackers = Vec::new();
    for a in 0..addresses {
        let url = url.to_owned();
        let (stop, frames) = (stop.clone(), frames.clone());
        attackers.push(tokio::spawn(async move {
            let mut client = connect_from(&url, abuser(a)).await?;
            // On until refused 20 times in a row: the share is reached
            // (it shrinks as the other addresses take theirs).
            let (held, refused) = hold_sessions(&mut client, None, usize::MAX, 20).await?;
            let count = held.len();
            let senders = held
                .into_iter()
                .map(|s| slow_reader(s, frames.clone(), stop.clone()));
            let senders: Vec<_> = senders.map(tokio::spawn).collect();
            anyhow::Ok((count, refused, senders))
        }));
    }
    let mut held = Vec::new();
    let mut senders = Vec::new();
    for (a, attacker) in attackers.into_iter().enumerate() {
        let (count, refused, s) = attacker.await??;
        println!(
            "  {}: holds {count} sessions, refused {refused} times",
            abuser(a)
        );
        held.push((count, refused));
        senders.extend(s);
    }
    // The slow readers' frames fill their queues meanwhile.
    tokio::time::sleep(Duration::from_millis(500)).await;
    let latency = victim.during().await;
    stop.store(true, Ordering::Relaxed);
    for s in &senders {
        s.abort();
    }
    let sum: usize = held.iter().map(|(c, _)| c).sum();
    println!(
        "  together {sum} of {total} sessions; a new client's fair share now {}",
        total / (addresses + 2)
    );
    victim.check(latency, MAX_RSS_GROWTH)?;
    ensure!(
        held.iter().all(|(_, refused)| *refused > 0),
        "not enforced: an address was never refused"
    );
    ensure!(
        sum < total,
        "not enforced: {addresses} addresses hold all {total} sessions"
    );
    Ok(())
}

/// Frames sent on `stream` as fast as its flow control takes them, its
/// answers never read, until `stop`.
async fn slow_reader(stream: Stream, frames: Arc<Vec<pb::Frame>>, stop: Arc<AtomicBool>) {
    let mut i = 0;
    while !stop.load(Ordering::Relaxed) {
        let frame = Req::Frame(frames[i % frames.len()].clone());
        let sent = tokio::time::timeout(
            Duration::from_millis(100),
            stream.tx.send(pb::StreamRequest { kind: Some(frame) }),
        )
        .await;
        match sent {
            Ok(Ok(())) => i += 1,
            Ok(Err(_)) => return,
            Err(_) => {}
        }
    }
    drop(stream);
}

//! Connection-level abuse, written as raw HTTP/2 frames (a well-behaved
//! client never does either): connections that send the preface and then
//! only answer keepalive PINGs (`idle`), and one connection flooding
//! WINDOW_UPDATE frames (`flood`). Each runs beside the healthy client.

use std::net::{IpAddr, SocketAddr};
use std::time::{Duration, Instant};

use anyhow::{ensure, Context, Result};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpSocket, TcpStream};

use crate::client::{socket_addr, Victim, MAX_RSS_GROWTH};

const PREFACE: &[u8; 24] = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n";
const SETTINGS: u8 = 0x4;
const PING: u8 = 0x6;
const GOAWAY: u8 = 0x7;
const WINDOW_UPDATE: u8 = 0x8;

fn frame(kind: u8, flags: u8, payload: &[u8]) -> Vec<u8> {
    let len = payload.len();
    let mut out = vec![
        (len >> 16) as u8,
        (len >> 8) as u8,
        len as u8,
        kind,
        flags,
        0,
        0,
        0,
        0,
    ];
    out.extend_from_slice(payload);
    out
}

/// Connect from `from` (any 127/8 address is loopback) and send the
/// preface and an empty SETTINGS frame.
async fn connect_from(from: IpAddr, to: SocketAddr) -> Result<TcpStream> {
    let socket = TcpSocket::new_v4()?;
    socket.bind(SocketAddr::new(from, 0))?;
    let mut s = socket.connect(to).await?;
    let mut hello = PREFACE.to_vec();
    hello.extend(frame(SETTINGS, 0, &[]));
    s.write_all(&hello).await?;
    Ok(s)
}

/// Keep `s` as keepalive does (SETTINGS acknowledged, PINGs answered and
/// sent) until the server sends GOAWAY or closes it; when that happened.
async fn ping_only(mut s: TcpStream, started: Instant, wait: Duration) -> Option<Duration> {
    let deadline = started + wait;
    let mut head = [0u8; 9];
    let mut next_ping = Instant::now();
    loop {
        // A keepalive PING every 2 s, as a client's keepalive would (more
        // often than any server's idle limit checks, far from a flood).
        if Instant::now() >= next_ping {
            let _ = s.write_all(&frame(PING, 0, &[1; 8])).await;
            next_ping = Instant::now() + Duration::from_secs(2);
        }
        let read = tokio::time::timeout(Duration::from_millis(500), s.read_exact(&mut head)).await;
        match read {
            Ok(Ok(_)) => {}
            Ok(Err(_)) => return Some(started.elapsed()),
            Err(_) => {
                if Instant::now() > deadline {
                    return None;
                }
                continue;
            }
        }
        let len = usize::from(head[0]) << 16 | usize::from(head[1]) << 8 | usize::from(head[2]);
        let mut payload = vec![0u8; len];
        if s.read_exact(&mut payload).await.is_err() {
            return Some(started.elapsed());
        }
        match (head[3], head[4] & 1) {
            (GOAWAY, _) => return Some(started.elapsed()),
            (SETTINGS, 0) => {
                let _ = s.write_all(&frame(SETTINGS, 1, &[])).await;
            }
            (PING, 0) => {
                let _ = s.write_all(&frame(PING, 1, &payload)).await;
            }
            _ => {}
        }
        if Instant::now() > deadline {
            return None;
        }
    }
}

/// `connections` PING-only connections from `addresses` loopback
/// addresses: all must get GOAWAY (or be closed) within `idle` + 10 s,
/// while the healthy client is served.
pub(crate) async fn idle(
    url: &str,
    pid: u32,
    connections: usize,
    addresses: usize,
    idle: Duration,
) -> Result<()> {
    println!("case idle: {connections} PING-only connections from {addresses} addresses (--max-connection-idle {idle:?})");
    let to = socket_addr(url).await?;
    let victim = Victim::before(url, None, pid).await?;
    let started = Instant::now();
    let mut tasks = Vec::new();
    for i in 0..connections {
        let from: IpAddr = format!("127.0.0.{}", 2 + i % addresses.max(1)).parse()?;
        let s = connect_from(from, to).await?;
        tasks.push(tokio::spawn(ping_only(
            s,
            started,
            idle + Duration::from_secs(10),
        )));
    }
    let latency = victim.during().await;
    let mut closed = Vec::new();
    for t in tasks {
        closed.push(t.await?);
    }
    let kept = closed.iter().filter(|c| c.is_none()).count();
    let last = closed.iter().flatten().max().copied().unwrap_or_default();
    println!(
        "  closed: {} of {connections}, the last after {:.1} s",
        connections - kept,
        last.as_secs_f64(),
    );
    victim.check(latency, MAX_RSS_GROWTH)?;
    ensure!(
        kept == 0,
        "not enforced: {kept} PING-only connections still open after {:?}",
        idle + Duration::from_secs(10)
    );
    Ok(())
}

/// One connection flooding WINDOW_UPDATE frames: GOAWAY (or closed)
/// within a second, while the healthy client is served.
pub(crate) async fn flood(url: &str, pid: u32) -> Result<()> {
    println!("case flood: one connection sends WINDOW_UPDATE frames as fast as it can");
    let to = socket_addr(url).await?;
    let victim = Victim::before(url, None, pid).await?;
    let s = connect_from("127.0.0.2".parse()?, to).await?;
    let (mut read, mut write) = s.into_split();
    let started = Instant::now();
    let writer = tokio::spawn(async move {
        let batch = frame(WINDOW_UPDATE, 0, &1u32.to_be_bytes()).repeat(1000);
        let mut sent = 0u64;
        while write.write_all(&batch).await.is_ok() {
            sent += 1000;
        }
        sent
    });
    let ended = tokio::time::timeout(Duration::from_secs(10), async {
        let mut head = [0u8; 9];
        loop {
            if read.read_exact(&mut head).await.is_err() {
                return started.elapsed();
            }
            let len = usize::from(head[0]) << 16 | usize::from(head[1]) << 8 | usize::from(head[2]);
            let mut payload = vec![0u8; len];
            if read.read_exact(&mut payload).await.is_err() || head[3] == GOAWAY {
                return started.elapsed();
            }
        }
    })
    .await;
    let sent = tokio::time::timeout(Duration::from_secs(5), writer).await;
    let latency = victim.during().await;
    let ended = ended.ok();
    println!(
        "  GOAWAY after {:?}; {} frames written before the close",
        ended,
        sent.ok().and_then(|s| s.ok()).unwrap_or(0)
    );
    victim.check(latency, MAX_RSS_GROWTH)?;
    let ended = ended.context("not enforced: the flooding connection was never closed")?;
    ensure!(
        ended <= Duration::from_secs(1),
        "not enforced: GOAWAY after {ended:?}, more than a second"
    );
    Ok(())
}

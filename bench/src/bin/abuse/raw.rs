//! The abuses no gRPC client commits, written on raw sockets: a flood of
//! HTTP/2 HEADERS frames on one connection that ignores the server's
//! SETTINGS_MAX_CONCURRENT_STREAMS, and TCP connections that never send
//! the HTTP/2 preface. A well-behaved client library (tonic's, the
//! `streams` case's) queues streams beyond the server's limit itself, so
//! only bytes written by hand show what the server does when the peer does
//! not. The cases `headers` and `preface` run them beside the healthy client.

use std::net::SocketAddr;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use anyhow::{Context, Result};

use crate::client::{check_growth, check_latency, healthy, rss, rss_growth, HEALTHY_FRAMES};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpSocket, TcpStream};

/// A running raw abuse.
pub(crate) enum Abuser {
    /// A task that ends when told to stop.
    Task(tokio::task::JoinHandle<()>),
    /// Connections held open.
    Held(Vec<TcpStream>),
}

impl Abuser {
    /// Wait for the task (told to stop by its flag) or drop the
    /// connections.
    pub(crate) async fn stop(self) {
        match self {
            Self::Task(task) => {
                let _ = task.await;
            }
            Self::Held(held) => drop(held),
        }
    }
}

/// The socket address of a server URL (`http://host:port`).
pub(crate) async fn socket_addr(url: &str) -> Result<SocketAddr> {
    let host_port = url
        .split_once("://")
        .map_or(url, |(_, rest)| rest)
        .trim_end_matches('/');
    tokio::net::lookup_host(host_port)
        .await
        .with_context(|| format!("resolving {host_port}"))?
        .next()
        .with_context(|| format!("{host_port} resolves to no address"))
}

/// A string literal of an HPACK header block, without Huffman coding.
fn hpack_str(out: &mut Vec<u8>, s: &[u8]) {
    assert!(s.len() < 127);
    out.push(s.len() as u8);
    out.extend_from_slice(s);
}

/// The HEADERS block of one call to the streaming method.
fn stream_call_headers() -> Vec<u8> {
    // :method POST, :scheme http (indexed), :path (literal)
    let mut block = vec![0x83, 0x86, 0x04];
    hpack_str(&mut block, b"/blapose.v1.PoseAdjustment/Stream");
    block.push(0x01); // :authority
    hpack_str(&mut block, b"localhost");
    block.push(0x0f); // content-type
    block.push(0x10);
    hpack_str(&mut block, b"application/grpc");
    block.push(0x00); // te: trailers
    hpack_str(&mut block, b"te");
    hpack_str(&mut block, b"trailers");
    block
}

/// One connection, `count` HEADERS frames for the stream method (streams
/// 1, 3, 5, ...), as fast as the socket takes them; `sent` counts them.
/// The connection is held open, its answers read and dropped so that the
/// server is never blocked on it, until `stop`.
pub(crate) async fn flood_headers(
    addr: SocketAddr,
    count: u32,
    stop: Arc<AtomicBool>,
    sent: Arc<AtomicU64>,
) {
    let Ok(mut s) = TcpStream::connect(addr).await else {
        return;
    };
    // The preface and an empty SETTINGS frame.
    let mut preface = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n".to_vec();
    preface.extend_from_slice(&[0, 0, 0, 4, 0, 0, 0, 0, 0]);
    let block = stream_call_headers();
    let _ = s.write_all(&preface).await;
    for batch in (0..count).collect::<Vec<_>>().chunks(256) {
        let mut buf = Vec::new();
        for i in batch {
            let len = block.len();
            // Length, type HEADERS, flag END_HEADERS, stream id.
            buf.extend_from_slice(&[(len >> 16) as u8, (len >> 8) as u8, len as u8, 1, 4]);
            buf.extend_from_slice(&(2 * i + 1).to_be_bytes());
            buf.extend_from_slice(&block);
        }
        if s.write_all(&buf).await.is_err() {
            break;
        }
        sent.fetch_add(batch.len() as u64, Ordering::Relaxed);
    }
    let mut sink = vec![0u8; 65536];
    while !stop.load(Ordering::Relaxed) {
        match tokio::time::timeout(Duration::from_millis(100), s.read(&mut sink)).await {
            Ok(Ok(0)) | Ok(Err(_)) => break,
            _ => {}
        }
    }
}

/// Up to `count` TCP connections to `addr` that never send a byte, from
/// 127.0.0.2-9 (loopback too, so a healthy client on 127.0.0.1 is not the
/// abuser's peer address); those that connected, held by the caller. A
/// refused connection ends the opening (reported, not an error: the
/// server's limits may refuse it).
pub(crate) async fn idle_connections(addr: SocketAddr, count: u32) -> Result<Vec<TcpStream>> {
    let mut held = Vec::new();
    for i in 0..count {
        let from = std::net::Ipv4Addr::new(127, 0, 0, 2 + (i % 8) as u8);
        let socket = TcpSocket::new_v4()?;
        socket.bind(SocketAddr::new(from.into(), 0))?;
        match socket.connect(addr).await {
            Ok(s) => held.push(s),
            Err(e) => {
                println!("  connect failed after {}: {e}", held.len());
                break;
            }
        }
    }
    Ok(held)
}

/// A raw abuse while the healthy client runs: its p99 against
/// its baseline and the server's memory growth, as every case checks them.
/// `abuse` starts the abuser once the baseline is measured; it is stopped
/// (its connections dropped) after.
async fn raw_case<F, Fut>(url: &str, pid: u32, what: &str, abuse: F) -> Result<()>
where
    F: FnOnce(std::net::SocketAddr, Arc<AtomicBool>) -> Fut,
    Fut: std::future::Future<Output = Result<Abuser>>,
{
    println!("case {what}");
    let addr = socket_addr(url).await?;
    let baseline = healthy(url, None, HEALTHY_FRAMES).await?;
    let rss_before = rss(pid)?;
    let stop = Arc::new(AtomicBool::new(false));
    let abuser = abuse(addr, stop.clone()).await?;
    tokio::time::sleep(Duration::from_millis(500)).await;
    let latency = check_latency(url, None, &baseline).await;
    let rss_after = rss(pid)?;
    stop.store(true, Ordering::Relaxed);
    abuser.stop().await;
    let growth = rss_growth(rss_before, rss_after);
    latency?;
    check_growth(growth)
}

/// `count` HEADERS frames on one raw connection ([`flood_headers`]).
pub(crate) async fn headers(url: &str, pid: u32, count: u32) -> Result<()> {
    let sent = Arc::new(AtomicU64::new(0));
    let what = format!("headers: {count} HEADERS frames on one raw connection");
    let counted = sent.clone();
    raw_case(url, pid, &what, |addr, stop| async move {
        let task = tokio::spawn(flood_headers(addr, count, stop, counted));
        Ok(Abuser::Task(task))
    })
    .await?;
    println!("  HEADERS frames written: {}", sent.load(Ordering::Relaxed));
    Ok(())
}

/// `n` connections without a preface ([`idle_connections`]).
pub(crate) async fn preface(url: &str, pid: u32, n: u32) -> Result<()> {
    let what = format!("preface: {n} connections that never send the HTTP/2 preface");
    raw_case(url, pid, &what, |addr, _| async move {
        let held = idle_connections(addr, n).await?;
        println!("  connections opened: {}", held.len());
        Ok(Abuser::Held(held))
    })
    .await
}

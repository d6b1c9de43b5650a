//! The abuses no gRPC client commits, written on raw sockets: a flood of
//! HTTP/2 HEADERS frames on one connection that ignores the server's
//! SETTINGS_MAX_CONCURRENT_STREAMS, and TCP connections that never send
//! the HTTP/2 preface. A well-behaved client library (tonic's, the
//! `streams` case's) queues streams beyond the server's limit itself, so
//! only bytes written by hand show what the server does when the peer does
//! not. The cases `headers` and `preface` run them beside the healthy client.

use std::net::{IpAddr, SocketAddr};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use anyhow::Result;

use crate::client::{abuser, socket_addr, Victim, MAX_RSS_GROWTH};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::tcp::OwnedReadHalf;
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

/// What HEADERS floods have done so far, over all their connections.
#[derive(Default)]
pub(crate) struct Tally {
    /// Connections that were accepted.
    pub(crate) connected: AtomicU64,
    /// HEADERS frames written.
    pub(crate) sent: AtomicU64,
    /// Streams the server ended at once: a trailers-only answer (HEADERS
    /// with END_STREAM: gRPC's refusal, RESOURCE_EXHAUSTED for a limit)
    /// or RST_STREAM.
    pub(crate) refused: AtomicU64,
    /// Connections the server sent GOAWAY on or closed.
    pub(crate) closed: AtomicU64,
    /// Streams not refused that ended with their connection.
    pub(crate) released: AtomicU64,
}

/// One connection's streams written, and whether the server closed it
/// (then its streams written and not refused are released, once).
#[derive(Default)]
struct Written {
    sent: u64,
    closed: bool,
}

impl Tally {
    pub(crate) fn get(counter: &AtomicU64) -> u64 {
        counter.load(Ordering::Relaxed)
    }

    /// Streams the server holds open now: written, neither refused nor
    /// ended with their connection.
    pub(crate) fn held(&self) -> u64 {
        let ended = Self::get(&self.refused) + Self::get(&self.released);
        Self::get(&self.sent).saturating_sub(ended)
    }
}

/// One connection from `from`, `count` HEADERS frames for the stream
/// method (streams 1, 3, 5, ...), as fast as the socket takes them. The
/// answers are read all along (so the server is never blocked writing
/// them) and the refusals among them counted in `tally`, until `stop` or
/// until the server closes the connection.
pub(crate) async fn flood_headers(
    addr: SocketAddr,
    from: IpAddr,
    count: u32,
    stop: Arc<AtomicBool>,
    tally: Arc<Tally>,
) {
    let Ok(socket) = TcpSocket::new_v4() else {
        return;
    };
    if socket.bind(SocketAddr::new(from, 0)).is_err() {
        return;
    }
    let Ok(s) = socket.connect(addr).await else {
        return;
    };
    tally.connected.fetch_add(1, Ordering::Relaxed);
    let (read, mut write) = s.into_split();
    let written = Arc::new(std::sync::Mutex::new(Written::default()));
    let reader = tokio::spawn(count_refusals(read, stop, tally.clone(), written.clone()));
    // The preface and an empty SETTINGS frame.
    let mut preface = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n".to_vec();
    preface.extend_from_slice(&[0, 0, 0, 4, 0, 0, 0, 0, 0]);
    let block = stream_call_headers();
    let _ = write.write_all(&preface).await;
    for batch in (0..count).collect::<Vec<_>>().chunks(256) {
        let mut buf = Vec::new();
        for i in batch {
            let len = block.len();
            // Length, type HEADERS, flag END_HEADERS, stream id.
            buf.extend_from_slice(&[(len >> 16) as u8, (len >> 8) as u8, len as u8, 1, 4]);
            buf.extend_from_slice(&(2 * i + 1).to_be_bytes());
            buf.extend_from_slice(&block);
        }
        if write.write_all(&buf).await.is_err() {
            break;
        }
        let n = batch.len() as u64;
        tally.sent.fetch_add(n, Ordering::Relaxed);
        let mut w = written.lock().unwrap_or_else(|p| p.into_inner());
        w.sent += n;
        if w.closed {
            tally.released.fetch_add(n, Ordering::Relaxed);
        }
    }
    let _ = reader.await;
}

/// Read the server's frames until `stop` or the connection's end,
/// counting refused streams and the end in `tally`.
async fn count_refusals(
    mut read: OwnedReadHalf,
    stop: Arc<AtomicBool>,
    tally: Arc<Tally>,
    written: Arc<std::sync::Mutex<Written>>,
) {
    const HEADERS: u8 = 0x1;
    const RST_STREAM: u8 = 0x3;
    const GOAWAY: u8 = 0x7;
    const END_STREAM: u8 = 0x1;
    let (mut buf, mut chunk) = (Vec::new(), vec![0u8; 1 << 16]);
    let mut ended = std::collections::HashSet::new();
    'read: while !stop.load(Ordering::Relaxed) {
        // `read` is cancel-safe (`read_exact` is not): frames are cut
        // from the buffer.
        match tokio::time::timeout(Duration::from_millis(100), read.read(&mut chunk)).await {
            Err(_) => continue,
            Ok(Ok(0)) | Ok(Err(_)) => break,
            Ok(Ok(n)) => buf.extend_from_slice(&chunk[..n]),
        }
        let mut at = 0;
        while buf.len() - at >= 9 {
            let h = &buf[at..at + 9];
            let len = usize::from(h[0]) << 16 | usize::from(h[1]) << 8 | usize::from(h[2]);
            if buf.len() - at < 9 + len {
                break;
            }
            let stream = u32::from_be_bytes([h[5], h[6], h[7], h[8]]) & 0x7fff_ffff;
            // A trailers-only answer (HEADERS with END_STREAM) is followed
            // by RST_STREAM (the request side is still open): one refusal,
            // counted once.
            let refusal = (h[3] == HEADERS && h[4] & END_STREAM != 0) || h[3] == RST_STREAM;
            if refusal && ended.insert(stream) {
                tally.refused.fetch_add(1, Ordering::Relaxed);
            }
            if h[3] == GOAWAY {
                break 'read;
            }
            at += 9 + len;
        }
        buf.drain(..at);
    }
    if !stop.load(Ordering::Relaxed) {
        tally.closed.fetch_add(1, Ordering::Relaxed);
        let mut w = written.lock().unwrap_or_else(|p| p.into_inner());
        w.closed = true;
        let released = w.sent.saturating_sub(ended.len() as u64);
        tally.released.fetch_add(released, Ordering::Relaxed);
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
    let victim = Victim::before(url, None, pid).await?;
    let stop = Arc::new(AtomicBool::new(false));
    let abuser = abuse(addr, stop.clone()).await?;
    tokio::time::sleep(Duration::from_millis(500)).await;
    let latency = victim.during().await;
    stop.store(true, Ordering::Relaxed);
    abuser.stop().await;
    victim.check(latency, MAX_RSS_GROWTH)
}

/// `count` HEADERS frames on one raw connection ([`flood_headers`]).
pub(crate) async fn headers(url: &str, pid: u32, count: u32) -> Result<()> {
    let tally = Arc::new(Tally::default());
    let what = format!("headers: {count} HEADERS frames on one raw connection");
    let counted = tally.clone();
    raw_case(url, pid, &what, |addr, stop| async move {
        let task = tokio::spawn(flood_headers(addr, abuser(0), count, stop, counted));
        Ok(Abuser::Task(task))
    })
    .await?;
    println!(
        "  HEADERS frames written: {}, streams refused at once: {}",
        Tally::get(&tally.sent),
        Tally::get(&tally.refused)
    );
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

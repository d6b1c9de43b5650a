//! Manual abuse check of the transport limits against a running server:
//! a healthy client's frame round trips (p50/p99/max) alone and while an
//! abuser either opens as many streams as it can on one HTTP/2 connection
//! (ignoring SETTINGS_MAX_CONCURRENT_STREAMS) or holds thousands of TCP
//! connections that never send the preface (from 127.0.0.2-9); with `--pid`, the server's
//! resident memory before, at its peak, and after.
//!
//! ```sh
//! blapose-server --addr 127.0.0.1:50099 --no-metrics &
//! cargo run --release -p blapose-server --example abuse -- 127.0.0.1:50099 streams 120000 $!
//! cargo run --release -p blapose-server --example abuse -- 127.0.0.1:50099 idle 2000 $!
//! ```

use std::net::SocketAddr;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use blapose_proto::v1 as pb;
use pb::stream_request::Kind as Req;
use tokio::io::AsyncWriteExt;
use tokio_stream::wrappers::ReceiverStream;

fn rss_mb(pid: Option<u32>) -> f64 {
    let Some(pid) = pid else { return f64::NAN };
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap_or_default();
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<f64>().ok())
        .map_or(f64::NAN, |kb| kb / 1024.0)
}

/// Frame round trips of one session, `n` frames one at a time: sorted ms.
async fn healthy(addr: SocketAddr, n: usize) -> anyhow::Result<Vec<f64>> {
    let mut client =
        pb::pose_adjustment_client::PoseAdjustmentClient::connect(format!("http://{addr}")).await?;
    let (tx, rx) = tokio::sync::mpsc::channel(4);
    let mut responses = client.stream(ReceiverStream::new(rx)).await?.into_inner();
    tx.send(pb::StreamRequest {
        kind: Some(Req::Open(pb::OpenSession {
            input_format: Some(pb::InputFormat {
                layout: 1,
                coordinates: Some(pb::input_format::Coordinates::Normalized(true)),
            }),
            ..Default::default()
        })),
    })
    .await?;
    responses.message().await?;
    let pose: Vec<f32> = (0..51).map(|i| (i as f32 * 0.37).sin()).collect();
    let mut ms = Vec::with_capacity(n);
    for i in 0..n {
        let t = Instant::now();
        tx.send(pb::StreamRequest {
            kind: Some(Req::Frame(pb::Frame {
                frame_index: i as u64,
                keypoints_2d: vec![0.1; 34],
                confidence: vec![],
                pose_3d: pose.clone(),
            })),
        })
        .await?;
        responses.message().await?;
        ms.push(t.elapsed().as_secs_f64() * 1e3);
    }
    ms.sort_by(f64::total_cmp);
    Ok(ms)
}

fn summary(ms: &[f64]) -> String {
    let q = |p: f64| ms[((ms.len() as f64 - 1.0) * p) as usize];
    format!(
        "p50 {:.2} ms, p99 {:.2} ms, max {:.2} ms",
        q(0.5),
        q(0.99),
        ms[ms.len() - 1]
    )
}

fn hpack_str(out: &mut Vec<u8>, s: &[u8]) {
    assert!(s.len() < 127);
    out.push(s.len() as u8);
    out.extend_from_slice(s);
}

/// One connection, `count` HEADERS frames for the stream method, as fast
/// as the socket takes them; held open until `stop`.
async fn open_streams(addr: SocketAddr, count: u32, stop: Arc<AtomicBool>, sent: Arc<AtomicU64>) {
    let Ok(mut s) = tokio::net::TcpStream::connect(addr).await else {
        return;
    };
    let mut out = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n".to_vec();
    out.extend_from_slice(&[0, 0, 0, 4, 0, 0, 0, 0, 0]);
    let mut block = vec![0x83, 0x86, 0x04];
    hpack_str(&mut block, b"/blapose.v1.PoseAdjustment/Stream");
    block.push(0x01);
    hpack_str(&mut block, b"localhost");
    block.push(0x0f);
    block.push(0x10);
    hpack_str(&mut block, b"application/grpc");
    block.push(0x00);
    hpack_str(&mut block, b"te");
    hpack_str(&mut block, b"trailers");
    let _ = s.write_all(&out).await;
    for batch in (0..count).collect::<Vec<_>>().chunks(256) {
        let mut buf = Vec::new();
        for i in batch {
            let len = block.len();
            buf.extend_from_slice(&[(len >> 16) as u8, (len >> 8) as u8, len as u8, 1, 4]);
            buf.extend_from_slice(&(2 * i + 1).to_be_bytes());
            buf.extend_from_slice(&block);
        }
        if s.write_all(&buf).await.is_err() {
            break;
        }
        sent.fetch_add(batch.len() as u64, Ordering::Relaxed);
    }
    // Keep reading (discarding) so the server is never blocked on us.
    let mut sink = vec![0u8; 65536];
    while !stop.load(Ordering::Relaxed) {
        use tokio::io::AsyncReadExt;
        match tokio::time::timeout(Duration::from_millis(100), s.read(&mut sink)).await {
            Ok(Ok(0)) | Ok(Err(_)) => break,
            _ => {}
        }
    }
}

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let addr: SocketAddr = args
        .get(1)
        .map_or("127.0.0.1:50051", |s| s.as_str())
        .parse()?;
    let mode = args.get(2).map_or("streams", |s| s.as_str()).to_string();
    let count: u32 = args.get(3).map_or(Ok(120_000), |s| s.parse())?;
    let pid: Option<u32> = args.get(4).map(|s| s.parse()).transpose()?;
    let frames = 400;

    healthy(addr, 50).await?; // warm-up
    let base = healthy(addr, frames).await?;
    let rss0 = rss_mb(pid);
    println!("baseline: {} (RSS {rss0:.0} MB)", summary(&base));

    let stop = Arc::new(AtomicBool::new(false));
    let sent = Arc::new(AtomicU64::new(0));
    let mut held = Vec::new();
    let abuser = match mode.as_str() {
        "streams" => Some(tokio::spawn(open_streams(
            addr,
            count,
            stop.clone(),
            sent.clone(),
        ))),
        "idle" => {
            // From 127.0.0.2-9 (loopback too), so that the healthy client on
            // 127.0.0.1 is not the abuser's peer address.
            for i in 0..count {
                let from = std::net::Ipv4Addr::new(127, 0, 0, 2 + (i % 8) as u8);
                let socket = tokio::net::TcpSocket::new_v4()?;
                socket.bind(SocketAddr::new(from.into(), 0))?;
                match socket.connect(addr).await {
                    Ok(s) => held.push(s),
                    Err(e) => {
                        println!("connect failed after {}: {e}", held.len());
                        break;
                    }
                }
            }
            None
        }
        other => anyhow::bail!("mode {other:?}: streams or idle"),
    };
    let peak = Arc::new(std::sync::Mutex::new(rss0));
    let sampler = {
        let (peak, stop) = (peak.clone(), stop.clone());
        tokio::spawn(async move {
            while !stop.load(Ordering::Relaxed) {
                let r = rss_mb(pid);
                {
                    let mut p = peak.lock().unwrap();
                    if r > *p {
                        *p = r;
                    }
                }
                tokio::time::sleep(Duration::from_millis(50)).await;
            }
        })
    };
    tokio::time::sleep(Duration::from_millis(500)).await;
    let during = healthy(addr, frames).await?;
    println!(
        "during {mode} x{count} (streams sent {}, connections opened {}): {}",
        sent.load(Ordering::Relaxed),
        held.len(),
        summary(&during)
    );
    tokio::time::sleep(Duration::from_secs(2)).await;
    let during2 = healthy(addr, frames).await?;
    println!("during, 2.5 s in: {}", summary(&during2));
    stop.store(true, Ordering::Relaxed);
    drop(held);
    if let Some(a) = abuser {
        let _ = a.await;
    }
    let _ = sampler.await;
    tokio::time::sleep(Duration::from_secs(1)).await;
    println!(
        "RSS: before {rss0:.0} MB, peak {:.0} MB, after {:.0} MB",
        *peak.lock().unwrap(),
        rss_mb(pid)
    );
    Ok(())
}

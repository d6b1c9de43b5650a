//! Connections that hold the server without using it: one that sent its
//! preface and then only answers (and sends) keepalive PINGs is sent
//! GOAWAY and closed after `--max-connection-idle`, while one with an open
//! stream is kept; one past `--max-connection-age` is sent GOAWAY; one
//! flooding WINDOW_UPDATE frames is sent GOAWAY and closed within a second
//! (`--max-control-frames-per-second`). A healthy client is answered
//! throughout. Limits set low, a few seconds in all.

use crate::support;

use std::net::SocketAddr;
use std::time::{Duration, Instant};

use blapose_proto::v1 as pb;
use blapose_server::protect::Protection;
use blapose_server::{ServerConfig, ServerHandle};
use blapose_test_support::{h2raw, spawn_constant};
use pb::pose_adjustment_client::PoseAdjustmentClient;
use pb::stream_response::Kind as Resp;
use tokio::io::AsyncWriteExt;
use tokio::net::TcpStream;
use tokio_stream::StreamExt;

const PING: u8 = 0x6;
const WINDOW_UPDATE: u8 = 0x8;

async fn start(protection: Protection) -> ServerHandle {
    spawn_constant(ServerConfig {
        protection,
        ..ServerConfig::default()
    })
    .await
}

/// A well-behaved client on a fresh connection gets ModelInfo answered.
async fn healthy(addr: SocketAddr) {
    let mut client = PoseAdjustmentClient::connect(format!("http://{addr}"))
        .await
        .unwrap();
    client.model_info(pb::ModelInfoRequest {}).await.unwrap();
}

/// Hold `s` open doing only what keepalive does: acknowledge SETTINGS,
/// answer the server's PINGs and send one every 200 ms. Returns the GOAWAY
/// and when it came, or `None` if the connection stayed up for `wait`.
async fn ping_only(s: &mut TcpStream, wait: Duration) -> Option<(h2raw::Frame, Instant)> {
    let deadline = Instant::now() + wait;
    let mut next_ping = Instant::now();
    loop {
        let now = Instant::now();
        if now >= deadline {
            return None;
        }
        if now >= next_ping {
            let _ = s.write_all(&h2raw::frame(PING, 0, 0, &[7; 8])).await;
            next_ping = now + Duration::from_millis(200);
        }
        let Some(f) = h2raw::read_frame(s, Duration::from_millis(100)).await else {
            continue;
        };
        match f.kind {
            h2raw::GOAWAY => return Some((f, Instant::now())),
            h2raw::SETTINGS if f.flags & 1 == 0 => {
                let _ = s.write_all(&h2raw::frame(h2raw::SETTINGS, 1, 0, &[])).await;
            }
            PING if f.flags & 1 == 0 => {
                let _ = s.write_all(&h2raw::frame(PING, 1, 0, &f.payload)).await;
            }
            _ => {}
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_idle_connection_is_closed_and_one_with_a_stream_is_kept() {
    let idle = Duration::from_millis(800);
    let server = start(Protection {
        max_connection_idle: Some(idle),
        max_connection_age_grace: Duration::from_millis(500),
        ..Protection::default()
    })
    .await;
    let addr = server.local_addr();
    // A client with a session open on its stream, and nothing sent after.
    let mut client = PoseAdjustmentClient::connect(format!("http://{addr}"))
        .await
        .unwrap();
    let (tx, rx) = tokio::sync::mpsc::channel(8);
    tx.send(support::open()).await.unwrap();
    let mut answers = client
        .stream(tokio_stream::wrappers::ReceiverStream::new(rx))
        .await
        .unwrap()
        .into_inner();
    assert!(matches!(
        answers.next().await.unwrap().unwrap().kind,
        Some(Resp::Opened(_))
    ));
    // The PING-only connection: GOAWAY after the idle limit, then closed.
    let started = Instant::now();
    let mut pinger = h2raw::connect(addr).await;
    let (goaway, at) = ping_only(&mut pinger, idle + Duration::from_secs(10))
        .await
        .expect("GOAWAY within the idle limit + 10 s");
    let after = at - started;
    eprintln!("PING-only connection: GOAWAY after {after:?} (limit {idle:?})");
    assert_eq!(goaway.error_code(), Some(0), "NO_ERROR: {goaway:?}");
    assert!(after >= idle, "not before the limit: {after:?}");
    assert!(after < idle + Duration::from_secs(3), "{after:?}");
    assert!(
        h2raw::wait_for(&mut pinger, Duration::from_secs(3), |_| false)
            .await
            .is_none(),
        "closed after the GOAWAY"
    );
    // The stream's connection, idle far longer than the limit, still works.
    tx.send(support::frame(0)).await.unwrap();
    let answer = tokio::time::timeout(Duration::from_secs(3), answers.next())
        .await
        .expect("answered")
        .unwrap()
        .unwrap();
    assert!(matches!(answer.kind, Some(Resp::Frame(_))), "{answer:?}");
    healthy(addr).await;
    drop(tx);
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_aged_connection_is_sent_goaway() {
    let server = start(Protection {
        max_connection_idle: None,
        max_connection_age: Some(Duration::from_millis(500)),
        max_connection_age_grace: Duration::from_millis(300),
        ..Protection::default()
    })
    .await;
    let mut s = h2raw::connect(server.local_addr()).await;
    let started = Instant::now();
    let (goaway, at) = ping_only(&mut s, Duration::from_secs(5))
        .await
        .expect("GOAWAY at the age limit");
    assert_eq!(goaway.error_code(), Some(0));
    assert!(at - started < Duration::from_secs(2), "{:?}", at - started);
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_window_update_flood_ends_in_goaway_within_a_second() {
    let server = start(Protection {
        max_control_frames_per_second: 1000,
        ..Protection::default()
    })
    .await;
    let addr = server.local_addr();
    let s = h2raw::connect(addr).await;
    let (mut read, mut write) = s.into_split();
    let started = Instant::now();
    let flood = tokio::spawn(async move {
        let one = h2raw::frame(WINDOW_UPDATE, 0, 0, &1u32.to_be_bytes());
        let batch: Vec<u8> = one.repeat(500);
        let mut sent = 0u64;
        while write.write_all(&batch).await.is_ok() {
            sent += 500;
            if sent > 50_000_000 {
                break;
            }
        }
        sent
    });
    let goaway = tokio::time::timeout(Duration::from_secs(3), async {
        let mut head = [0u8; 9];
        loop {
            use tokio::io::AsyncReadExt;
            read.read_exact(&mut head).await.ok()?;
            let len = usize::from(head[0]) << 16 | usize::from(head[1]) << 8 | usize::from(head[2]);
            let mut payload = vec![0u8; len];
            read.read_exact(&mut payload).await.ok()?;
            if head[3] == h2raw::GOAWAY {
                return Some((payload, Instant::now()));
            }
        }
    })
    .await
    .expect("an answer within 3 s");
    let (payload, at) = goaway.expect("a GOAWAY before the connection closed");
    let after = at - started;
    let sent = tokio::time::timeout(Duration::from_secs(3), flood)
        .await
        .expect("the connection is closed: the flood's writes fail")
        .unwrap();
    eprintln!(
        "WINDOW_UPDATE flood: GOAWAY after {after:?}; {sent} frames written before the close"
    );
    assert!(after < Duration::from_secs(1), "{after:?}");
    assert_eq!(&payload[4..8], &[0, 0, 0, 0], "NO_ERROR");
    healthy(addr).await;
    server.shutdown().await.unwrap();
}

//! Transport limits, each against a client that breaks it: streams beyond
//! `--max-concurrent-streams` on one connection, a header list beyond
//! `--max-header-list-bytes`, connections beyond `--max-connections` and
//! `--max-connections-per-peer`, and connections that never finish their
//! preface within `--handshake-timeout`. Loopback only, limits set low, a
//! few seconds in all; while each abuse runs, a well-behaved client on its
//! own connection must still be answered.

use blapose_test_support::h2raw;

use std::net::{IpAddr, SocketAddr};
use std::time::{Duration, Instant};

use blapose_proto::v1 as pb;
use blapose_server::transport::ConnectionLimits;
use blapose_server::{ServerConfig, ServerHandle};
use blapose_test_support::spawn_constant;
use h2raw::Frame;
use pb::pose_adjustment_client::PoseAdjustmentClient;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpSocket, TcpStream};

const WAIT: Duration = Duration::from_secs(3);

async fn start(config: ServerConfig) -> ServerHandle {
    spawn_constant(config).await
}

/// A well-behaved client on a fresh connection gets ModelInfo answered.
async fn healthy(addr: SocketAddr) {
    let call = async {
        let mut client = PoseAdjustmentClient::connect(format!("http://{addr}")).await?;
        client.model_info(pb::ModelInfoRequest {}).await?;
        Ok::<_, Box<dyn std::error::Error>>(())
    };
    match tokio::time::timeout(WAIT, call).await {
        Ok(Ok(())) => {}
        Ok(Err(e)) => panic!("a healthy client was refused: {e}"),
        Err(_) => panic!("a healthy client was not answered within {WAIT:?}"),
    }
}

/// The server's first SETTINGS frame on a raw connection (`None`: the
/// connection was closed instead).
async fn server_settings(s: &mut TcpStream) -> Option<Frame> {
    h2raw::wait_for(s, WAIT, |f| f.kind == h2raw::SETTINGS && f.flags & 1 == 0).await
}

/// Read the server's SETTINGS on `s` and check it advertises `value` for
/// `parameter`.
async fn assert_advertised(s: &mut TcpStream, parameter: u16, value: u32) {
    let settings = server_settings(s)
        .await
        .expect("server SETTINGS")
        .settings();
    assert!(
        settings.contains(&(parameter, value)),
        "advertised: {settings:?}"
    );
}

/// Connect from `from` (any 127/8 address is loopback on Linux) and send
/// the preface.
async fn connect_from(from: IpAddr, addr: SocketAddr) -> TcpStream {
    let socket = TcpSocket::new_v4().unwrap();
    socket.bind(SocketAddr::new(from, 0)).unwrap();
    let mut s = socket.connect(addr).await.unwrap();
    let mut hello = h2raw::PREFACE.to_vec();
    hello.extend(h2raw::frame(h2raw::SETTINGS, 0, 0, &[]));
    // A refused connection may already be closed: ignore a failed write.
    let _ = s.write_all(&hello).await;
    s
}

/// Whether the server closed `s` within `wait` (EOF or reset) rather than
/// keeping it open.
async fn closed_within(s: &mut TcpStream, wait: Duration) -> bool {
    let mut buf = [0u8; 256];
    let deadline = Instant::now() + wait;
    loop {
        let left = deadline.saturating_duration_since(Instant::now());
        match tokio::time::timeout(left, s.read(&mut buf)).await {
            Err(_) => return false,
            Ok(Ok(0) | Err(_)) => return true,
            Ok(Ok(_)) => continue,
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn streams_beyond_max_concurrent_streams_are_refused() {
    let server = start(ServerConfig {
        max_concurrent_streams: 8,
        ..ServerConfig::default()
    })
    .await;
    let mut s = h2raw::connect(server.local_addr()).await;
    assert_advertised(&mut s, h2raw::SETTINGS_MAX_CONCURRENT_STREAMS, 8).await;
    // Twelve streams at once, ignoring the advertised limit.
    let block = h2raw::grpc_headers(h2raw::STREAM_PATH, &[]);
    let mut burst = Vec::new();
    for i in 0..12u32 {
        burst.extend(h2raw::frame(
            h2raw::HEADERS,
            h2raw::END_HEADERS,
            2 * i + 1,
            &block,
        ));
    }
    s.write_all(&burst).await.unwrap();
    let mut refused = Vec::new();
    while refused.len() < 4 {
        let Some(f) = h2raw::wait_for(&mut s, WAIT, |f| f.kind == h2raw::RST_STREAM).await else {
            break;
        };
        assert_eq!(f.error_code(), Some(h2raw::REFUSED_STREAM), "{f:?}");
        refused.push(f.stream);
    }
    refused.sort_unstable();
    assert_eq!(refused, [17, 19, 21, 23], "the four streams beyond 8");
    healthy(server.local_addr()).await;
    drop(s);
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn header_lists_beyond_the_limit_are_refused() {
    let server = start(ServerConfig {
        max_header_list_bytes: 4096,
        ..ServerConfig::default()
    })
    .await;
    let mut s = h2raw::connect(server.local_addr()).await;
    assert_advertised(&mut s, h2raw::SETTINGS_MAX_HEADER_LIST_SIZE, 4096).await;
    let big = vec![b'x'; 10_000];
    let oversized = h2raw::grpc_headers(h2raw::STREAM_PATH, &[("x-big", &big)]);
    let normal = h2raw::grpc_headers(h2raw::STREAM_PATH, &[]);
    let mut both = h2raw::frame(h2raw::HEADERS, h2raw::END_HEADERS, 1, &oversized);
    both.extend(h2raw::frame(h2raw::HEADERS, h2raw::END_HEADERS, 3, &normal));
    s.write_all(&both).await.unwrap();
    let mut answers = std::collections::HashMap::new();
    while answers.len() < 2 {
        let Some(f) = h2raw::wait_for(&mut s, WAIT, |f| {
            matches!(f.kind, h2raw::HEADERS | h2raw::RST_STREAM)
        })
        .await
        else {
            break;
        };
        answers.entry(f.stream).or_insert(f);
    }
    // Stream 1: 431 Request Header Fields Too Large (":status" with a
    // Huffman-coded literal; 200 would be the static entry 0x88), and
    // nothing more.
    let refused = answers.get(&1).expect("an answer to the oversized request");
    assert_eq!(refused.kind, h2raw::HEADERS, "{refused:?}");
    assert!(refused.flags & h2raw::END_STREAM != 0);
    assert_eq!(refused.payload, [0x48, 0x83, 0x69, 0x90, 0xff], "431");
    // Stream 3: served (response headers, the stream open).
    let served = answers.get(&3).expect("an answer to the normal request");
    assert_eq!(served.kind, h2raw::HEADERS);
    assert_eq!(served.flags & h2raw::END_STREAM, 0, "{served:?}");
    healthy(server.local_addr()).await;
    drop(s);
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn connections_beyond_the_limits_are_closed_at_once() {
    let server = start(ServerConfig {
        connection_limits: ConnectionLimits {
            max_connections: 4,
            max_connections_per_peer: 2,
            handshake_timeout: Duration::from_secs(10),
        },
        ..ServerConfig::default()
    })
    .await;
    let addr = server.local_addr();
    let (a, b, c): (IpAddr, IpAddr, IpAddr) = (
        "127.0.0.1".parse().unwrap(),
        "127.0.0.2".parse().unwrap(),
        "127.0.0.3".parse().unwrap(),
    );
    let mut held = Vec::new();
    for from in [a, a] {
        let mut s = connect_from(from, addr).await;
        assert!(server_settings(&mut s).await.is_some(), "admitted");
        held.push(s);
    }
    // A third from the same address: per-peer limit.
    let mut third = connect_from(a, addr).await;
    let started = Instant::now();
    assert!(closed_within(&mut third, WAIT).await, "per-peer limit");
    assert!(started.elapsed() < Duration::from_secs(1), "closed at once");
    for from in [b, b] {
        let mut s = connect_from(from, addr).await;
        assert!(server_settings(&mut s).await.is_some(), "admitted");
        held.push(s);
    }
    // A fifth from a new address: the total limit.
    let mut fifth = connect_from(c, addr).await;
    assert!(closed_within(&mut fifth, WAIT).await, "total limit");
    // Closing one makes room again.
    drop(held.remove(0));
    let deadline = Instant::now() + WAIT;
    loop {
        let mut s = connect_from(c, addr).await;
        if server_settings(&mut s).await.is_some() {
            break;
        }
        assert!(Instant::now() < deadline, "a freed slot is reused");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    drop(held);
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn connections_without_a_preface_are_closed_after_the_handshake_timeout() {
    let server = start(ServerConfig {
        connection_limits: ConnectionLimits {
            handshake_timeout: Duration::from_millis(300),
            ..ServerConfig::default().connection_limits
        },
        ..ServerConfig::default()
    })
    .await;
    let addr = server.local_addr();
    let started = Instant::now();
    let mut silent = Vec::new();
    for _ in 0..200 {
        silent.push(TcpStream::connect(addr).await.unwrap());
    }
    // Part of the preface, then nothing.
    let mut partial = TcpStream::connect(addr).await.unwrap();
    partial.write_all(&h2raw::PREFACE[..10]).await.unwrap();
    // A well-behaved client is served meanwhile, and kept past the deadline.
    let mut good = h2raw::connect(addr).await;
    assert!(server_settings(&mut good).await.is_some());
    healthy(addr).await;
    for s in silent.iter_mut().chain([&mut partial]) {
        assert!(
            closed_within(s, WAIT).await,
            "a silent connection is closed"
        );
    }
    assert!(
        started.elapsed() >= Duration::from_millis(250),
        "not before the deadline"
    );
    assert!(
        !closed_within(&mut good, Duration::from_millis(700)).await,
        "a connection that sent its preface stays open"
    );
    // Not HTTP/2 at all: closed as soon as the preface is wrong.
    let mut http1 = TcpStream::connect(addr).await.unwrap();
    http1
        .write_all(b"GET / HTTP/1.1\r\nHost: x\r\n\r\n")
        .await
        .unwrap();
    assert!(closed_within(&mut http1, WAIT).await);
    drop(good);
    server.shutdown().await.unwrap();
}

//! What the Prometheus exporter says about transport-level events: errors
//! that tonic answers before a handler runs (an undecodable AdjustSequence
//! request), client cancels (CANCELLED, not FAILED_PRECONDITION),
//! connections refused by a limit or closed before HTTP/2, streams h2
//! refuses by itself, and the limits in force. Its own test binary: the recorder is process-global.

use blapose_test_support::h2raw;

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use blapose_proto::v1 as pb;
use blapose_server::transport::ConnectionLimits;
use blapose_server::ServerConfig;
use blapose_test_support::ConstantModel;
use pb::stream_request::Kind as Req;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio_stream::wrappers::ReceiverStream;

const WAIT: Duration = Duration::from_secs(3);

async fn scrape(addr: SocketAddr) -> String {
    let mut s = tokio::net::TcpStream::connect(addr).await.unwrap();
    s.write_all(b"GET /metrics HTTP/1.0\r\nHost: localhost\r\n\r\n")
        .await
        .unwrap();
    let mut body = String::new();
    s.read_to_string(&mut body).await.unwrap();
    body
}

/// Scrape until every needle is there (the server records some events just
/// after the client sees their effect); bounded by a count.
async fn scrape_until(addr: SocketAddr, needles: &[&str]) -> String {
    let mut body = scrape(addr).await;
    for _ in 0..300 {
        if needles.iter().all(|n| body.contains(n)) {
            break;
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
        body = scrape(addr).await;
    }
    for needle in needles {
        assert!(body.contains(needle), "missing {needle:?} in:\n{body}");
    }
    body
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn transport_events_are_counted() {
    let metrics_addr: SocketAddr = {
        let probe = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        probe.local_addr().unwrap()
    };
    let config = ServerConfig {
        metrics_addr: Some(metrics_addr),
        connection_limits: ConnectionLimits {
            max_connections: 64,
            max_connections_per_peer: 3,
            handshake_timeout: Duration::from_millis(200),
        },
        ..ServerConfig::default()
    };
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let server = blapose_server::spawn_with_provider(config, listener, Arc::new(ConstantModel))
        .await
        .unwrap();
    let addr = server.local_addr();

    // An AdjustSequence request that is not the method's protobuf (field
    // 1, a message, sent as a varint): tonic answers INTERNAL before the
    // handler runs.
    let mut s = h2raw::connect(addr).await;
    let headers = h2raw::grpc_headers(h2raw::ADJUST_SEQUENCE_PATH, &[]);
    let mut call = h2raw::frame(h2raw::HEADERS, h2raw::END_HEADERS, 1, &headers);
    call.extend(h2raw::frame(
        h2raw::DATA,
        h2raw::END_STREAM,
        1,
        &h2raw::grpc_message(&[0x08, 0x01]),
    ));
    s.write_all(&call).await.unwrap();
    let answer = h2raw::wait_for(&mut s, WAIT, |f| f.kind == h2raw::HEADERS && f.stream == 1).await;
    assert!(answer.is_some(), "AdjustSequence was answered");

    // A stream cancelled by its client before it opened (RST_STREAM
    // CANCEL), and one cancelled after its session opened (a tonic client
    // dropping the call).
    let headers = h2raw::grpc_headers(h2raw::STREAM_PATH, &[]);
    let mut cancel = h2raw::frame(h2raw::HEADERS, h2raw::END_HEADERS, 3, &headers);
    cancel.extend(h2raw::frame(h2raw::RST_STREAM, 0, 3, &8u32.to_be_bytes()));
    s.write_all(&cancel).await.unwrap();

    // Streams past --max-concurrent-streams (100) on that connection: h2
    // refuses the 101st itself (RST_STREAM REFUSED_STREAM), no handler
    // sees it, and it is counted.
    let mut flood = Vec::new();
    for i in 0..101u32 {
        flood.extend(h2raw::frame(
            h2raw::HEADERS,
            h2raw::END_HEADERS,
            5 + 2 * i,
            &headers,
        ));
    }
    s.write_all(&flood).await.unwrap();
    let refused = h2raw::wait_for(&mut s, WAIT, |f| {
        f.kind == h2raw::RST_STREAM && f.error_code() == Some(7)
    })
    .await;
    assert!(refused.is_some(), "the 101st stream was refused");
    let mut client =
        pb::pose_adjustment_client::PoseAdjustmentClient::connect(format!("http://{addr}"))
            .await
            .unwrap();
    let (tx, rx) = tokio::sync::mpsc::channel(4);
    let mut responses = client
        .stream(ReceiverStream::new(rx))
        .await
        .unwrap()
        .into_inner();
    tx.send(pb::StreamRequest {
        kind: Some(Req::Open(pb::OpenSession {
            input_format: Some(pb::InputFormat {
                layout: 1,
                coordinates: Some(pb::input_format::Coordinates::Normalized(true)),
            }),
            ..Default::default()
        })),
    })
    .await
    .unwrap();
    responses.message().await.unwrap().expect("SessionOpened");
    drop(responses);
    drop(tx);

    // Connections: three held from 127.0.0.1 (the raw one, the client's,
    // one more), the fourth refused; a silent one closed at the deadline
    // would need a free slot, so free one first.
    let _third = h2raw::connect(addr).await;
    let mut fourth = tokio::net::TcpStream::connect(addr).await.unwrap();
    let mut buf = [0u8; 8];
    let _ = tokio::time::timeout(WAIT, fourth.read(&mut buf)).await;
    drop(s);
    scrape_until(
        metrics_addr,
        &["blapose_connections_refused_total{limit=\"max_connections_per_peer\"} 1"],
    )
    .await;
    let mut silent = None;
    for _ in 0..100 {
        let mut c = tokio::net::TcpStream::connect(addr).await.unwrap();
        match tokio::time::timeout(Duration::from_millis(100), c.read(&mut buf)).await {
            // Still open after 100 ms: admitted, waiting for its preface.
            Err(_) => {
                silent = Some(c);
                break;
            }
            Ok(_) => tokio::time::sleep(Duration::from_millis(20)).await,
        }
    }
    let mut silent = silent.expect("a slot freed");
    let _ = tokio::time::timeout(WAIT, silent.read(&mut buf)).await;

    let body = scrape_until(
        metrics_addr,
        &[
            "blapose_errors_total{code=\"INTERNAL\",rpc=\"AdjustSequence\"} 1",
            "blapose_errors_total{code=\"CANCELLED\",rpc=\"Stream\"}",
            "blapose_connections_closed_total{reason=\"handshake_timeout\"} 1",
            "blapose_limit{limit=\"max_concurrent_streams\"} 100",
            "blapose_limited_total{limit=\"max_concurrent_streams\"} 1",
            "blapose_limit{limit=\"max_connections_per_peer\"} 3",
            "blapose_connections ",
        ],
    )
    .await;
    assert!(
        !body.contains("code=\"FAILED_PRECONDITION\""),
        "a cancel is not a failed precondition:\n{body}"
    );
    drop((_third, silent, fourth, client));
    server.shutdown().await.unwrap();
}

//! The Prometheus exporter, in its own test binary because the recorder is
//! process-global.

use std::sync::Arc;
use std::time::Duration;

use blapose_proto::v1 as pb;
use blapose_server::ServerConfig;
use blapose_test_support::ConstantModel;
use pb::stream_request::Kind as Req;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio_stream::wrappers::ReceiverStream;

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

async fn scrape(addr: std::net::SocketAddr) -> String {
    let mut s = tokio::net::TcpStream::connect(addr).await.unwrap();
    s.write_all(b"GET /metrics HTTP/1.0\r\nHost: localhost\r\n\r\n")
        .await
        .unwrap();
    let mut body = String::new();
    s.read_to_string(&mut body).await.unwrap();
    body
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn prometheus_endpoint_reports_traffic() {
    let metrics_addr: std::net::SocketAddr = format!("127.0.0.1:{}", free_port()).parse().unwrap();
    let config = ServerConfig {
        metrics_addr: Some(metrics_addr),
        ..ServerConfig::default()
    };
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let server = blapose_server::spawn_with_provider(config, listener, Arc::new(ConstantModel))
        .await
        .unwrap();
    let before = scrape(metrics_addr).await;
    assert!(before.contains("blapose_sessions 0"), "{before}");

    let mut client = pb::pose_adjustment_client::PoseAdjustmentClient::connect(format!(
        "http://{}",
        server.local_addr()
    ))
    .await
    .unwrap();
    let (tx, rx) = tokio::sync::mpsc::channel(16);
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
    responses.message().await.unwrap();
    let pose: Vec<f32> = (0..51).map(|i| (i as f32 * 0.37).sin()).collect();
    for (i, keypoints) in [vec![0.1; 34], vec![0.1; 3]].into_iter().enumerate() {
        tx.send(pb::StreamRequest {
            kind: Some(Req::Frame(pb::Frame {
                frame_index: i as u64,
                keypoints_2d: keypoints,
                confidence: vec![],
                pose_3d: pose.clone(),
            })),
        })
        .await
        .unwrap();
        responses.message().await.unwrap();
    }
    drop(tx);
    while responses.message().await.unwrap().is_some() {}

    // The stream's task finishes just after its responses end: poll for it
    // (bounded by a count, not timed).
    let mut after = scrape(metrics_addr).await;
    for _ in 0..10_000 {
        if after.contains("blapose_streams_attached 0") {
            break;
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
        after = scrape(metrics_addr).await;
    }
    for needle in [
        "blapose_frames_total{outcome=\"ok\"} 1",
        "blapose_frames_total{outcome=\"error\"} 1",
        "blapose_errors_total{code=\"INVALID_ARGUMENT\",rpc=\"Stream\"} 1",
        "blapose_session_events_total{event=\"opened\"} 1",
        "blapose_sessions 1",
        "blapose_streams_attached 0",
        "blapose_batch_size_bucket",
        "blapose_queue_latency_seconds_bucket",
        "blapose_compute_latency_seconds_bucket",
        "blapose_frame_latency_seconds_bucket",
    ] {
        assert!(after.contains(needle), "missing {needle:?} in:\n{after}");
    }
    server.shutdown().await.unwrap();
}

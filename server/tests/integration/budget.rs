//! The memory budget and the per-address stream cap over real gRPC: past
//! `--max-streams-per-peer` (open streams of one address across all its
//! connections) a new stream is RESOURCE_EXHAUSTED at once, whichever
//! connection it comes on; past `--memory-budget` new sessions are
//! refused, and calls served again once streams end.

use crate::support;

use std::time::Duration;

use blapose_proto::v1 as pb;
use blapose_server::protect::Protection;
use blapose_server::{ServerConfig, ServerHandle};
use blapose_test_support::spawn_constant;
use pb::pose_adjustment_client::PoseAdjustmentClient;
use pb::stream_response::Kind as Resp;
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tokio_stream::StreamExt;
use tonic::transport::Channel;
use tonic::Code;

async fn start(protection: Protection) -> ServerHandle {
    spawn_constant(ServerConfig {
        protection,
        ..ServerConfig::default()
    })
    .await
}

async fn connect(server: &ServerHandle) -> PoseAdjustmentClient<Channel> {
    PoseAdjustmentClient::connect(format!("http://{}", server.local_addr()))
        .await
        .unwrap()
}

/// Open a session on a new stream of `client` and keep it attached; the
/// sender keeps it open, or the status it was refused with.
async fn hold(
    client: &mut PoseAdjustmentClient<Channel>,
) -> Result<mpsc::Sender<pb::StreamRequest>, tonic::Status> {
    let (tx, rx) = mpsc::channel(4);
    tx.send(support::open()).await.unwrap();
    let mut answers = client.stream(ReceiverStream::new(rx)).await?.into_inner();
    match tokio::time::timeout(Duration::from_secs(5), answers.next())
        .await
        .expect("an answer")
    {
        Some(Ok(pb::StreamResponse {
            kind: Some(Resp::Opened(_)),
        })) => {
            tokio::spawn(async move { while answers.next().await.is_some() {} });
            Ok(tx)
        }
        Some(Err(status)) => Err(status),
        other => panic!("unexpected {other:?}"),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn streams_of_one_address_are_capped_across_its_connections() {
    let server = start(Protection {
        max_streams_per_peer: 8,
        ..Protection::default()
    })
    .await;
    let mut held = Vec::new();
    let mut refused = None;
    // Three connections from the same address, four streams each.
    for _ in 0..3 {
        let mut client = connect(&server).await;
        for _ in 0..4 {
            match hold(&mut client).await {
                Ok(tx) => held.push(tx),
                Err(status) => refused = refused.or(Some(status)),
            }
        }
    }
    assert_eq!(held.len(), 8, "the address's streams, across connections");
    let refused = refused.expect("the ninth stream is refused");
    assert_eq!(refused.code(), Code::ResourceExhausted, "{refused:?}");
    assert!(
        refused.message().contains("--max-streams-per-peer"),
        "{}",
        refused.message()
    );
    // Streams that end make room.
    held.truncate(4);
    tokio::time::sleep(Duration::from_millis(200)).await;
    let mut client = connect(&server).await;
    held.push(hold(&mut client).await.expect("room again"));
    drop(held);
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn past_the_memory_budget_new_sessions_are_refused_until_some_end() {
    // 512 KB: the connection (64 KB and 100 pending streams of 2 KB), then
    // about ten attached sessions (8 KB per stream, 16 KB per session state).
    let server = start(Protection {
        memory_budget: Some(512 << 10),
        ..Protection::default()
    })
    .await;
    let mut client = connect(&server).await;
    let mut held = Vec::new();
    let refused = loop {
        match hold(&mut client).await {
            Ok(tx) => held.push(tx),
            Err(status) => break status,
        }
        assert!(held.len() <= 20, "never refused");
        // Let the sampler see the sessions (every 100 ms).
        tokio::time::sleep(Duration::from_millis(120)).await;
    };
    eprintln!("{} sessions held, then: {refused:?}", held.len());
    assert!(held.len() >= 5, "{}", held.len());
    assert_eq!(refused.code(), Code::ResourceExhausted, "{refused:?}");
    assert!(
        refused.message().contains("--memory-budget"),
        "{}",
        refused.message()
    );
    // Their streams end (the sessions stay, detached, until their TTL):
    // the streams' share of the budget is free again.
    drop(held);
    tokio::time::sleep(Duration::from_millis(300)).await;
    client
        .model_info(pb::ModelInfoRequest {})
        .await
        .expect("served");
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn connections_hold_at_most_half_the_memory_budget() {
    // At what each may hold (itself and 100 pending streams), half of this
    // budget is four connections: --max-connections is lowered to that.
    let each = blapose_server::budget::http2_connection_bytes(100);
    let server = start(Protection {
        memory_budget: Some(8 * each + each / 2),
        ..Protection::default()
    })
    .await;
    let mut held = Vec::new();
    for _ in 0..4 {
        let mut client = connect(&server).await;
        client
            .model_info(pb::ModelInfoRequest {})
            .await
            .expect("served");
        held.push(client);
    }
    let url = format!("http://{}", server.local_addr());
    let fifth = match PoseAdjustmentClient::connect(url).await {
        Ok(mut client) => client.model_info(pb::ModelInfoRequest {}).await.err(),
        Err(e) => Some(tonic::Status::unavailable(e.to_string())),
    };
    assert!(fifth.is_some(), "a fifth connection was served");
    // A closed connection makes room.
    held.truncate(3);
    tokio::time::sleep(Duration::from_millis(300)).await;
    let mut again = connect(&server).await;
    again
        .model_info(pb::ModelInfoRequest {})
        .await
        .expect("served once a connection closed");
    server.shutdown().await.unwrap();
}

//! Per-client limits over real gRPC: one client that opens sessions as fast
//! as it can fills its own share of the session table and is refused
//! (RESOURCE_EXHAUSTED naming the limit), while another client opens and
//! streams as before; the client is told by a header only when a trusted
//! proxy sets it.

use crate::support;

use std::time::{Duration, Instant};

use blapose_proto::v1 as pb;
use blapose_server::ServerConfig;
use pb::pose_adjustment_client::PoseAdjustmentClient;
use pb::stream_response::Kind as Resp;
use support::{frame, frames, open, start};
use tonic::transport::Channel;
use tonic::Code;

const HEADER: &str = "x-blapose-client";

fn config(trusted: bool, max_sessions: usize) -> ServerConfig {
    ServerConfig {
        max_sessions,
        max_sessions_per_client: Some(max_sessions / 2),
        client_header: Some(HEADER.into()),
        trusted_proxies: if trusted {
            vec!["127.0.0.1".parse().unwrap()]
        } else {
            vec![]
        },
        ..ServerConfig::default()
    }
}

async fn exchange(
    client: &mut PoseAdjustmentClient<Channel>,
    who: &str,
    requests: Vec<pb::StreamRequest>,
) -> Result<Vec<Resp>, tonic::Status> {
    support::exchange(client, &[(HEADER, who)], requests).await
}

/// Open as many sessions (left detached) as `who` is allowed; how many,
/// and the refusal.
async fn flood(client: &mut PoseAdjustmentClient<Channel>, who: &str) -> (usize, tonic::Status) {
    let mut opened = 0;
    loop {
        match exchange(client, who, vec![open()]).await {
            Ok(_) => opened += 1,
            Err(status) => return (opened, status),
        }
        assert!(opened <= 4096, "never refused");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn one_client_filling_its_share_leaves_the_others_served() {
    // The default table (4,096 sessions), as in the report that one client
    // filled it in 1.7 s.
    let (server, mut client) = start(config(true, 4096)).await;
    let started = Instant::now();
    let (opened, refused) = flood(&mut client, "flooder").await;
    let flood_time = started.elapsed();
    // Its share: half the table (the default at this size).
    assert_eq!(opened, 2048);
    assert_eq!(refused.code(), Code::ResourceExhausted, "{refused:?}");
    assert!(
        refused.message().contains("--max-sessions-per-client"),
        "{}",
        refused.message()
    );
    // Another client opens and streams as before.
    let started = Instant::now();
    let mut requests = vec![open()];
    requests.extend((0..20).map(frame));
    let answers = exchange(&mut client, "someone else", requests)
        .await
        .unwrap();
    let other = started.elapsed();
    assert_eq!(frames(&answers), 20, "{answers:?}");
    eprintln!(
        "flooder: {opened} sessions in {flood_time:?}, then refused; \
         another client: open + 20 frames in {other:?}"
    );
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn the_client_header_counts_only_from_trusted_proxies() {
    let (server, mut client) = start(config(false, 64)).await;
    let (opened, _) = flood(&mut client, "a").await;
    assert_eq!(opened, 32);
    // Not trusted: "b" is the same peer as "a", and refused too.
    let refused = exchange(&mut client, "b", vec![open()]).await.unwrap_err();
    assert_eq!(refused.code(), Code::ResourceExhausted, "{refused:?}");
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn limits_are_flags_with_env_variables_and_defaults() {
    use clap::Parser;
    let cli = blapose_server::config::Cli::try_parse_from(["blapose-server"]).unwrap();
    let cfg = cli.into_config();
    assert_eq!(cfg.max_sessions_per_client, None);
    assert_eq!(cfg.max_frames_per_session, 128);
    assert_eq!(cfg.token_ttl, Duration::from_secs(3600));
    let limits = blapose_server::state::limits(&cfg);
    assert_eq!(limits.sessions_per_client, 2048);
    assert_eq!(limits.queued_per_client, cfg.queue_capacity / 2);
    // A small table is not split.
    assert_eq!(blapose_server::quota::default_share(3), 3);
    assert_eq!(blapose_server::quota::default_share(1500), 1024);
    let cli = blapose_server::config::Cli::try_parse_from([
        "blapose-server",
        "--max-sessions-per-client",
        "7",
        "--client-header",
        HEADER,
        "--trusted-proxies",
        "10.0.0.1,10.0.0.2",
        "--token-ttl",
        "10m",
    ])
    .unwrap();
    let cfg = cli.into_config();
    assert_eq!(cfg.max_sessions_per_client, Some(7));
    assert_eq!(cfg.trusted_proxies.len(), 2);
    assert_eq!(cfg.token_ttl, Duration::from_secs(600));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn the_client_header_counts_behind_a_dual_stack_listener() {
    // `[::]` accepts IPv4 clients as `::ffff:127.0.0.1`; the trusted proxy
    // is configured as 127.0.0.1 and must still be believed.
    let Ok(listener) = tokio::net::TcpListener::bind("[::]:0").await else {
        eprintln!("SKIP: no IPv6 on this machine");
        return;
    };
    let port = listener.local_addr().unwrap().port();
    let server = blapose_server::spawn(config(true, 64), listener)
        .await
        .unwrap();
    let mut client = PoseAdjustmentClient::connect(format!("http://127.0.0.1:{port}"))
        .await
        .unwrap();
    let (opened, _) = flood(&mut client, "a").await;
    assert_eq!(opened, 32);
    // Trusted: "b" is another client with its own share.
    let answers = exchange(&mut client, "b", vec![open(), frame(0)])
        .await
        .unwrap();
    assert_eq!(frames(&answers), 1, "{answers:?}");
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn two_clients_at_their_shares_leave_a_third_served() {
    // The report: two clients held 2,048 + 2,047 of 4,096 sessions and
    // every other client was refused. Shares now shrink as more clients
    // hold sessions: alone half, with another a third, ...
    let (server, mut client) = start(config(true, 4096)).await;
    let (first, _) = flood(&mut client, "first").await;
    let (second, refused) = flood(&mut client, "second").await;
    // Alone half; then until a share for one more (4,096 / 4) is left.
    assert_eq!((first, second), (2048, 1024));
    assert_eq!(refused.code(), Code::ResourceExhausted, "{refused:?}");
    assert!(refused.message().contains("share"), "{}", refused.message());
    let mut requests = vec![open()];
    requests.extend((0..20).map(frame));
    let answers = exchange(&mut client, "third", requests).await.unwrap();
    assert_eq!(frames(&answers), 20, "{answers:?}");
    // A third flooding as well leaves a share for a fourth (4,096 / 5):
    // without that reserve it took the rest of the table (2,048 + 1,365 +
    // 683) and every later client was refused.
    let (third, _) = flood(&mut client, "third").await;
    assert_eq!(first + second + third + 1, 4096 - 4096 / 5);
    let answers = exchange(&mut client, "fourth", vec![open(), frame(0)])
        .await
        .unwrap();
    assert_eq!(frames(&answers), 1, "{answers:?}");
    server.shutdown().await.unwrap();
}

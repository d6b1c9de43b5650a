//! The token rules and per-client limits end to end through the real
//! HAProxy with `deploy/haproxy.cfg`: two in-process replicas sharing a
//! session key behind it, trusting the balancer's `x-blapose-client`.
//! Skipped (with a note) when `haproxy` is not installed, unless
//! `BLAPOSE_REQUIRE_HAPROXY=1` (deploy/failover-test.sh sets it).

use crate::support;

use std::net::IpAddr;
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use blapose_proto::v1 as pb;
use blapose_server::token::SessionKey;
use blapose_server::{ServerConfig, ServerHandle};
use pb::pose_adjustment_client::PoseAdjustmentClient;
use pb::stream_request::Kind as Req;
use pb::stream_response::Kind as Resp;
use support::{frame, frames, open};
use tonic::transport::{Channel, Endpoint};
use tonic::Code;

const KEY: &str = "a session key the two replicas share";

/// HAProxy, stopped when dropped.
struct Balancer(Child);

impl Drop for Balancer {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

async fn replica() -> ServerHandle {
    let config = ServerConfig {
        session_key: Some(SessionKey::parse(KEY).unwrap()),
        token_every: 10,
        max_sessions: 16,
        max_sessions_per_client: Some(8),
        client_header: Some("x-blapose-client".into()),
        trusted_proxies: vec!["127.0.0.1".parse().unwrap()],
        ..ServerConfig::default()
    };
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    blapose_server::spawn(config, listener).await.unwrap()
}

fn balancer(lb_port: u16, a: &ServerHandle, b: &ServerHandle) -> Option<Balancer> {
    let cfg = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../deploy/haproxy.cfg");
    let child = Command::new("haproxy")
        .args(["-db", "-f"])
        .arg(cfg)
        .env("BLAPOSE_LB_ADDR", format!("127.0.0.1:{lb_port}"))
        .env("BLAPOSE_LB_STATS", format!("127.0.0.1:{}", free_port()))
        .env("BLAPOSE_REPLICA_1", a.local_addr().to_string())
        .env("BLAPOSE_REPLICA_2", b.local_addr().to_string())
        .env("BLAPOSE_REPLICA_3", a.local_addr().to_string())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn();
    match child {
        Ok(child) => Some(Balancer(child)),
        Err(e) => {
            assert!(
                std::env::var("BLAPOSE_REQUIRE_HAPROXY").as_deref() != Ok("1"),
                "haproxy is required: {e}"
            );
            eprintln!("skipped: cannot run haproxy ({e})");
            None
        }
    }
}

/// A client of the balancer connecting from `from` (a loopback address).
fn client(lb_port: u16, from: &str) -> PoseAdjustmentClient<Channel> {
    let channel = Endpoint::from_shared(format!("http://127.0.0.1:{lb_port}"))
        .unwrap()
        .local_address(Some(from.parse::<IpAddr>().unwrap()))
        .connect_lazy();
    PoseAdjustmentClient::new(channel)
}

/// One stream through the balancer with the session's affinity key and a
/// client header HAProxy must overwrite.
async fn exchange(
    client: &mut PoseAdjustmentClient<Channel>,
    affinity: &str,
    requests: Vec<pb::StreamRequest>,
) -> Result<Vec<Resp>, tonic::Status> {
    let headers = [
        ("blapose-affinity", affinity),
        ("x-blapose-client", "spoofed"),
    ];
    support::exchange(client, &headers, requests).await
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn token_rules_and_client_limits_hold_behind_haproxy() {
    let (a, b) = (replica().await, replica().await);
    let lb_port = free_port();
    let Some(_balancer) = balancer(lb_port, &a, &b) else {
        return;
    };
    let mut one = client(lb_port, "127.0.0.2");
    // Wait for the health checks to take the replicas in.
    let mut up = false;
    for _ in 0..100 {
        if exchange(&mut one, "probe", vec![open()]).await.is_ok() {
            up = true;
            break;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    assert!(up, "the balancer never served a stream");
    // A closed session's token is refused where the balancer sends it.
    let mut requests = vec![open()];
    requests.extend((0..12).map(frame));
    requests.push(pb::StreamRequest {
        kind: Some(Req::Close(pb::CloseSession {})),
    });
    let run = exchange(&mut one, "closed", requests).await.unwrap();
    let (id, token) = match (&run[0], run.iter().find(|r| matches!(r, Resp::Token(_)))) {
        (Resp::Opened(o), Some(Resp::Token(t))) => (o.session_id.clone(), t.token.clone()),
        other => panic!("no session and token: {other:?}"),
    };
    let resume = pb::StreamRequest {
        kind: Some(Req::Resume(pb::ResumeSession {
            session_id: id,
            session_token: token,
            session_tokens: true,
        })),
    };
    let refused = exchange(&mut one, "closed", vec![resume])
        .await
        .unwrap_err();
    assert_eq!(refused.code(), Code::FailedPrecondition, "{refused:?}");
    assert!(
        refused.message().contains("closed"),
        "{}",
        refused.message()
    );
    // One client (127.0.0.2, whatever header it sends) fills its share of
    // a replica's table (half of 16; the probe holds one) ...
    let mut opened = 1;
    let status = loop {
        match exchange(&mut one, "flood", vec![open()]).await {
            Ok(_) => opened += 1,
            Err(status) => break status,
        }
        assert!(opened <= 16, "never refused");
    };
    assert_eq!(status.code(), Code::ResourceExhausted, "{status:?}");
    assert!(status.message().contains("--max-sessions-per-client"));
    // ... and another (127.0.0.3) is served on that replica as before.
    let mut two = client(lb_port, "127.0.0.3");
    let mut requests = vec![open()];
    requests.extend((0..5).map(frame));
    let answers = exchange(&mut two, "flood", requests).await.unwrap();
    assert_eq!(frames(&answers), 5, "{answers:?}");
    a.shutdown().await.unwrap();
    b.shutdown().await.unwrap();
}

//! Failover across replicas: two in-process servers
//! with the shipped weights share a session key; `replay_across` streams a
//! shipped example to server A, A shuts down mid-stream (its sessions end
//! with it), and the client library resumes the session on server B from
//! its latest session token, re-sending the frames after the token. The
//! result equals an uninterrupted replay on one server: every frame
//! answered exactly once, the session's frame count exactly the file's,
//! every pose and length within 1e-6 m (in fact bit for bit).
//!
//! Behind a tiny TCP proxy standing in for a load balancer, the same holds
//! when the serving replica becomes unreachable without answering (the
//! proxy switches backends and cuts the connection), and when a connection
//! to the same replica drops with answers in flight (the held session is
//! ahead of the answers received: the library closes it there and restores
//! it from its token, so those answers are not lost).

use std::path::PathBuf;
use std::sync::{Arc, Mutex};

use blapose_client::{
    replay, replay_across, Client, ClientConfig, ClientError, ReplayOptions, Sequence,
};
use blapose_server::token::SessionKey;
use blapose_server::{ServerConfig, ServerHandle};

const KEY: &str = "a shared key of more than 16 bytes";

fn config(key: Option<&str>) -> ServerConfig {
    ServerConfig {
        session_key: key.map(|k| SessionKey::parse(k).unwrap()),
        token_every: 25,
        ..ServerConfig::default()
    }
}

async fn start(config: ServerConfig) -> (ServerHandle, Client) {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let server = blapose_server::spawn(config, listener).await.unwrap();
    let client = Client::connect(ClientConfig::new(format!("http://{}", server.local_addr())))
        .await
        .unwrap();
    (server, client)
}

fn example() -> Sequence {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../examples/cmu_02_02_walk.npz");
    Sequence::load(path, None).unwrap()
}

fn max_diff<const N: usize>(a: &[[f32; N]], b: &[[f32; N]]) -> f32 {
    a.iter()
        .flatten()
        .zip(b.iter().flatten())
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

/// Replay `seq` across `clients` with the sending paced, shutting `victim`
/// down once `after` frames were answered.
async fn replay_shutting_down(
    clients: Vec<Client>,
    seq: &Sequence,
    victim: ServerHandle,
    after: usize,
) -> Result<blapose_client::Adjusted, ClientError> {
    let answered = Arc::new(Mutex::new(0usize));
    let (tx, mut rx) = tokio::sync::mpsc::unbounded_channel();
    let options = ReplayOptions {
        window: 8,
        fps: Some(400.0),
        label: Some("failover".into()),
        ..ReplayOptions::default()
    };
    let counter = answered.clone();
    let run = replay_across(&clients, seq, &options, move |n| {
        *counter.lock().unwrap() = n;
        if n == after {
            let _ = tx.send(());
        }
    });
    let kill = async move {
        rx.recv().await.expect("the replay reaches the frame");
        victim.shutdown().await.unwrap();
    };
    let (result, ()) = tokio::join!(run, kill);
    result
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_replay_moves_to_another_replica_when_its_server_goes_away() {
    let seq = example();
    let n = seq.len();
    assert!(n > 100, "{n} frames");

    // The uninterrupted replay on one server.
    let (server_r, reference_client) = start(config(Some(KEY))).await;
    let reference = replay(&reference_client, &seq, &ReplayOptions::default(), |_| {})
        .await
        .unwrap();
    assert_eq!(reference.resumes, 0);
    assert_eq!(reference.adjusted.len(), n);
    server_r.shutdown().await.unwrap();

    let (server_a, a) = start(config(Some(KEY))).await;
    let (server_b, b) = start(config(Some(KEY))).await;
    let after = 61; // tokens every 25 frames: resumes from frame 50 or later
    let result = replay_shutting_down(vec![a, b], &seq, server_a, after)
        .await
        .expect("the replay survives its server");
    assert!(result.resumes >= 1, "the session moved");
    assert_eq!(result.first_frame, 0);
    assert_eq!(result.adjusted.len(), n, "every frame answered once");
    assert_eq!(result.bone_lengths.len(), n);
    let summary = result.session.expect("closed on B");
    assert_eq!(summary.frames_seen, n as u64, "no frame processed twice");
    let dl = max_diff(&result.bone_lengths, &reference.bone_lengths);
    let dp = result
        .adjusted
        .iter()
        .zip(&reference.adjusted)
        .map(|(x, y)| max_diff(x, y))
        .fold(0.0, f32::max);
    println!(
        "failover after {after} frames: {} resume(s); max length diff {dl:e} m, max pose diff {dp:e} m",
        result.resumes
    );
    assert!(dl <= 1e-6 && dp <= 1e-6, "lengths {dl}, poses {dp}");
    let final_lengths = summary.bone_lengths.expect("lengths");
    let want = reference.session.unwrap().bone_lengths.unwrap();
    let d = max_diff(&[final_lengths], &[want]);
    assert!(d <= 1e-6, "final lengths differ by {d}");
    server_b.shutdown().await.unwrap();
}

/// Without a session key there is no token to move with: the replay ends
/// with the server's UNAVAILABLE, as it always did.
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn without_a_key_the_replay_fails_with_its_server() {
    let seq = example();
    let (server_a, a) = start(config(None)).await;
    let (server_b, b) = start(config(None)).await;
    match replay_shutting_down(vec![a, b], &seq, server_a, 20).await {
        Err(ClientError::Status(s)) => assert_eq!(s.code(), tonic::Code::Unavailable, "{s:?}"),
        other => panic!("expected UNAVAILABLE, got {other:?}"),
    }
    server_b.shutdown().await.unwrap();
}

/// A tiny TCP proxy standing in for a load balancer: it forwards each
/// connection to the current backend, can switch backends, and can cut
/// every open connection at once (a crash or a network failure as the
/// client sees it: frames in flight and their answers are lost).
struct Proxy {
    addr: std::net::SocketAddr,
    backend: Arc<Mutex<std::net::SocketAddr>>,
    cut: tokio::sync::watch::Sender<u64>,
}

impl Proxy {
    async fn start(backend: std::net::SocketAddr) -> Self {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap();
        let backend = Arc::new(Mutex::new(backend));
        let (cut, _) = tokio::sync::watch::channel(0u64);
        let (to, cuts) = (backend.clone(), cut.clone());
        tokio::spawn(async move {
            while let Ok((mut down, _)) = listener.accept().await {
                let target = *to.lock().unwrap();
                let mut cut = cuts.subscribe();
                tokio::spawn(async move {
                    let Ok(mut up) = tokio::net::TcpStream::connect(target).await else {
                        return;
                    };
                    tokio::select! {
                        _ = tokio::io::copy_bidirectional(&mut down, &mut up) => {}
                        _ = cut.changed() => {}
                    }
                });
            }
        });
        Proxy { addr, backend, cut }
    }

    fn switch_to(&self, backend: std::net::SocketAddr) {
        *self.backend.lock().unwrap() = backend;
    }

    fn cut_connections(&self) {
        self.cut.send_modify(|n| *n += 1);
    }

    async fn client(&self) -> Client {
        Client::connect(ClientConfig::new(format!("http://{}", self.addr)))
            .await
            .unwrap()
    }
}

/// Replay through `proxy`, calling `at(proxy)` right when the answer to
/// frame `after - 1` arrives (the frames sent after it are in flight).
async fn replay_through(
    proxy: &Proxy,
    seq: &Sequence,
    after: usize,
    at: impl FnOnce(&Proxy),
) -> blapose_client::Adjusted {
    let client = proxy.client().await;
    // Unpaced: 8 frames in flight at any time, so a cut loses answers to
    // frames the server has processed.
    let options = ReplayOptions {
        window: 8,
        ..ReplayOptions::default()
    };
    let mut at = Some(at);
    replay_across(std::slice::from_ref(&client), seq, &options, |n| {
        if n == after {
            if let Some(at) = at.take() {
                at(proxy);
            }
        }
    })
    .await
    .expect("the replay survives")
}

fn assert_equal_to(result: &blapose_client::Adjusted, reference: &blapose_client::Adjusted) {
    let n = reference.adjusted.len();
    assert!(result.resumes >= 1, "the session was resumed");
    assert_eq!(result.first_frame, 0);
    assert_eq!(result.adjusted.len(), n, "every frame answered once");
    assert_eq!(
        result.session.as_ref().unwrap().frames_seen,
        n as u64,
        "no frame processed twice"
    );
    let dl = max_diff(&result.bone_lengths, &reference.bone_lengths);
    let dp = result
        .adjusted
        .iter()
        .zip(&reference.adjusted)
        .map(|(x, y)| max_diff(x, y))
        .fold(0.0, f32::max);
    assert!(dl <= 1e-6 && dp <= 1e-6, "lengths {dl}, poses {dp}");
}

/// Behind a load balancer: the replica serving a session becomes
/// unreachable mid-stream (it keeps running, as a crashed or partitioned
/// one would look; no graceful answers) and the balancer sends the
/// reconnect to another replica, which restores the session from the token.
/// Then the connection drops again, and the session resumes on the replica
/// now holding it, the answers lost in flight recovered from the token.
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_replay_behind_a_switching_proxy_moves_and_recovers_lost_answers() {
    let seq = example();
    let (server_r, reference_client) = start(config(Some(KEY))).await;
    let reference = replay(&reference_client, &seq, &ReplayOptions::default(), |_| {})
        .await
        .unwrap();
    server_r.shutdown().await.unwrap();

    let (server_a, _) = start(config(Some(KEY))).await;
    let (server_b, _) = start(config(Some(KEY))).await;
    let proxy = Proxy::start(server_a.local_addr()).await;
    let b = server_b.local_addr();
    let result = replay_through(&proxy, &seq, 61, |p| {
        p.switch_to(b);
        p.cut_connections();
    })
    .await;
    println!("moved behind the proxy: {} resume(s)", result.resumes);
    assert_equal_to(&result, &reference);

    // Same replica: the connection drops with answers in flight.
    let proxy = Proxy::start(b).await;
    let result = replay_through(&proxy, &seq, 87, |p| p.cut_connections()).await;
    println!(
        "reconnected to the same replica: {} resume(s)",
        result.resumes
    );
    assert_equal_to(&result, &reference);
    server_a.shutdown().await.unwrap();
    server_b.shutdown().await.unwrap();
}

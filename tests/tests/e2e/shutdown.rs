//! Graceful shutdown answers every frame the server has already received.
//!
//! To have frames provably waiting when shutdown starts, one attached
//! session stays idle: the batcher then runs a partial batch only after
//! `max_queue_delay` (250 ms), so each active session gets one answer per
//! 250 ms, and when the first answers arrive the remaining frames are still
//! queued inside the server.

use std::time::Duration;

use blapose_client::{KeypointLayout, SessionEvent};
use blapose_tests::{synthetic_sequence, test_config, TestServer};
use tonic::Code;

const ACTIVE: u64 = 3;
const FRAMES: usize = 8;
/// A grace period no drain comes near, and a bound between the two: a
/// drain takes about a second (a few frames at 250 ms each).
const GRACE: Duration = Duration::from_secs(3600);
const DRAIN_BOUND: Duration = Duration::from_secs(120);

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn shutdown_drains_frames_already_received() {
    let config = blapose_server::ServerConfig {
        max_queue_delay: Duration::from_millis(250),
        shutdown_grace: GRACE,
        ..test_config()
    };
    let server = TestServer::start(config).await;
    let addr = server.addr;
    let client = server.client().await;
    let format = synthetic_sequence(40, 1, KeypointLayout::H36m17).input_format;
    let idle = client
        .open_session(format, Some("idle"))
        .await
        .expect("idle session");

    let mut streams = Vec::new();
    for s in 0..ACTIVE {
        let seq = synthetic_sequence(41 + s, FRAMES, KeypointLayout::H36m17);
        let session = client
            .open_session(seq.input_format, None)
            .await
            .expect("open");
        let (_, sender, receiver) = session.split();
        for t in 0..FRAMES {
            sender.send(&seq.frame(t)).await.expect("send");
        }
        streams.push((sender, receiver));
    }
    // Wait for each session's first answer: by then all its frames have
    // long been read (loopback) and most are still queued.
    let mut answered = vec![Vec::new(); ACTIVE as usize];
    for (s, (_, receiver)) in streams.iter_mut().enumerate() {
        match receiver.next().await.expect("first answer") {
            Some(SessionEvent::Adjusted(f)) => answered[s].push(f.frame_index),
            other => panic!("session {s}: {other:?}"),
        }
    }

    let shutdown = tokio::spawn(server.shutdown());
    let mut after_shutdown = 0;
    for (s, (_, receiver)) in streams.iter_mut().enumerate() {
        let end = loop {
            match receiver.next().await {
                Ok(Some(SessionEvent::Adjusted(f))) => {
                    answered[s].push(f.frame_index);
                    after_shutdown += 1;
                }
                Ok(other) => panic!("session {s}: unexpected {other:?}"),
                Err(e) => break e,
            }
        };
        assert_eq!(end.code(), Some(Code::Unavailable), "session {s}: {end}");
        assert_eq!(
            answered[s],
            (0..FRAMES as u64).collect::<Vec<_>>(),
            "session {s}: every frame, once, in order"
        );
    }
    assert!(
        after_shutdown >= ACTIVE as usize,
        "only {after_shutdown} answers came after shutdown began: nothing was drained"
    );
    // The drain ends the server, not the grace period: with a grace far
    // longer than the bound, only a drain finishes in time.
    tokio::time::timeout(DRAIN_BOUND, shutdown)
        .await
        .expect("shutdown ended by the grace period, not by draining")
        .expect("shutdown task");
    drop(idle);
    drop(streams);

    // The server is gone.
    let mut config = blapose_client::ClientConfig::new(format!("http://{addr}"));
    config.connect_attempts = 1;
    config.connect_timeout = Duration::from_millis(500);
    assert!(
        blapose_client::Client::connect(config).await.is_err(),
        "server still accepts connections"
    );
}

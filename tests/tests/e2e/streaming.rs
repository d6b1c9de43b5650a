//! Many sessions at once: every frame answered exactly once, in order, with
//! exactly what the library computes.

use std::sync::Arc;

use blapose_client::{
    adjust_offline, replay, replay_session, KeypointLayout, ModelKind, ReplayOptions, SessionEvent,
};
use blapose_tests::{
    lengths_diff, pose_diff, synthetic_sequence, test_camera, test_config, Reference, TestServer,
    TOLERANCE,
};
use tokio::task::JoinSet;

const SESSIONS: u64 = 64;
const FRAMES: usize = 40;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn concurrent_sessions_match_the_library_path() {
    let server = TestServer::start(test_config()).await;
    let client = server.client().await;
    let reference = Arc::new(Reference::new());
    let layouts = [
        KeypointLayout::H36m17,
        KeypointLayout::Sh16,
        KeypointLayout::Coco17,
    ];

    let mut tasks = JoinSet::new();
    for s in 0..SESSIONS {
        let client = client.clone();
        let layout = layouts[s as usize % layouts.len()];
        tasks.spawn(async move {
            let mut seq = synthetic_sequence(1000 + s, FRAMES, layout);
            // Every other session sends a camera: the camera-aware model.
            if s % 2 == 1 {
                seq.camera = Some(test_camera());
            }
            let options = ReplayOptions {
                window: 8,
                label: Some(format!("e2e-{s}")),
                ..ReplayOptions::default()
            };
            let result = replay(&client, &seq, &options, |_| {}).await;
            (s, seq, result)
        });
    }
    let mut ids = std::collections::HashSet::new();
    while let Some(joined) = tasks.join_next().await {
        let (s, seq, result) = joined.expect("task");
        let result = result.unwrap_or_else(|e| panic!("session {s}: {e}"));
        let (want_poses, want_lengths) = reference.online(&seq);
        assert_eq!(result.adjusted.len(), FRAMES, "session {s}");
        for t in 0..FRAMES {
            let dp = pose_diff(&result.adjusted[t], &want_poses[t]);
            let dl = lengths_diff(&result.bone_lengths[t], &want_lengths[t]);
            assert!(
                dp < TOLERANCE && dl < TOLERANCE,
                "session {s} frame {t}: pose diff {dp}, length diff {dl}"
            );
        }
        assert_eq!(result.camera, seq.camera, "session {s} echoes its camera");
        let summary = result.session.expect("stream result has a session");
        assert_eq!(summary.frames_seen, FRAMES as u64);
        let last = summary.bone_lengths.expect("final lengths");
        assert!(lengths_diff(&last, &want_lengths[FRAMES - 1]) < TOLERANCE);
        assert!(
            ids.insert(summary.session_id.clone()),
            "duplicate session id"
        );
    }
    assert_eq!(ids.len(), SESSIONS as usize);
    for id in &ids {
        assert_eq!(id.len(), 32, "{id}");
        assert!(
            id.chars()
                .all(|c| c.is_ascii_hexdigit() && !c.is_ascii_uppercase()),
            "{id}"
        );
    }
    server.shutdown().await;
}

/// Frame indices are the client's own numbers: echoed unchanged, in send
/// order, one answer each, then exactly one `closed`.
#[tokio::test]
async fn answers_echo_arbitrary_indices_in_order_exactly_once() {
    let server = TestServer::start(test_config()).await;
    let client = server.client().await;
    let seq = synthetic_sequence(7, 30, KeypointLayout::H36m17);
    let session = client
        .open_session(seq.input_format, None)
        .await
        .expect("open");
    assert!(!session.info().resumed);
    assert_eq!(session.info().frames_seen, 0);
    assert!(session.info().bone_lengths.is_none());
    let (_, sender, mut receiver) = session.split();
    let indices: Vec<u64> = (0..30u64).map(|t| 1_000_000 - 7 * t * t).collect();
    for (t, &index) in indices.iter().enumerate() {
        let mut frame = seq.frame(t);
        frame.frame_index = index;
        sender.send(&frame).await.expect("send");
    }
    sender.close().await.expect("close");
    let mut seen = Vec::new();
    let mut closed = 0;
    while let Some(event) = receiver.next().await.expect("stream ends with OK") {
        match event {
            SessionEvent::Adjusted(f) => {
                assert_eq!(closed, 0, "answer after closed");
                assert_eq!(f.frames_seen, seen.len() as u64 + 1);
                seen.push(f.frame_index);
            }
            SessionEvent::Closed(s) => {
                closed += 1;
                assert_eq!(s.frames_seen, 30);
            }
            SessionEvent::Rejected(r) => panic!("unexpected rejection {r:?}"),
        }
    }
    assert_eq!(seen, indices);
    assert_eq!(closed, 1);
    server.shutdown().await;
}

#[tokio::test]
async fn offline_rpc_matches_the_library_path() {
    let server = TestServer::start(test_config()).await;
    let client = server.client().await;
    let reference = Reference::new();
    for (seed, layout, camera) in [
        (11, KeypointLayout::H36m17, None),
        (12, KeypointLayout::Sh16, None),
        (13, KeypointLayout::Coco17, None),
        (14, KeypointLayout::H36m17, Some(test_camera())),
    ] {
        let mut seq = synthetic_sequence(seed, 75, layout);
        seq.camera = camera;

        let bigru = adjust_offline(&client, &seq, ModelKind::BiGru)
            .await
            .expect("bigru");
        assert_eq!(bigru.model, ModelKind::BiGru);
        let (want, lengths) = reference.offline(&seq);
        for (t, (got, want)) in bigru.adjusted.iter().zip(&want).enumerate() {
            assert!(pose_diff(got, want) < TOLERANCE, "{layout} frame {t}");
            assert!(
                lengths_diff(&bigru.bone_lengths[t], &lengths) < TOLERANCE,
                "{layout} frame {t}"
            );
        }
        assert_eq!(bigru.adjusted.len(), seq.len());
        if seq.camera.is_some() {
            // The rectification changed what the model read.
            let plain = blapose_client::Sequence {
                camera: None,
                ..seq.clone()
            };
            assert!(lengths_diff(&reference.offline(&plain).1, &lengths) > 1e-4);
        }

        // The online model through the offline RPC gives what a stream gives.
        let gru = adjust_offline(&client, &seq, ModelKind::Gru)
            .await
            .expect("gru");
        assert_eq!(gru.model, ModelKind::Gru);
        let (want, lengths) = reference.online(&seq);
        for t in 0..seq.len() {
            assert!(
                pose_diff(&gru.adjusted[t], &want[t]) < TOLERANCE,
                "{layout} frame {t}"
            );
            assert!(
                lengths_diff(&gru.bone_lengths[t], &lengths[t]) < TOLERANCE,
                "{layout} frame {t}"
            );
        }
    }
    server.shutdown().await;
}

#[tokio::test]
async fn model_info_and_health() {
    use tonic_health::pb::health_check_response::ServingStatus;
    use tonic_health::pb::{health_client::HealthClient, HealthCheckRequest};

    let server = TestServer::start(test_config()).await;
    let client = server.client().await;
    let info = client.model_info().await.expect("model info");
    assert_eq!(info.protocol, "blapose.v1");
    assert_eq!(info.joint_names.len(), 17);
    assert_eq!(info.bone_names.len(), 16);
    assert_eq!(info.layouts.len(), 3);
    let kinds: Vec<_> = info.models.iter().filter_map(|m| m.model).collect();
    assert!(
        kinds.contains(&ModelKind::Gru) && kinds.contains(&ModelKind::BiGru),
        "{kinds:?}"
    );
    for m in &info.models {
        assert_eq!(m.parameter_count, 2_390_784, "{}", m.name);
        assert_eq!(m.hidden_size, 512);
        assert_eq!(m.weights_sha256.len(), 64);
    }
    assert_eq!(info.session_ttl, test_config().session_ttl);

    for service in ["", blapose_proto::SERVICE_NAME] {
        let status = HealthClient::new(client.channel())
            .check(HealthCheckRequest {
                service: service.to_string(),
            })
            .await
            .expect("health check")
            .into_inner()
            .status;
        assert_eq!(status, ServingStatus::Serving as i32, "service {service:?}");
    }
    server.shutdown().await;
}

/// `--fps` paces the sending side (the pacing itself is tested with paused
/// time in the client's `replay` module): a paced replay still answers
/// every frame, in order.
#[tokio::test]
async fn replay_paces_to_the_requested_frame_rate() {
    let server = TestServer::start(test_config()).await;
    let client = server.client().await;
    let seq = synthetic_sequence(14, 20, KeypointLayout::H36m17);
    let options = ReplayOptions {
        fps: Some(1000.0),
        window: 4,
        ..ReplayOptions::default()
    };
    let mut progress = Vec::new();
    let result = replay(&client, &seq, &options, |n| progress.push(n))
        .await
        .expect("replay");
    assert_eq!(progress, (1..=20).collect::<Vec<_>>());
    assert_eq!(result.adjusted.len(), 20);
    server.shutdown().await;
}

/// After a dropped connection the client continues from the resumed
/// session's `frames_seen` (`replay_session`): frames the server processed
/// whose answers never arrived are not sent again, so every answer from
/// there on is the uninterrupted session's.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_resumed_replay_continues_from_frames_seen() {
    let server = TestServer::start(test_config()).await;
    let client = server.client().await;
    let reference = Reference::new();
    let seq = synthetic_sequence(15, 40, KeypointLayout::H36m17);
    let (want_poses, want_lengths) = reference.online(&seq);

    // 12 frames sent, 5 answers read, then the stream goes away and the
    // other 7 answers with it.
    let mut session = client
        .open_session(seq.input_format, None)
        .await
        .expect("open");
    for t in 0..12 {
        session.send(&seq.frame(t)).await.expect("send");
    }
    for (t, want) in want_lengths.iter().enumerate().take(5) {
        match session.next_event().await.expect("answer") {
            Some(SessionEvent::Adjusted(f)) => {
                assert_eq!(f.frame_index, t as u64);
                assert!(lengths_diff(&f.bone_lengths, want) < TOLERANCE);
            }
            other => panic!("frame {t}: {other:?}"),
        }
    }
    let id = session.detach(std::time::Duration::from_secs(60)).await;

    let resumed = client.resume_session(&id).await.expect("resume");
    assert_eq!(
        resumed.info().frames_seen,
        12,
        "the 7 unanswered frames were processed"
    );
    let options = ReplayOptions {
        window: 4,
        ..ReplayOptions::default()
    };
    let result = replay_session(resumed, &seq, &options, |_| {})
        .await
        .expect("the replay continues");
    assert_eq!(result.first_frame, 12);
    assert_eq!(result.adjusted.len(), seq.len() - 12);
    for (k, t) in (12..seq.len()).enumerate() {
        let dp = pose_diff(&result.adjusted[k], &want_poses[t]);
        let dl = lengths_diff(&result.bone_lengths[k], &want_lengths[t]);
        assert!(
            dp < TOLERANCE && dl < TOLERANCE,
            "frame {t}: pose diff {dp}, length diff {dl}"
        );
    }
    assert_eq!(
        result.session.expect("closed").frames_seen,
        seq.len() as u64
    );
    server.shutdown().await;
}

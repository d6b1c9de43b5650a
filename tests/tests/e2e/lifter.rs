//! The server lifter (`--lifter-weights`): sessions opened with
//! `server_lifter` send 2D keypoints only and get back poses the server
//! lifted with its causal lifter and then adjusted, named by the lifter.
//! Checked against the library path (the lifter's own window and lift, the
//! GRU reference, `adjust_pose`), with refused frames that must leave the
//! lifter's window as it was, resume, ModelInfo, start-up errors, and
//! sessions that send their own poses on the same server.

use std::sync::Arc;
use std::time::Duration;

use blapose_client::sequence::{read_adjusted, read_lifted};
use blapose_client::{
    replay, ClientError, Coordinates, FrameInput, InputFormat, KeypointLayout, ReplayOptions,
    Sequence, SessionEvent, SessionOptions,
};
use blapose_core::bones::bone_lengths;
use blapose_lifters::{keypoints_tensor, poses_from_tensor};
use blapose_tests::{
    centred_lifter_weights_file, input_frames, lengths_diff, lifted_reference, lifter_config,
    lifter_weights_file, pose_diff, synthetic_sequence, test_config, test_lifter, weights_dir,
    Reference, TestServer, TEST_LIFTER_NAME, TOLERANCE,
};
use tokio::task::JoinSet;
use tonic::Code;

/// Lifted poses: the server's batched lift and the one-window library lift
/// may round differently in the last bits.
const LIFT_TOLERANCE: f32 = 1e-5;

fn lifting() -> SessionOptions<'static> {
    SessionOptions {
        label: Some("lifting"),
        server_lifter: true,
        ..Default::default()
    }
}

/// `seq` with its keypoints converted to normalized Human3.6M-17 (the
/// server's model input), so a test can send values the server uses as is.
fn normalized(seq: &Sequence) -> Sequence {
    Sequence {
        input_format: InputFormat {
            layout: KeypointLayout::H36m17,
            coordinates: Coordinates::Normalized,
        },
        keypoints_2d: Reference::model_inputs(seq),
        confidence: Vec::new(),
        ..seq.clone()
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_lifting_session_answers_keypoints_only_frames_with_the_lifters_poses() {
    let server = TestServer::start(lifter_config()).await;
    let client = server.client().await;
    let lifter = test_lifter();
    let reference = Reference::new();
    // COCO keypoints in pixels: the lifter sees what the GRU sees, after
    // the server's layout conversion and normalization.
    let seq = synthetic_sequence(21, 30, KeypointLayout::Coco17);
    let options = ReplayOptions {
        window: 8,
        server_lifter: true,
        ..ReplayOptions::default()
    };
    let result = replay(&client, &seq, &options, |_| {})
        .await
        .expect("replay");
    assert_eq!(result.lifter.as_deref(), Some(TEST_LIFTER_NAME));
    assert_eq!(result.adjusted.len(), seq.len());
    assert_eq!(result.lifted.len(), seq.len());

    // The first pose is the network on the edge-padded window: the first
    // frame repeated receptive_field times.
    let first = input_frames(&seq)[0];
    let window = keypoints_tensor(&vec![first; lifter.receptive_field()]).unwrap();
    let out = lifter.model().forward_window(&window).unwrap();
    let want_first = poses_from_tensor(&out).unwrap()[0];
    assert_eq!(want_first[0], [0.0; 3], "the file's pelvis outputs are 0");
    let d = pose_diff(&result.lifted[0], &want_first);
    assert!(d < LIFT_TOLERANCE, "first lifted pose differs by {d}");

    // Every frame: the lifter's pose from its window of this stream, root
    // at 0, adjusted exactly as a client's pose would be.
    let want_lifted = lifted_reference(&lifter, &seq);
    let (want_poses, want_lengths) = reference.online_lifted(&seq, &want_lifted);
    for t in 0..seq.len() {
        assert_eq!(result.lifted[t][0], [0.0; 3], "frame {t}: root at 0");
        let dl = pose_diff(&result.lifted[t], &want_lifted[t]);
        assert!(dl < LIFT_TOLERANCE, "frame {t}: lifted pose diff {dl}");
        let dp = pose_diff(&result.adjusted[t], &want_poses[t]);
        let db = lengths_diff(&result.bone_lengths[t], &want_lengths[t]);
        assert!(
            dp < TOLERANCE && db < TOLERANCE,
            "frame {t}: pose diff {dp}, length diff {db}"
        );
        // The adjusted pose has exactly the returned lengths, and the
        // lifted pose's root.
        let own = bone_lengths(&result.adjusted[t]);
        assert!(
            lengths_diff(&own, &result.bone_lengths[t]) < 1e-5,
            "frame {t}: {own:?} vs {:?}",
            result.bone_lengths[t]
        );
        assert_eq!(result.adjusted[t][0], [0.0; 3]);
    }
    // A stream whose window has filled differs from the padded start.
    assert!(pose_diff(&result.lifted[20], &result.lifted[0]) > 1e-4);

    // `replay --server-lifter --out` keeps the lifter's poses: lifted_3d.
    let out = weights_dir().join(format!("lifted-out-{}.npz", std::process::id()));
    result.write_npz(&out).expect("write the output file");
    assert_eq!(
        read_lifted(&out).expect("read lifted_3d"),
        Some(result.lifted.clone())
    );
    let (adjusted, lengths) = read_adjusted(&out).expect("read the output file");
    assert_eq!((adjusted, lengths), (result.adjusted, result.bone_lengths));
    std::fs::remove_file(&out).ok();
    server.shutdown().await;
}

#[tokio::test]
async fn refused_frames_of_a_lifting_session_leave_its_window_as_it_was() {
    let server = TestServer::start(lifter_config()).await;
    let client = server.client().await;
    let lifter = test_lifter();
    let reference = Reference::new();
    let seq = normalized(&synthetic_sequence(22, 16, KeypointLayout::H36m17));
    let session = client
        .open_session_with(seq.input_format, &lifting())
        .await
        .expect("open");
    assert_eq!(session.info().lifter.as_deref(), Some(TEST_LIFTER_NAME));
    let (_, sender, mut receiver) = session.split();

    // Frames 0..4 go through; then three refused frames; then the rest.
    let bad: Vec<(&str, FrameInput, Code)> = vec![
        (
            "a pose in a lifting session",
            FrameInput {
                frame_index: 100,
                ..seq.frame(4)
            },
            Code::InvalidArgument,
        ),
        (
            "a NaN keypoint",
            FrameInput {
                frame_index: 101,
                keypoints_2d: vec![[f32::NAN, 0.0]; 17],
                ..seq.keypoints_frame(4)
            },
            Code::InvalidArgument,
        ),
        (
            // Valid keypoints (within +-1e6) the lifter turns into a pose
            // outside +-1e4 m: the server lifter's failure, this frame only.
            "a pose the lifter cannot produce sensibly",
            FrameInput {
                frame_index: 102,
                keypoints_2d: vec![[1e6, -1e6]; 17],
                ..seq.keypoints_frame(4)
            },
            Code::Internal,
        ),
    ];
    for t in 0..4 {
        sender.send(&seq.keypoints_frame(t)).await.expect("send");
    }
    for (_, frame, _) in &bad {
        sender.send(frame).await.expect("send");
    }
    for t in 4..seq.len() {
        sender.send(&seq.keypoints_frame(t)).await.expect("send");
    }
    sender.close().await.expect("close");

    // The accepted frames are exactly a clean session's.
    let want_lifted = lifted_reference(&lifter, &seq);
    let (want_poses, want_lengths) = reference.online_lifted(&seq, &want_lifted);
    let check = |t: usize, event: Option<SessionEvent>| match event {
        Some(SessionEvent::Adjusted(f)) => {
            assert_eq!(f.frame_index, t as u64);
            assert_eq!(
                f.frames_seen,
                t as u64 + 1,
                "refused frames are not counted"
            );
            assert_eq!(f.lifter(), Some(TEST_LIFTER_NAME));
            let lifted = f.lifted.expect("a lifted pose").pose;
            let dl = pose_diff(&lifted, &want_lifted[t]);
            assert!(dl < LIFT_TOLERANCE, "frame {t}: lifted diff {dl}");
            assert!(pose_diff(&f.pose, &want_poses[t]) < TOLERANCE, "frame {t}");
            assert!(lengths_diff(&f.bone_lengths, &want_lengths[t]) < TOLERANCE);
        }
        other => panic!("frame {t}: {other:?}"),
    };
    for t in 0..4 {
        check(t, receiver.next().await.expect("answer"));
    }
    for (what, frame, code) in &bad {
        match receiver.next().await.expect("answer") {
            Some(SessionEvent::Rejected(r)) => {
                assert_eq!(
                    (r.code, r.frame_index),
                    (*code, frame.frame_index),
                    "{what}: {}",
                    r.message
                );
                if *code == Code::InvalidArgument && frame.pose_3d.is_some() {
                    assert!(r.message.contains("server lifter"), "{what}: {}", r.message);
                }
                if *code == Code::Internal {
                    assert!(r.message.contains("server lifter"), "{what}: {}", r.message);
                    assert!(r.message.contains("not updated"), "{what}: {}", r.message);
                }
            }
            other => panic!("{what}: expected a rejection, got {other:?}"),
        }
    }
    for t in 4..seq.len() {
        check(t, receiver.next().await.expect("answer"));
    }
    match receiver.next().await.expect("answer") {
        Some(SessionEvent::Closed(s)) => assert_eq!(s.frames_seen, seq.len() as u64),
        other => panic!("close: {other:?}"),
    }
    server.shutdown().await;
}

#[tokio::test]
async fn server_lifter_on_a_server_without_one_is_invalid_argument() {
    let server = TestServer::start(test_config()).await;
    let client = server.client().await;
    let format = InputFormat::pixels(KeypointLayout::H36m17, 1000, 1000);
    match client.open_session_with(format, &lifting()).await {
        Err(ClientError::Status(s)) => {
            assert_eq!(s.code(), Code::InvalidArgument, "{}", s.message());
            assert!(s.message().contains("--lifter-weights"), "{}", s.message());
        }
        other => panic!(
            "expected INVALID_ARGUMENT, got {:?}",
            other.map(|s| s.info().clone())
        ),
    }
    // The server is fine afterwards, and reports no lifter.
    assert!(client.model_info().await.expect("info").lifter.is_none());
    let session = client.open_session(format, None).await.expect("open");
    assert_eq!(session.info().lifter, None);
    server.shutdown().await;
}

/// Client-pose sessions on a lifting server, concurrently with lifting
/// sessions (so frames of both kinds share batches): answered exactly as
/// without a lifter, and never named after it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sessions_that_send_poses_are_unchanged_on_a_lifting_server() {
    let server = TestServer::start(lifter_config()).await;
    let client = server.client().await;
    let reference = Arc::new(Reference::new());
    let lifter = Arc::new(test_lifter());
    let mut tasks = JoinSet::new();
    for s in 0..6u64 {
        let client = client.clone();
        let seq = synthetic_sequence(300 + s, 24, KeypointLayout::Sh16);
        let server_lifter = s % 2 == 0;
        tasks.spawn(async move {
            let options = ReplayOptions {
                window: 4,
                server_lifter,
                ..ReplayOptions::default()
            };
            let result = replay(&client, &seq, &options, |_| {}).await;
            (s, server_lifter, seq, result)
        });
    }
    while let Some(joined) = tasks.join_next().await {
        let (s, server_lifter, seq, result) = joined.expect("task");
        let result = result.unwrap_or_else(|e| panic!("session {s}: {e}"));
        let (want_poses, want_lengths) = if server_lifter {
            assert_eq!(result.lifter.as_deref(), Some(TEST_LIFTER_NAME));
            reference.online_lifted(&seq, &lifted_reference(&lifter, &seq))
        } else {
            assert_eq!(result.lifter, None, "session {s}");
            assert!(result.lifted.is_empty(), "session {s}");
            reference.online(&seq)
        };
        for t in 0..seq.len() {
            let dp = pose_diff(&result.adjusted[t], &want_poses[t]);
            let dl = lengths_diff(&result.bone_lengths[t], &want_lengths[t]);
            assert!(
                dp < TOLERANCE && dl < TOLERANCE,
                "session {s} (lifting {server_lifter}) frame {t}: pose diff {dp}, length diff {dl}"
            );
        }
    }
    // One frame at a time: a client pose's answer carries no lifter fields.
    let seq = synthetic_sequence(310, 1, KeypointLayout::H36m17);
    let mut session = client
        .open_session(seq.input_format, None)
        .await
        .expect("open");
    assert_eq!(session.info().lifter, None);
    let answer = session.adjust(&seq.frame(0)).await.expect("frame");
    assert_eq!((answer.lifter(), &answer.lifted), (None, &None));
    // ... and a frame without a pose is still refused there.
    let refused = session.adjust(&seq.keypoints_frame(0)).await;
    assert!(
        matches!(&refused, Err(ClientError::FrameRejected { code: Code::InvalidArgument, message, .. }) if message.contains("pose_3d")),
        "{refused:?}"
    );
    server.shutdown().await;
}

#[tokio::test]
async fn resume_keeps_the_lifter_window() {
    let server = TestServer::start(lifter_config()).await;
    let client = server.client().await;
    let lifter = test_lifter();
    let reference = Reference::new();
    let seq = synthetic_sequence(23, 20, KeypointLayout::H36m17);
    let want_lifted = lifted_reference(&lifter, &seq);
    let (want_poses, _) = reference.online_lifted(&seq, &want_lifted);
    let check = |t: usize, f: &blapose_client::AdjustedFrame| {
        let lifted = f.lifted.as_ref().expect("lifted").pose;
        assert!(
            pose_diff(&lifted, &want_lifted[t]) < LIFT_TOLERANCE,
            "frame {t}"
        );
        assert!(pose_diff(&f.pose, &want_poses[t]) < TOLERANCE, "frame {t}");
    };

    let mut first = client
        .open_session_with(seq.input_format, &lifting())
        .await
        .expect("open");
    for t in 0..6 {
        let f = first.adjust(&seq.keypoints_frame(t)).await.expect("frame");
        check(t, &f);
    }
    let id = first.detach(Duration::from_secs(5)).await;
    let mut resumed = client.resume_session(&id).await.expect("resume");
    assert!(resumed.info().resumed);
    assert_eq!(resumed.info().frames_seen, 6);
    assert_eq!(resumed.info().lifter.as_deref(), Some(TEST_LIFTER_NAME));
    // The window still holds frames 0..6: frame 6 onwards continue the
    // stream (a fresh window would pad with frame 6 instead).
    for t in 6..seq.len() {
        let f = resumed
            .adjust(&seq.keypoints_frame(t))
            .await
            .expect("frame");
        check(t, &f);
    }
    let summary = resumed.close().await.expect("close");
    assert_eq!(summary.frames_seen, seq.len() as u64);
    server.shutdown().await;
}

#[tokio::test]
async fn model_info_describes_the_server_lifter() {
    let server = TestServer::start(lifter_config()).await;
    let client = server.client().await;
    let info = client.model_info().await.expect("info");
    let l = info.lifter.expect("a lifter");
    let lifter = test_lifter();
    assert_eq!(l.name, TEST_LIFTER_NAME);
    assert_eq!(l.receptive_field, 9);
    assert!(l.causal);
    assert_eq!(l.parameter_count, lifter.params() as u64);
    assert_eq!(
        l.weights_source,
        lifter_weights_file().display().to_string()
    );
    assert_eq!(l.weights_sha256.len(), 64);
    assert_eq!(l.metadata["train_steps"], "0");
    assert_eq!(l.metadata["keypoint_layout"], "h36m17");
    assert!(
        l.metadata["training_data"].contains("random weights"),
        "{:?}",
        l.metadata
    );
    assert!(
        l.metadata["arch"].contains("\"videopose\""),
        "{:?}",
        l.metadata
    );
    // The bone-length models are described as before: the default pair and
    // the camera-aware pair.
    assert_eq!(info.models.len(), 4);
    assert_eq!(info.models.iter().filter(|m| m.camera_aware).count(), 2);
    let text = format!("{}", client.model_info().await.expect("info"));
    assert!(text.contains(TEST_LIFTER_NAME), "{text}");
    server.shutdown().await;
}

#[tokio::test]
async fn a_lifter_file_that_cannot_be_served_stops_the_server_at_start_up() {
    let cases = [
        (centred_lifter_weights_file().to_path_buf(), "centred"),
        (weights_dir().join("gru.safetensors"), "blapose_lifter"),
        (
            weights_dir().join("no-such-lifter.safetensors"),
            "cannot read",
        ),
    ];
    for (path, why) in cases {
        let config = blapose_server::ServerConfig {
            lifter: Some(blapose_server::config::WeightsSource::File(path.clone())),
            ..test_config()
        };
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        match blapose_server::spawn(config, listener).await {
            Ok(handle) => {
                let _ = handle.shutdown().await;
                panic!("{} was served", path.display());
            }
            Err(e) => {
                let text = e.to_string();
                assert!(text.contains("--lifter-weights"), "{text}");
                assert!(text.contains(&path.display().to_string()), "{text}");
                assert!(text.contains(why), "{text}");
            }
        }
    }
}

/// `replay --server-lifter` against a server without a lifter stops at the
/// open with the server's INVALID_ARGUMENT; it never falls back to sending
/// the file's poses.
#[tokio::test]
async fn a_replay_with_the_server_lifter_on_a_server_without_one_fails_cleanly() {
    let server = TestServer::start(test_config()).await;
    let client = server.client().await;
    let seq = synthetic_sequence(24, 5, KeypointLayout::H36m17);
    let options = ReplayOptions {
        server_lifter: true,
        ..ReplayOptions::default()
    };
    match replay(&client, &seq, &options, |_| {}).await {
        Err(ClientError::Status(s)) => assert_eq!(s.code(), Code::InvalidArgument),
        other => panic!("expected INVALID_ARGUMENT, got {other:?}"),
    }
    server.shutdown().await;
}

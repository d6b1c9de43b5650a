//! Every error the server defines, with hostile input: the right status
//! code, a message that says what is wrong, and no damage to the session or
//! to other sessions.

use blapose_client::{ClientError, FrameInput, KeypointLayout, SessionEvent, ToProto};
use blapose_proto::v1 as pb;
use blapose_proto::v1::stream_request::Kind;
use blapose_tests::{
    lengths_diff, pose_diff, synthetic_sequence, test_config, Reference, TestServer, TOLERANCE,
};
use tonic::Code;

fn status_of<T: std::fmt::Debug>(result: Result<T, ClientError>) -> tonic::Status {
    match result {
        Err(ClientError::Status(s)) => s,
        other => panic!("expected a gRPC status, got {other:?}"),
    }
}

/// The client pose of a frame built from a replay sequence.
fn pose(f: &mut FrameInput) -> &mut blapose_core::Pose {
    f.pose_3d.as_mut().expect("a frame with a client pose")
}

fn open_request(
    layout: i32,
    coordinates: Option<pb::input_format::Coordinates>,
    model: pb::Model,
) -> pb::StreamRequest {
    pb::StreamRequest {
        kind: Some(Kind::Open(pb::OpenSession {
            input_format: Some(pb::InputFormat {
                layout,
                coordinates,
            }),
            model: model as i32,
            client_label: "hostile".into(),
            server_lifter: false,
            camera: None,
            session_tokens: false,
            subject: None,
            motion: None,
        })),
    }
}

fn image(width: u32, height: u32) -> Option<pb::input_format::Coordinates> {
    Some(pb::input_format::Coordinates::ImageSize(pb::ImageSize {
        width,
        height,
    }))
}

#[tokio::test]
async fn bad_opens_and_first_messages_end_the_stream_with_the_right_code() {
    let server = TestServer::start(test_config()).await;
    let client = server.client().await;
    let h36m = pb::KeypointLayout::H36m17 as i32;
    let frame = pb::StreamRequest {
        kind: Some(Kind::Frame(pb::Frame {
            frame_index: 0,
            keypoints_2d: vec![1.0; 34],
            confidence: vec![],
            pose_3d: vec![0.1; 51],
        })),
    };
    let cases: Vec<(&str, pb::StreamRequest, Code)> = vec![
        ("frame before open", frame, Code::FailedPrecondition),
        (
            "close before open",
            pb::StreamRequest {
                kind: Some(Kind::Close(pb::CloseSession {})),
            },
            Code::FailedPrecondition,
        ),
        (
            "empty request",
            pb::StreamRequest { kind: None },
            Code::InvalidArgument,
        ),
        (
            "zero width",
            open_request(h36m, image(0, 1000), pb::Model::Unspecified),
            Code::InvalidArgument,
        ),
        (
            "zero height",
            open_request(h36m, image(1000, 0), pb::Model::Unspecified),
            Code::InvalidArgument,
        ),
        (
            "unspecified layout",
            open_request(0, image(1000, 1000), pb::Model::Unspecified),
            Code::InvalidArgument,
        ),
        (
            "unknown layout",
            open_request(99, image(1000, 1000), pb::Model::Unspecified),
            Code::InvalidArgument,
        ),
        (
            "negative layout",
            open_request(-1, image(1000, 1000), pb::Model::Unspecified),
            Code::InvalidArgument,
        ),
        (
            "no coordinates",
            open_request(h36m, None, pb::Model::Unspecified),
            Code::InvalidArgument,
        ),
        (
            "normalized = false",
            open_request(
                h36m,
                Some(pb::input_format::Coordinates::Normalized(false)),
                pb::Model::Unspecified,
            ),
            Code::InvalidArgument,
        ),
        (
            "bigru on a stream",
            open_request(h36m, image(1000, 1000), pb::Model::OfflineBigru),
            Code::InvalidArgument,
        ),
        (
            "no input format",
            pb::StreamRequest {
                kind: Some(Kind::Open(pb::OpenSession::default())),
            },
            Code::InvalidArgument,
        ),
        (
            "unknown session id",
            pb::StreamRequest {
                kind: Some(Kind::Resume(pb::ResumeSession {
                    session_id: "0123456789abcdef0123456789abcdef".into(),
                    session_token: Vec::new(),
                    session_tokens: false,
                })),
            },
            Code::NotFound,
        ),
    ];
    for (what, first, want) in cases {
        let status = status_of(client.open_raw(first).await);
        assert_eq!(status.code(), want, "{what}: {}", status.message());
        assert!(!status.message().is_empty(), "{what}: empty message");
    }
    // The server is unharmed: a proper open still works.
    let ok = client
        .open_raw(open_request(h36m, image(1000, 1000), pb::Model::OnlineGru))
        .await;
    assert!(ok.is_ok(), "{ok:?}");
    server.shutdown().await;
}

#[tokio::test]
async fn a_second_open_on_a_stream_is_failed_precondition() {
    let server = TestServer::start(test_config()).await;
    let client = server.client().await;
    let seq = synthetic_sequence(31, 1, KeypointLayout::H36m17);
    let session = client
        .open_session(seq.input_format, None)
        .await
        .expect("open");
    let (_, sender, mut receiver) = session.split();
    sender
        .send_raw(open_request(1, image(1000, 1000), pb::Model::Unspecified))
        .await
        .expect("send");
    let err = receiver.next().await.expect_err("stream ends");
    assert_eq!(err.code(), Some(Code::FailedPrecondition), "{err}");
    server.shutdown().await;
}

/// Bad frames are answered in order with a FrameError and leave the session
/// exactly as it was.
#[tokio::test]
async fn bad_frames_are_rejected_in_band_and_do_not_corrupt_the_session() {
    let server = TestServer::start(test_config()).await;
    let client = server.client().await;
    let reference = Reference::new();
    let seq = synthetic_sequence(32, 2, KeypointLayout::H36m17);
    let want = reference.online(&seq);

    let good = |t: usize| seq.frame(t);
    let with = |f: &dyn Fn(&mut FrameInput)| {
        let mut frame = seq.frame(1);
        frame.frame_index = 100;
        f(&mut frame);
        frame
    };
    let bad: Vec<(&str, FrameInput)> = vec![
        (
            "16 keypoints for h36m17",
            with(&|f| f.keypoints_2d.truncate(16)),
        ),
        ("18 keypoints", with(&|f| f.keypoints_2d.push([1.0, 2.0]))),
        ("NaN keypoint", with(&|f| f.keypoints_2d[3][1] = f32::NAN)),
        (
            "+Inf keypoint",
            with(&|f| f.keypoints_2d[0][0] = f32::INFINITY),
        ),
        ("-Inf pose", with(&|f| pose(f)[7][2] = f32::NEG_INFINITY)),
        ("NaN pose", with(&|f| pose(f)[16][0] = f32::NAN)),
        (
            "zero-length bone",
            with(&|f| {
                let p = pose(f);
                p[2] = p[1];
            }),
        ),
        ("missing pose", with(&|f| f.pose_3d = None)),
        ("huge coordinate", with(&|f| f.keypoints_2d[5][0] = 3.0e38)),
        (
            "wrong confidence count",
            with(&|f| f.confidence = vec![1.0; 5]),
        ),
        (
            "negative confidence",
            with(&|f| f.confidence = vec![-1.0; 17]),
        ),
        (
            "NaN confidence",
            with(&|f| f.confidence = vec![f32::NAN; 17]),
        ),
    ];

    let session = client
        .open_session(seq.input_format, None)
        .await
        .expect("open");
    let (_, sender, mut receiver) = session.split();
    sender.send(&good(0)).await.expect("send");
    for (_, frame) in &bad {
        sender.send(frame).await.expect("send");
    }
    // Raw frames the typed API cannot express: a 50-value pose.
    let mut short_pose = seq.frame(1).to_proto();
    short_pose.pose_3d.pop();
    short_pose.frame_index = 200;
    sender
        .send_raw(pb::StreamRequest {
            kind: Some(Kind::Frame(short_pose)),
        })
        .await
        .expect("send");
    sender.send(&good(1)).await.expect("send");
    sender.close().await.expect("close");

    match receiver.next().await.expect("answer") {
        Some(SessionEvent::Adjusted(f)) => assert_eq!(f.frames_seen, 1),
        other => panic!("frame 0: {other:?}"),
    }
    for (what, frame) in &bad {
        match receiver.next().await.expect("answer") {
            Some(SessionEvent::Rejected(r)) => {
                assert_eq!(r.code, Code::InvalidArgument, "{what}: {}", r.message);
                assert_eq!(r.frame_index, frame.frame_index, "{what}");
                assert!(!r.message.is_empty(), "{what}");
            }
            other => panic!("{what}: expected a rejection, got {other:?}"),
        }
    }
    match receiver.next().await.expect("answer") {
        Some(SessionEvent::Rejected(r)) => {
            assert_eq!(
                (r.code, r.frame_index),
                (Code::InvalidArgument, 200),
                "{}",
                r.message
            );
            assert!(
                r.message.contains("50"),
                "message should name the count: {}",
                r.message
            );
        }
        other => panic!("short pose: {other:?}"),
    }
    // The good frame after all that is exactly what a clean session gives.
    match receiver.next().await.expect("answer") {
        Some(SessionEvent::Adjusted(f)) => {
            assert_eq!(f.frames_seen, 2, "rejected frames must not count");
            assert!(pose_diff(&f.pose, &want.0[1]) < TOLERANCE);
            assert!(lengths_diff(&f.bone_lengths, &want.1[1]) < TOLERANCE);
        }
        other => panic!("frame 1: {other:?}"),
    }
    match receiver.next().await.expect("answer") {
        Some(SessionEvent::Closed(s)) => assert_eq!(s.frames_seen, 2),
        other => panic!("close: {other:?}"),
    }
    server.shutdown().await;
}

/// A session flooding the server with garbage does not disturb another.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_hostile_session_does_not_affect_a_good_one() {
    let server = TestServer::start(test_config()).await;
    let client = server.client().await;
    let reference = Reference::new();
    let seq = synthetic_sequence(33, 50, KeypointLayout::Coco17);
    let want = reference.online(&seq);

    let hostile_client = client.clone();
    let hostile = tokio::spawn(async move {
        let seq = synthetic_sequence(34, 1, KeypointLayout::Coco17);
        let session = hostile_client
            .open_session(seq.input_format, None)
            .await
            .expect("open");
        let (_, sender, mut receiver) = session.split();
        let mut frame = seq.frame(0);
        for t in 0..200u64 {
            frame.frame_index = t;
            frame.keypoints_2d[(t % 17) as usize][0] =
                if t % 2 == 0 { f32::NAN } else { f32::INFINITY };
            sender.send(&frame).await.expect("send");
        }
        sender.close().await.expect("close");
        let mut rejected = 0;
        while let Some(event) = receiver.next().await.expect("ends OK") {
            if let SessionEvent::Rejected(r) = event {
                assert_eq!(r.code, Code::InvalidArgument);
                rejected += 1;
            }
        }
        rejected
    });
    let good = blapose_client::replay(
        &client,
        &seq,
        &blapose_client::ReplayOptions::default(),
        |_| {},
    )
    .await
    .expect("good session");
    for t in 0..seq.len() {
        assert!(
            pose_diff(&good.adjusted[t], &want.0[t]) < TOLERANCE,
            "frame {t}"
        );
    }
    assert_eq!(hostile.await.expect("hostile task"), 200);
    server.shutdown().await;
}

#[tokio::test]
async fn oversize_messages_are_out_of_range() {
    let config = blapose_server::ServerConfig {
        max_message_bytes: 64 * 1024,
        ..test_config()
    };
    let server = TestServer::start(config).await;
    let client = server.client().await;

    // Offline: 1,000 frames is ~340 KB, over the 64 KiB limit.
    let seq = synthetic_sequence(35, 1000, KeypointLayout::H36m17);
    let err = blapose_client::adjust_offline(&client, &seq, blapose_client::ModelKind::BiGru)
        .await
        .expect_err("too big");
    assert_eq!(err.code(), Some(Code::OutOfRange), "{err}");
    // The error says which limit and what to do (not only tonic's "decoded
    // message length too large").
    let text = err.to_string();
    assert!(text.contains("1000-frame sequence"), "{text}");
    assert!(text.contains("the limit is: 65536"), "{text}");
    assert!(text.contains("--max-message-bytes"), "{text}");
    assert!(text.contains("blapose-client replay"), "{text}");
    // A smaller one on the same connection is fine.
    let small = synthetic_sequence(36, 50, KeypointLayout::H36m17);
    blapose_client::adjust_offline(&client, &small, blapose_client::ModelKind::BiGru)
        .await
        .expect("within the limit");

    // Streaming: one frame with 100,000 keypoint values ends the stream.
    let session = client
        .open_session(small.input_format, None)
        .await
        .expect("open");
    let (_, sender, mut receiver) = session.split();
    let mut huge = small.frame(0).to_proto();
    huge.keypoints_2d = vec![1.0; 100_000];
    sender
        .send_raw(pb::StreamRequest {
            kind: Some(Kind::Frame(huge)),
        })
        .await
        .expect("send");
    let err = receiver.next().await.expect_err("stream ends");
    assert_eq!(err.code(), Some(Code::OutOfRange), "{err}");
    server.shutdown().await;
}

#[tokio::test]
async fn bad_offline_requests_are_invalid_argument() {
    let server = TestServer::start(test_config()).await;
    let client = server.client().await;
    let seq = synthetic_sequence(37, 10, KeypointLayout::H36m17);
    let good = pb::AdjustSequenceRequest {
        input_format: Some(
            blapose_client::InputFormat::pixels(KeypointLayout::H36m17, 1000, 1002).into(),
        ),
        model: pb::Model::OfflineBigru as i32,
        num_frames: 10,
        keypoints_2d: seq.keypoints_2d.clone(),
        confidence: vec![],
        poses_3d: seq.pose_3d.as_flattened().as_flattened().to_vec(),
        camera: None,
        subject: None,
        motion: None,
    };
    client
        .adjust_sequence_raw(good.clone())
        .await
        .expect("good request");
    let mut cases: Vec<(&str, pb::AdjustSequenceRequest)> = Vec::new();
    cases.push((
        "frame count mismatch",
        pb::AdjustSequenceRequest {
            num_frames: 11,
            ..good.clone()
        },
    ));
    cases.push((
        "zero frames",
        pb::AdjustSequenceRequest {
            num_frames: 0,
            keypoints_2d: vec![],
            poses_3d: vec![],
            ..good.clone()
        },
    ));
    let mut nan = good.clone();
    nan.keypoints_2d[100] = f32::NAN;
    cases.push(("NaN keypoint", nan));
    let mut inf = good.clone();
    inf.poses_3d[51 * 4 + 2] = f32::INFINITY;
    cases.push(("Inf pose", inf));
    cases.push((
        "no input format",
        pb::AdjustSequenceRequest {
            input_format: None,
            ..good.clone()
        },
    ));
    let mut layout = good.clone();
    layout.input_format = Some(pb::InputFormat {
        layout: 42,
        ..good.input_format.expect("format")
    });
    cases.push(("unknown layout", layout));
    let mut size = good.clone();
    size.input_format = Some(pb::InputFormat {
        coordinates: image(0, 0),
        ..good.input_format.expect("format")
    });
    cases.push(("zero image size", size));
    for (what, req) in cases {
        let status = status_of(client.adjust_sequence_raw(req).await);
        assert_eq!(
            status.code(),
            Code::InvalidArgument,
            "{what}: {}",
            status.message()
        );
    }
    server.shutdown().await;
}

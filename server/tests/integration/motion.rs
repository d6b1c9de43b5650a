//! The offline motion stage through the real server and its embedded
//! weights: a request without the option is answered exactly as before,
//! one with it gets smoothed poses with the same lengths and a pelvis
//! placed where the person walks, and a bad frame rate is refused.

use blapose_proto::v1 as pb;
use pb::pose_adjustment_client::PoseAdjustmentClient;
use tonic::Code;

/// Image size and focal length of the synthetic camera (pixels): the focal
/// length the server assumes without a calibration (the larger side).
const SIZE: u32 = 1000;
const FOCAL: f32 = 1000.0;
const FRAMES: usize = 100;

/// A standing person (pelvis at the origin, y down), metres.
fn body() -> [[f32; 3]; 17] {
    [
        [0.0, 0.0, 0.0],
        [-0.13, 0.0, 0.0],
        [-0.13, 0.45, 0.02],
        [-0.13, 0.88, 0.0],
        [0.13, 0.0, 0.0],
        [0.13, 0.45, 0.02],
        [0.13, 0.88, 0.0],
        [0.0, -0.23, 0.0],
        [0.0, -0.48, 0.0],
        [0.0, -0.58, -0.03],
        [0.0, -0.7, 0.0],
        [0.18, -0.45, 0.0],
        [0.2, -0.18, 0.02],
        [0.21, 0.07, 0.05],
        [-0.18, -0.45, 0.0],
        [-0.2, -0.18, 0.02],
        [-0.21, 0.07, 0.05],
    ]
}

/// The pelvis at frame `t`: walking 2 m to the right, 5 m away (the lifted
/// poses, root-relative, jitter; the keypoints do not).
fn root(t: usize) -> [f32; 3] {
    [-1.0 + 2.0 * t as f32 / (FRAMES - 1) as f32, 0.0, 5.0]
}

fn request(motion: Option<pb::MotionOptions>) -> pb::AdjustSequenceRequest {
    let mut keypoints = Vec::new();
    let mut poses = Vec::new();
    for t in 0..FRAMES {
        let r = root(t);
        for (j, p) in body().iter().enumerate() {
            let q = [p[0] + r[0], p[1] + r[1], p[2] + r[2]];
            keypoints.push(FOCAL * q[0] / q[2] + SIZE as f32 / 2.0);
            keypoints.push(FOCAL * q[1] / q[2] + SIZE as f32 / 2.0);
            // The pelvis stays put: the stage keeps the pose's own root.
            let wobble = match j {
                0 => 0.0,
                _ if (t + j) % 2 == 0 => 0.01,
                _ => -0.01,
            };
            poses.extend([p[0] + wobble, p[1], p[2] - wobble]);
        }
    }
    pb::AdjustSequenceRequest {
        input_format: Some(pb::InputFormat {
            layout: pb::KeypointLayout::H36m17 as i32,
            coordinates: Some(pb::input_format::Coordinates::ImageSize(pb::ImageSize {
                width: SIZE,
                height: SIZE,
            })),
        }),
        num_frames: FRAMES as u32,
        keypoints_2d: keypoints,
        poses_3d: poses,
        motion,
        ..Default::default()
    }
}

fn length(p: &[f32], a: usize, b: usize) -> f32 {
    (0..3)
        .map(|i| (p[3 * a + i] - p[3 * b + i]).powi(2))
        .sum::<f32>()
        .sqrt()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn offline_motion_places_the_walker_and_keeps_the_lengths() {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let config = blapose_server::ServerConfig {
        metrics_addr: None,
        ..Default::default()
    };
    let server = blapose_server::spawn(config, listener).await.unwrap();
    let mut c = PoseAdjustmentClient::connect(format!("http://{}", server.local_addr()))
        .await
        .unwrap();
    let plain = c.adjust_sequence(request(None)).await.unwrap().into_inner();
    let off = pb::MotionOptions {
        enabled: false,
        frame_rate_hz: 30.0,
    };
    let disabled = c
        .adjust_sequence(request(Some(off)))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(plain, disabled, "a disabled stage changes nothing");
    assert!(plain.root_positions.is_empty() && plain.world_poses_3d.is_empty());

    let on = pb::MotionOptions {
        enabled: true,
        frame_rate_hz: 0.0,
    };
    let moved = c
        .adjust_sequence(request(Some(on)))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(
        moved.bone_lengths, plain.bone_lengths,
        "lengths are the model's"
    );
    assert!(moved.focal_assumed);
    assert_eq!(moved.root_positions.len(), FRAMES * 3);
    // Every pose has exactly the answered lengths (thigh, forearm).
    for (pose, l) in moved
        .adjusted_poses_3d
        .chunks(51)
        .zip(moved.bone_lengths.chunks(16))
    {
        assert!((length(pose, 1, 2) - l[1]).abs() < 1e-4);
        assert!((length(pose, 15, 16) - l[15]).abs() < 1e-4);
    }
    // The smoothed poses move less from frame to frame than the input.
    let speed = |poses: &[f32]| -> f32 {
        poses
            .chunks(51)
            .collect::<Vec<_>>()
            .windows(2)
            .map(|w| (0..51).map(|i| (w[1][i] - w[0][i]).abs()).sum::<f32>())
            .sum()
    };
    let (smooth, raw) = (
        speed(&moved.adjusted_poses_3d),
        speed(&plain.adjusted_poses_3d),
    );
    assert!(smooth < 0.2 * raw, "{smooth} vs {raw}");
    // The pelvis walks about 2 m to the right at about 5 m (the model's
    // lengths, not the synthetic body's, set the scale).
    let first = &moved.root_positions[..3];
    let last = &moved.root_positions[(FRAMES - 1) * 3..];
    let scale = first[2] / 5.0;
    assert!((0.75..1.33).contains(&scale), "depth {}", first[2]);
    assert!(
        ((last[0] - first[0]) / scale - 2.0).abs() < 0.2,
        "{first:?} -> {last:?}"
    );
    assert!((last[2] - first[2]).abs() < 0.1 * first[2]);

    for bad in [-1.0, f32::NAN, 5000.0] {
        let rate = pb::MotionOptions {
            enabled: true,
            frame_rate_hz: bad,
        };
        let err = c.adjust_sequence(request(Some(rate))).await.unwrap_err();
        assert_eq!(err.code(), Code::InvalidArgument, "{bad}");
        assert!(err.message().contains("frame_rate_hz"), "{}", err.message());
    }
    server.shutdown().await.unwrap();
}

/// One stream of the walker's frames `range` on a session opened (or
/// resumed) with `first`; the answers in order, and the session's id and
/// latest token when `token_after` frames are answered.
async fn stream(
    c: &mut PoseAdjustmentClient<tonic::transport::Channel>,
    first: pb::StreamRequest,
    frames: &[(Vec<f32>, Vec<f32>)],
    range: std::ops::Range<usize>,
    token_after: Option<usize>,
) -> (Vec<pb::AdjustedFrame>, String, Vec<u8>) {
    use pb::stream_request::Kind as Req;
    use pb::stream_response::Kind as Resp;
    let (tx, rx) = tokio::sync::mpsc::channel(8);
    tx.send(first).await.unwrap();
    let mut answers = c
        .stream(tokio_stream::wrappers::ReceiverStream::new(rx))
        .await
        .unwrap()
        .into_inner();
    let id = match answers.message().await.unwrap().and_then(|r| r.kind) {
        Some(Resp::Opened(o)) => o.session_id,
        other => panic!("{other:?}"),
    };
    let (mut out, mut token) = (Vec::new(), Vec::new());
    for t in range {
        let (keypoints, pose) = frames[t].clone();
        let frame = pb::Frame {
            frame_index: t as u64,
            keypoints_2d: keypoints,
            pose_3d: pose,
            confidence: vec![],
        };
        tx.send(pb::StreamRequest {
            kind: Some(Req::Frame(frame)),
        })
        .await
        .unwrap();
        loop {
            match answers.message().await.unwrap().and_then(|r| r.kind) {
                Some(Resp::Frame(f)) => {
                    out.push(f);
                    break;
                }
                Some(Resp::Token(_)) => continue,
                other => panic!("{other:?}"),
            }
        }
        if token_after == Some(out.len()) {
            tx.send(pb::StreamRequest {
                kind: Some(Req::TokenRequest(pb::TokenRequest {})),
            })
            .await
            .unwrap();
            token = match answers.message().await.unwrap().and_then(|r| r.kind) {
                Some(Resp::Token(tk)) => tk.token,
                other => panic!("{other:?}"),
            };
        }
    }
    (out, id, token)
}

/// The walker's frames, `(keypoints, pose)`, from the offline request.
fn walker_frames() -> Vec<(Vec<f32>, Vec<f32>)> {
    let r = request(None);
    r.keypoints_2d
        .chunks(34)
        .zip(r.poses_3d.chunks(51))
        .map(|(k, p)| (k.to_vec(), p.to_vec()))
        .collect()
}

fn open(motion: bool) -> pb::StreamRequest {
    pb::StreamRequest {
        kind: Some(pb::stream_request::Kind::Open(pb::OpenSession {
            input_format: request(None).input_format,
            session_tokens: true,
            motion: motion.then_some(pb::MotionOptions {
                enabled: true,
                frame_rate_hz: 50.0,
            }),
            ..Default::default()
        })),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn streamed_motion_is_causal_keeps_lengths_and_continues_bit_exactly_from_a_token() {
    let key = blapose_server::token::SessionKey::new(&[7u8; 32]).unwrap();
    let config = || blapose_server::ServerConfig {
        metrics_addr: None,
        session_key: Some(key.clone()),
        ..Default::default()
    };
    let mut servers = Vec::new();
    let mut clients = Vec::new();
    for _ in 0..2 {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let server = blapose_server::spawn(config(), listener).await.unwrap();
        clients.push(
            PoseAdjustmentClient::connect(format!("http://{}", server.local_addr()))
                .await
                .unwrap(),
        );
        servers.push(server);
    }
    let frames = walker_frames();
    let (plain, _, _) = stream(&mut clients[0], open(false), &frames, 0..FRAMES, None).await;
    assert!(plain
        .iter()
        .all(|f| f.root_position.is_empty() && !f.focal_assumed));
    let (moved, id, token) =
        stream(&mut clients[0], open(true), &frames, 0..FRAMES, Some(40)).await;
    // Lengths are the session's, exactly those of the plain session; the
    // poses have them, and move less.
    for (m, p) in moved.iter().zip(&plain) {
        assert_eq!(m.bone_lengths, p.bone_lengths);
        assert!((length(&m.adjusted_pose_3d, 1, 2) - m.bone_lengths[1]).abs() < 1e-4);
        assert_eq!(m.root_position.len(), 3);
        assert!(m.focal_assumed);
    }
    let travel = moved[FRAMES - 1].root_position[0] - moved[10].root_position[0];
    assert!(travel > 1.0, "the pelvis moved {travel} m");
    // Causal: other frames after frame 60 leave the answers up to it alone.
    let mut changed = frames.clone();
    for f in &mut changed[61..] {
        for v in &mut f.1[3..] {
            *v += 0.05;
        }
    }
    let (other, _, _) = stream(&mut clients[0], open(true), &changed, 0..FRAMES, None).await;
    assert_eq!(other[..=60], moved[..=60]);
    assert_ne!(other[61..], moved[61..]);
    // A second server restores the session from the token taken after 40
    // frames and answers the rest exactly as the first did.
    let resume = pb::StreamRequest {
        kind: Some(pb::stream_request::Kind::Resume(pb::ResumeSession {
            session_id: id,
            session_token: token,
            session_tokens: true,
        })),
    };
    let (rest, _, _) = stream(&mut clients[1], resume, &frames, 40..FRAMES, None).await;
    assert_eq!(rest[..], moved[40..]);
    for s in servers {
        s.shutdown().await.unwrap();
    }
}

//! Session tokens (portable session state) over real gRPC with the real
//! embedded models: a session taken at frame k on one server and resumed
//! from its token on a second server with the same key continues exactly,
//! every answer equal BIT FOR BIT to an uninterrupted run's on one server
//! (default, camera-aware and server-lifter sessions, their frames losing
//! joints as a detector does, so the held joints travel too); and every
//! bad token is refused with the documented status, no server needed
//! beyond it. Missing joints themselves: their coordinates are never read,
//! and a frame without a detected joint changes nothing but the count.

use crate::support;

use std::path::PathBuf;
use std::time::Duration;

use blapose_proto::v1 as pb;
use blapose_server::token::{PortableState, SessionKey};
use blapose_server::{ServerConfig, WeightsSource};
use pb::pose_adjustment_client::PoseAdjustmentClient;
use pb::stream_request::Kind as Req;
use pb::stream_response::Kind as Resp;
use support::start;
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tonic::transport::Channel;
use tonic::Code;

const KEY: &str = "hex:3f1c9a0b7d2e4f6a8b1c3d5e7f9a0b2c4d6e8f0a1b3c5d7e9f1a2b4c6d8e0f1a";
const N: u64 = 57;
const K: u64 = 30;
const EVERY: u64 = 10;

fn models(file: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../models")
        .join(file)
}

fn config(key: Option<&str>) -> ServerConfig {
    ServerConfig {
        session_key: key.map(|k| SessionKey::parse(k).unwrap()),
        token_every: EVERY,
        lifter: Some(WeightsSource::File(models(
            "lifter_videopose27_causal.safetensors",
        ))),
        session_ttl: Duration::from_secs(30),
        ..ServerConfig::default()
    }
}

/// A 3D pose (metres, camera frame) that moves a little with `t`.
fn pose(t: u64) -> [[f32; 3]; 17] {
    let base: [[f32; 3]; 17] = [
        [0.0, 0.0, 4.0],
        [-0.13, 0.0, 4.0],
        [-0.13, 0.45, 4.0],
        [-0.13, 0.88, 4.0],
        [0.13, 0.0, 4.0],
        [0.13, 0.45, 4.0],
        [0.13, 0.88, 4.0],
        [0.0, -0.25, 4.0],
        [0.0, -0.5, 4.0],
        [0.0, -0.6, 4.0],
        [0.0, -0.72, 4.0],
        [0.17, -0.5, 4.0],
        [0.2, -0.22, 4.0],
        [0.22, 0.02, 4.0],
        [-0.17, -0.5, 4.0],
        [-0.2, -0.22, 4.0],
        [-0.22, 0.02, 4.0],
    ];
    let t = t as f32;
    std::array::from_fn(|j| {
        let [x, y, z] = base[j];
        let j = j as f32;
        [
            x + 0.03 * (0.3 * t + j).sin(),
            y + 0.02 * (0.2 * t + 0.5 * j).cos(),
            z + 0.05 * (0.1 * t + j).sin(),
        ]
    })
}

/// Frame `t`, with a detector's gaps: every third frame loses one joint
/// (confidence 0), and a client-pose session's frames 5 and 35 lose every
/// joint ([`NO_JOINT`]); a lost joint's coordinates are garbage drawn
/// from `garbage` (NaN for odd seeds).
fn frame_with(t: u64, lifting: bool, garbage: u64) -> pb::StreamRequest {
    let p = pose(t);
    // Pixels of a 1000 x 1000 image, focal length 1150, centred.
    let mut keypoints: Vec<f32> = p
        .iter()
        .flat_map(|[x, y, z]| [1150.0 * x / z + 500.0, 1150.0 * y / z + 500.0])
        .collect();
    let mut confidence = vec![0.9; 17];
    if t.is_multiple_of(3) {
        confidence[(t as usize * 7) % 17] = 0.0;
    }
    if !lifting && NO_JOINT.contains(&t) {
        confidence = vec![0.05; 17];
    }
    for (j, &c) in confidence.iter().enumerate() {
        if c < 0.1 {
            let g = if garbage % 2 == 1 {
                f32::NAN
            } else {
                (garbage as f32 * 37.0 + j as f32 * 11.0) % 1000.0
            };
            keypoints[2 * j] = g;
            keypoints[2 * j + 1] = -g;
        }
    }
    pb::StreamRequest {
        kind: Some(Req::Frame(pb::Frame {
            frame_index: t,
            keypoints_2d: keypoints,
            confidence,
            pose_3d: if lifting {
                vec![]
            } else {
                p.iter().flatten().copied().collect()
            },
        })),
    }
}

/// Frames of a client-pose session without a detected joint.
const NO_JOINT: [u64; 2] = [5, 35];

fn frame(t: u64, lifting: bool) -> pb::StreamRequest {
    frame_with(t, lifting, 0)
}

fn calibration() -> pb::CameraCalibration {
    let tilt = 12f32.to_radians();
    pb::CameraCalibration {
        up: vec![0.0, -tilt.cos(), -tilt.sin()],
        focal_x: 1150.0,
        focal_y: 1150.0,
        principal_x: 500.0,
        principal_y: 500.0,
        image_size: None,
        height: 1.6,
        distortion: vec![],
    }
}

#[derive(Debug, Clone, Copy)]
enum Kind {
    Plain,
    Camera,
    Lifter,
    Subject,
}

/// The subject of `Kind::Subject` sessions.
const SUBJECT: pb::Subject = pb::Subject {
    height_m: 1.81,
    sex: pb::Sex::Male as i32,
};

fn open(kind: Kind) -> pb::StreamRequest {
    pb::StreamRequest {
        kind: Some(Req::Open(pb::OpenSession {
            input_format: Some(pb::InputFormat {
                layout: pb::KeypointLayout::H36m17 as i32,
                coordinates: Some(pb::input_format::Coordinates::ImageSize(pb::ImageSize {
                    width: 1000,
                    height: 1000,
                })),
            }),
            model: 0,
            client_label: format!("{kind:?}"),
            server_lifter: matches!(kind, Kind::Lifter),
            camera: matches!(kind, Kind::Camera).then(calibration),
            session_tokens: true,
            subject: matches!(kind, Kind::Subject).then_some(SUBJECT),
            motion: None,
        })),
    }
}

fn resume(id: &str, token: &[u8]) -> pb::StreamRequest {
    pb::StreamRequest {
        kind: Some(Req::Resume(pb::ResumeSession {
            session_id: id.to_string(),
            session_token: token.to_vec(),
            session_tokens: true,
        })),
    }
}

fn token_request() -> pb::StreamRequest {
    pb::StreamRequest {
        kind: Some(Req::TokenRequest(pb::TokenRequest {})),
    }
}

/// Run `requests` on one stream; every response until the stream ends
/// (or its status).
async fn exchange(
    client: &mut PoseAdjustmentClient<Channel>,
    requests: Vec<pb::StreamRequest>,
) -> (Vec<Resp>, Result<(), tonic::Status>) {
    let (tx, rx) = mpsc::channel(requests.len() + 1);
    for r in requests {
        tx.send(r).await.unwrap();
    }
    drop(tx);
    let mut inbound = match client.stream(ReceiverStream::new(rx)).await {
        Ok(r) => r.into_inner(),
        Err(status) => return (vec![], Err(status)),
    };
    let mut out = Vec::new();
    loop {
        match tokio::time::timeout(Duration::from_secs(60), inbound.message())
            .await
            .expect("an answer within 60 s")
        {
            Ok(Some(m)) => out.extend(m.kind),
            Ok(None) => return (out, Ok(())),
            Err(status) => return (out, Err(status)),
        }
    }
}

fn opened(r: &[Resp]) -> &pb::SessionOpened {
    match r.first() {
        Some(Resp::Opened(o)) => o,
        other => panic!("expected SessionOpened, got {other:?}"),
    }
}

fn frames(r: &[Resp]) -> Vec<&pb::AdjustedFrame> {
    r.iter()
        .filter_map(|m| match m {
            Resp::Frame(f) => Some(f),
            Resp::Error(e) => panic!("frame refused: {e:?}"),
            _ => None,
        })
        .collect()
}

fn tokens(r: &[Resp]) -> Vec<&pb::SessionToken> {
    r.iter()
        .filter_map(|m| match m {
            Resp::Token(t) => Some(t),
            _ => None,
        })
        .collect()
}

/// Two tokens of the same state: equal but for their issue times (and the
/// chain origin a restored session's tokens carry).
fn assert_same_state(a: &[u8], b: &[u8]) {
    let key = SessionKey::parse(KEY).unwrap();
    let mut a = PortableState::open(a, &key).unwrap();
    let mut b = PortableState::open(b, &key).unwrap();
    a.issued_at_ms = 0;
    b.issued_at_ms = 0;
    a.origin_ms = None;
    b.origin_ms = None;
    a.owner = None;
    b.owner = None;
    assert!(a == b, "the same state, the same token");
}

fn bits(v: &[f32]) -> Vec<u32> {
    v.iter().map(|x| x.to_bits()).collect()
}

fn assert_same_frame(a: &pb::AdjustedFrame, b: &pb::AdjustedFrame) {
    assert_eq!(a.frame_index, b.frame_index);
    assert_eq!(a.frames_seen, b.frames_seen, "frame {}", a.frame_index);
    assert_eq!(
        bits(&a.bone_lengths),
        bits(&b.bone_lengths),
        "frame {}: lengths differ",
        a.frame_index
    );
    assert_eq!(
        bits(&a.adjusted_pose_3d),
        bits(&b.adjusted_pose_3d),
        "frame {}: poses differ",
        a.frame_index
    );
    assert_eq!(bits(&a.lifted_pose_3d), bits(&b.lifted_pose_3d));
    assert_eq!(a.lifter, b.lifter);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_session_resumed_from_its_token_on_another_server_continues_bit_for_bit() {
    let (server_a, mut a) = start(config(Some(KEY))).await;
    let (server_b, mut b) = start(config(Some(KEY))).await;
    let stature = blapose_server::models::embedded_stature_model().unwrap();
    for kind in [Kind::Plain, Kind::Camera, Kind::Lifter, Kind::Subject] {
        let lifting = matches!(kind, Kind::Lifter);
        // Uninterrupted on A, with a token request after frame K - 1.
        let mut requests = vec![open(kind)];
        for t in 0..N {
            requests.push(frame(t, lifting));
            if t == K - 1 {
                requests.push(token_request());
            }
        }
        requests.push(pb::StreamRequest {
            kind: Some(Req::Close(pb::CloseSession {})),
        });
        let (whole, end) = exchange(&mut a, requests).await;
        end.unwrap();
        let o = opened(&whole);
        assert!(!o.session_token.is_empty(), "a token on open");
        let whole_frames = frames(&whole);
        assert_eq!(whole_frames.len() as u64, N);
        if matches!(kind, Kind::Subject) {
            // The subject's stature-regression lengths, every frame.
            assert_eq!(o.subject, Some(SUBJECT));
            let want = stature.predict(1.81, Some(blapose_model::stature::Sex::Male));
            for f in &whole_frames {
                assert_eq!(bits(&f.bone_lengths), bits(&want));
            }
        }
        // Periodic tokens every 10 frames, each right after its frame's
        // answer, plus the requested one at K (after frame K - 1's answer,
        // and identical to the periodic token of the same state).
        let all_tokens = tokens(&whole);
        let seen: Vec<u64> = all_tokens.iter().map(|t| t.frames_seen).collect();
        assert_eq!(seen, [10, 20, 30, 30, 40, 50], "{kind:?}");
        assert_same_state(&all_tokens[2].token, &all_tokens[3].token);
        for (i, m) in whole.iter().enumerate() {
            if let Resp::Token(t) = m {
                match &whole[i - 1] {
                    Resp::Frame(f) => assert_eq!(f.frames_seen, t.frames_seen),
                    Resp::Token(prev) => assert_eq!(prev.frames_seen, t.frames_seen),
                    other => panic!("a token after {other:?}"),
                }
            }
        }
        let token = &all_tokens[3];
        let size = token.token.len();
        println!("{kind:?}: token of {size} bytes at frame {K}");
        if matches!(kind, Kind::Plain) {
            // 4,489 + the label + 16 bytes naming the owner.
            assert!(size < 4520, "{size} bytes");
        }

        // B has never seen the session: it restores it from the token.
        let mut requests = vec![resume(&o.session_id, &token.token)];
        requests.extend((K..N).map(|t| frame(t, lifting)));
        let (resumed, end) = exchange(&mut b, requests).await;
        end.unwrap();
        let r = opened(&resumed);
        assert!(r.resumed);
        assert_eq!(r.session_id, o.session_id);
        assert_eq!(r.frames_seen, K);
        assert_eq!(
            bits(&r.bone_lengths),
            bits(&whole_frames[K as usize - 1].bone_lengths)
        );
        assert_eq!(r.input_format, o.input_format);
        assert_eq!(r.camera, o.camera);
        assert_eq!(r.subject, o.subject, "the token carries the subject");
        assert_eq!(r.lifter, o.lifter);
        assert_same_state(&r.session_token, &token.token);
        let after = frames(&resumed);
        assert_eq!(after.len() as u64, N - K);
        for (x, y) in after.iter().zip(&whole_frames[K as usize..]) {
            assert_same_frame(x, y);
        }
        // B's periodic tokens are A's, byte for byte but the issue time.
        let b_tokens = tokens(&resumed);
        assert_eq!(b_tokens.len(), 2);
        assert_same_state(&b_tokens[0].token, &all_tokens[4].token);
        assert_same_state(&b_tokens[1].token, &all_tokens[5].token);
        // B holds it now; a resume there with the token continues from it.
        let (again, end) = exchange(&mut b, vec![resume(&o.session_id, &token.token)]).await;
        end.unwrap();
        assert_eq!(opened(&again).frames_seen, K);
    }
    server_a.shutdown().await.unwrap();
    server_b.shutdown().await.unwrap();
}

/// A safetensors file's bytes with one more `__metadata__` entry.
fn relabeled(path: &std::path::Path) -> Vec<u8> {
    let bytes = std::fs::read(path).unwrap();
    let n = u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
    let mut header: serde_json::Value = serde_json::from_slice(&bytes[8..8 + n]).unwrap();
    header["__metadata__"]["tokens_test"] = "another copy".into();
    let header = serde_json::to_vec(&header).unwrap();
    let mut out = (header.len() as u64).to_le_bytes().to_vec();
    out.extend_from_slice(&header);
    out.extend_from_slice(&bytes[8 + n..]);
    out
}

async fn status_of(
    client: &mut PoseAdjustmentClient<Channel>,
    first: pb::StreamRequest,
) -> tonic::Status {
    let (responses, end) = exchange(client, vec![first]).await;
    match end {
        Err(status) => status,
        Ok(()) => panic!("expected an error status, got {responses:?}"),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn bad_tokens_are_refused_with_a_status_naming_the_problem() {
    let (server_a, mut a) = start(config(Some(KEY))).await;
    let mut requests = vec![open(Kind::Plain)];
    requests.extend((0..12).map(|t| frame(t, false)));
    let (run, end) = exchange(&mut a, requests).await;
    end.unwrap();
    let id = opened(&run).session_id.clone();
    let token = tokens(&run)[0].token.clone();
    // A client that does not ask for them (one that predates tokens) gets
    // no SessionToken responses, only the token in SessionOpened.
    let mut quiet = open(Kind::Plain);
    if let Some(Req::Open(o)) = &mut quiet.kind {
        o.session_tokens = false;
    }
    let mut requests = vec![quiet];
    requests.extend((0..25).map(|t| frame(t, false)));
    let (quiet_run, end) = exchange(&mut a, requests).await;
    end.unwrap();
    assert!(!opened(&quiet_run).session_token.is_empty());
    assert!(tokens(&quiet_run).is_empty());
    assert_eq!(frames(&quiet_run).len(), 25);
    // A detached session held by A: restore it elsewhere.
    let (server_b, mut b) = start(config(Some(KEY))).await;

    // Altered anywhere after the version byte, or truncated.
    for at in [10, 100, 2000, token.len() - 1] {
        let mut t = token.clone();
        t[at] ^= 0x20;
        let s = status_of(&mut b, resume(&id, &t)).await;
        assert_eq!(s.code(), Code::Unauthenticated, "byte {at}: {s:?}");
        assert!(s.message().contains("altered"), "{}", s.message());
    }
    for cut in [40, token.len() / 2, token.len() - 1] {
        let s = status_of(&mut b, resume(&id, &token[..cut])).await;
        assert_eq!(s.code(), Code::Unauthenticated, "cut {cut}: {s:?}");
    }
    // Not a token at all.
    let s = status_of(&mut b, resume(&id, b"hello")).await;
    assert_eq!(s.code(), Code::InvalidArgument, "{s:?}");
    // Another version (1: before missing joints were held).
    let mut v1 = token.clone();
    v1[4] = 1;
    let s = status_of(&mut b, resume(&id, &v1)).await;
    assert_eq!(s.code(), Code::FailedPrecondition, "{s:?}");
    assert!(s.message().contains("version 1"), "{}", s.message());
    // Another session's id.
    let other = "0123456789abcdef0123456789abcdef";
    let s = status_of(&mut b, resume(other, &token)).await;
    assert_eq!(s.code(), Code::InvalidArgument, "{s:?}");
    assert!(s.message().contains("not"), "{}", s.message());
    // Without a token an unknown session is still NOT_FOUND.
    let s = status_of(&mut b, resume(&id, &[])).await;
    assert_eq!(s.code(), Code::NotFound, "{s:?}");
    server_b.shutdown().await.unwrap();

    // Another key.
    let (server_c, mut c) = start(config(Some("another key of enough bytes"))).await;
    let s = status_of(&mut c, resume(&id, &token)).await;
    assert_eq!(s.code(), Code::Unauthenticated, "{s:?}");
    server_c.shutdown().await.unwrap();

    // Other weights under the same key: the shipped GRU with one more
    // metadata entry (the same model, other bytes, so another SHA-256).
    let other_weights = std::env::temp_dir().join(format!(
        "blapose-tokens-test-{}.safetensors",
        std::process::id()
    ));
    std::fs::write(
        &other_weights,
        relabeled(&models("bone_length_gru.safetensors")),
    )
    .unwrap();
    let (server_d, mut d) = start(ServerConfig {
        weights: WeightsSource::File(other_weights.clone()),
        ..config(Some(KEY))
    })
    .await;
    let _ = std::fs::remove_file(&other_weights);
    let s = status_of(&mut d, resume(&id, &token)).await;
    assert_eq!(s.code(), Code::FailedPrecondition, "{s:?}");
    assert!(s.message().contains("other weights"), "{}", s.message());
    server_d.shutdown().await.unwrap();

    // No key: no tokens issued or accepted, token requests refused per
    // frame, everything else as before.
    let (server_e, mut e) = start(config(None)).await;
    let s = status_of(&mut e, resume(&id, &token)).await;
    assert_eq!(s.code(), Code::FailedPrecondition, "{s:?}");
    assert!(s.message().contains("--session-key"), "{}", s.message());
    let (run, end) = exchange(
        &mut e,
        vec![
            open(Kind::Plain),
            frame(0, false),
            token_request(),
            frame(1, false),
        ],
    )
    .await;
    end.unwrap();
    assert!(opened(&run).session_token.is_empty());
    assert!(tokens(&run).is_empty());
    match &run[2] {
        Resp::Error(err) => assert_eq!(err.code, Code::FailedPrecondition as i32),
        other => panic!("expected a FrameError, got {other:?}"),
    }
    assert_eq!(frames(&run[3..]).len(), 1);
    server_e.shutdown().await.unwrap();
    server_a.shutdown().await.unwrap();
}

/// A draining server (SIGTERM) ends each stream with a final token as of
/// every frame answered, then UNAVAILABLE saying to resume elsewhere with
/// it: the client re-sends nothing.
/// Open with `first` on a fresh server, send 12 frames, wait for their
/// answers, then shut the server down with the stream still open: what
/// came after the answers, and the status the stream ended with.
async fn drained(first: pb::StreamRequest) -> (Vec<Resp>, tonic::Status) {
    let (server, mut client) = start(config(Some(KEY))).await;
    let (tx, rx) = mpsc::channel(32);
    tx.send(first).await.unwrap();
    for t in 0..12 {
        tx.send(frame(t, false)).await.unwrap();
    }
    let mut inbound = client
        .stream(ReceiverStream::new(rx))
        .await
        .unwrap()
        .into_inner();
    let mut answered = 0;
    while answered < 12 {
        if let Some(Resp::Frame(_)) = inbound.message().await.unwrap().unwrap().kind {
            answered += 1;
        }
    }
    // The stream stays open (tx is alive) while the server drains.
    let shutdown = tokio::spawn(server.shutdown());
    let mut after = Vec::new();
    let status = loop {
        match tokio::time::timeout(Duration::from_secs(30), inbound.message())
            .await
            .expect("the drain ends the stream")
        {
            Ok(Some(m)) => after.extend(m.kind),
            Ok(None) => panic!("the stream ended without a status"),
            Err(status) => break status,
        }
    };
    drop(tx);
    shutdown.await.unwrap().unwrap();
    (after, status)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_draining_server_sends_each_stream_a_final_token() {
    let (after, status) = drained(open(Kind::Plain)).await;
    assert_eq!(status.code(), Code::Unavailable, "{status:?}");
    assert!(status.message().contains("token"), "{}", status.message());
    match after.last() {
        Some(Resp::Token(t)) => {
            assert_eq!(t.frames_seen, 12);
            assert!(!t.token.is_empty());
        }
        other => panic!("the last message before the status is not a token: {other:?}"),
    }
}

/// A lost joint's coordinates are never read (two kinds of garbage, NaN
/// among them, give the same answers bit for bit), and a frame without a
/// detected joint changes nothing but the frame count: it is answered with
/// the estimate as it stood, and the session goes on exactly as if it had
/// not been sent.
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn missing_joints_are_not_read_and_empty_frames_change_nothing() {
    let (server, mut client) = start(config(None)).await;
    let run = |frames: Vec<pb::StreamRequest>| {
        let mut requests = vec![open(Kind::Plain)];
        requests.extend(frames);
        requests
    };
    let (a, end) = exchange(
        &mut client,
        run((0..N).map(|t| frame_with(t, false, 2)).collect()),
    )
    .await;
    end.unwrap();
    let (b, end) = exchange(
        &mut client,
        run((0..N).map(|t| frame_with(t, false, 7)).collect()),
    )
    .await;
    end.unwrap();
    let (a, b) = (frames(&a), frames(&b));
    assert_eq!(a.len() as u64, N);
    for (x, y) in a.iter().zip(&b) {
        assert_same_frame(x, y);
    }
    // Without the empty frames: the same session, two frames fewer.
    let kept: Vec<u64> = (0..N).filter(|t| !NO_JOINT.contains(t)).collect();
    let (c, end) = exchange(
        &mut client,
        run(kept.iter().map(|&t| frame_with(t, false, 2)).collect()),
    )
    .await;
    end.unwrap();
    let c = frames(&c);
    for (x, &t) in c.iter().zip(&kept) {
        let y = a[t as usize];
        let before = NO_JOINT.iter().filter(|&&e| e < t).count() as u64;
        assert_eq!(x.frames_seen + before, y.frames_seen, "frame {t}");
        assert_eq!(bits(&x.bone_lengths), bits(&y.bone_lengths), "frame {t}");
        assert_eq!(
            bits(&x.adjusted_pose_3d),
            bits(&y.adjusted_pose_3d),
            "frame {t}"
        );
    }
    for &e in &NO_JOINT {
        let (empty, prev) = (a[e as usize], a[e as usize - 1]);
        assert_eq!(empty.frames_seen, e + 1, "an empty frame counts");
        assert_eq!(
            bits(&empty.bone_lengths),
            bits(&prev.bone_lengths),
            "frame {e}: the estimate as it stood"
        );
    }
    server.shutdown().await.unwrap();
}

/// A token of `state` as `edit` leaves it, signed with the real key.
fn crafted(token: &[u8], edit: impl FnOnce(&mut PortableState)) -> Vec<u8> {
    let key = SessionKey::parse(KEY).unwrap();
    let mut state = PortableState::open(token, &key).unwrap();
    edit(&mut state);
    state.seal(&key)
}

fn now_ms() -> u64 {
    blapose_server::token::now_ms()
}

/// A session of `kind` on `client` with `n` frames, its stream ended
/// without close (detached); its id and tokens.
async fn detached(
    client: &mut PoseAdjustmentClient<Channel>,
    kind: Kind,
    n: u64,
) -> (String, Vec<pb::SessionToken>) {
    let mut requests = vec![open(kind)];
    requests.extend((0..n).map(|t| frame(t, matches!(kind, Kind::Lifter))));
    let (run, end) = exchange(client, requests).await;
    end.unwrap();
    let id = opened(&run).session_id.clone();
    (id, tokens(&run).into_iter().cloned().collect())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_restored_state_is_checked_like_input_even_with_a_valid_signature() {
    let (server_a, mut a) = start(config(Some(KEY))).await;
    let (server_b, mut b) = start(config(Some(KEY))).await;
    let (id, plain) = detached(&mut a, Kind::Plain, 12).await;
    let token = plain[0].token.clone();
    let (lift_id, lifting) = detached(&mut a, Kind::Lifter, 12).await;
    let nan_held = |s: &mut PortableState| {
        let mut last = *s.held.last();
        last[4] = Some([f32::NAN, 0.0]);
        s.held = blapose_core::missing::HeldJoints::from_last(last);
    };
    type Edit = Box<dyn FnOnce(&mut PortableState)>;
    let cases: Vec<(&str, Edit)> = vec![
        ("hidden state [3]", Box::new(|s| s.hidden[3] = f32::NAN)),
        ("hidden state [5]", Box::new(|s| s.hidden[5] = 4.0)),
        (
            "frames read",
            Box::new(|s| {
                s.lengths =
                    blapose_server::session::RunningMean::from_parts(*s.lengths.sum(), u64::MAX)
            }),
        ),
        ("frames without a joint", Box::new(|s| s.skipped = u64::MAX)),
        (
            "running sum [bone 2]",
            Box::new(|s| {
                let mut sum = *s.lengths.sum();
                sum[2] = f64::INFINITY;
                s.lengths =
                    blapose_server::session::RunningMean::from_parts(sum, s.lengths.count());
            }),
        ),
        (
            "input format",
            Box::new(|s| {
                s.input.coordinates = blapose_server::session::Coordinates::Pixels {
                    width: 0,
                    height: 1000,
                }
            }),
        ),
        ("held joint [4]", Box::new(nan_held)),
        (
            "issue time",
            Box::new(|s| s.issued_at_ms = now_ms() + 3_600_000),
        ),
    ];
    for (field, edit) in cases {
        let s = status_of(&mut b, resume(&id, &crafted(&token, edit))).await;
        assert_eq!(s.code(), Code::InvalidArgument, "{field}: {s:?}");
        assert!(s.message().contains(field), "{field}: {}", s.message());
    }
    let window = crafted(&lifting[0].token, |s| {
        if let Some(w) = &mut s.window {
            w.frames[0][0][0] = f32::INFINITY;
        }
    });
    let s = status_of(&mut b, resume(&lift_id, &window)).await;
    assert_eq!(s.code(), Code::InvalidArgument, "{s:?}");
    assert!(s.message().contains("lifter window"), "{}", s.message());
    // An expired token: every replica refuses it.
    let old = crafted(&token, |s| s.issued_at_ms = now_ms() - 2 * 3_600_000);
    let s = status_of(&mut b, resume(&id, &old)).await;
    assert_eq!(s.code(), Code::FailedPrecondition, "{s:?}");
    assert!(s.message().contains("expired"), "{}", s.message());
    // The same state, re-signed as it was: restored.
    let (back, end) = exchange(&mut b, vec![resume(&id, &crafted(&token, |_| {}))]).await;
    end.unwrap();
    assert_eq!(opened(&back).frames_seen, 10);
    server_a.shutdown().await.unwrap();
    server_b.shutdown().await.unwrap();
}

/// A plain session opened on `client`, 12 frames, then closed in its
/// stream: its id and the first token it was given.
async fn closed_session(client: &mut PoseAdjustmentClient<Channel>) -> (String, Vec<u8>) {
    let mut requests = vec![open(Kind::Plain)];
    requests.extend((0..12).map(|t| frame(t, false)));
    requests.push(pb::StreamRequest {
        kind: Some(Req::Close(pb::CloseSession {})),
    });
    let (run, end) = exchange(client, requests).await;
    end.unwrap();
    (
        opened(&run).session_id.clone(),
        tokens(&run)[0].token.clone(),
    )
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn closing_a_session_ends_its_tokens_where_it_lived() {
    let (server_a, mut a) = start(config(Some(KEY))).await;
    let (server_b, mut b) = start(config(Some(KEY))).await;
    // Closed in its stream.
    let (id, token) = closed_session(&mut a).await;
    let s = status_of(&mut a, resume(&id, &token)).await;
    assert_eq!(s.code(), Code::FailedPrecondition, "{s:?}");
    assert!(s.message().contains("closed"), "{}", s.message());
    // Closed by CloseSession while detached.
    let (id2, tokens2) = detached(&mut a, Kind::Plain, 12).await;
    a.close_session(pb::CloseSessionRequest {
        session_id: id2.clone(),
    })
    .await
    .unwrap();
    let s = status_of(&mut a, resume(&id2, &tokens2[0].token)).await;
    assert_eq!(s.code(), Code::FailedPrecondition, "{s:?}");
    assert!(s.message().contains("closed"), "{}", s.message());
    // Around the balancer: a replica that never saw the session or its
    // close restores it, until the token expires (documented).
    let (on_b, end) = exchange(&mut b, vec![resume(&id, &token)]).await;
    end.unwrap();
    assert_eq!(opened(&on_b).frames_seen, 10);
    let old = crafted(&tokens2[0].token, |s| {
        s.issued_at_ms = now_ms() - 2 * 3_600_000
    });
    let s = status_of(&mut b, resume(&id2, &old)).await;
    assert_eq!(s.code(), Code::FailedPrecondition, "{s:?}");
    server_a.shutdown().await.unwrap();
    server_b.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn an_older_token_never_rolls_a_session_back() {
    let short = ServerConfig {
        session_ttl: Duration::from_millis(300),
        ..config(Some(KEY))
    };
    let (server_a, mut a) = start(short).await;
    let (id, issued) = detached(&mut a, Kind::Plain, 35).await;
    let frames_of = |t: &pb::SessionToken| t.frames_seen;
    assert_eq!(
        issued.iter().map(frames_of).collect::<Vec<_>>(),
        [10, 20, 30]
    );
    // Held: the token names the state the client continues from (it lost
    // the answers after it), and its SessionOpened brings the newest token.
    let (held, end) = exchange(&mut a, vec![resume(&id, &issued[2].token)]).await;
    end.unwrap();
    assert_eq!(opened(&held).frames_seen, 30);
    let newest = opened(&held).session_token.clone();
    let mut requests = vec![resume(&id, &newest)];
    requests.extend((30..35).map(|t| frame(t, false)));
    requests.push(token_request());
    let (again, end) = exchange(&mut a, requests).await;
    end.unwrap();
    let newest = tokens(&again)[0].clone();
    assert_eq!(newest.frames_seen, 35);
    let newest = newest.token;
    // Evicted after its TTL: remembered, and a token older than the
    // newest one issued is refused, named ...
    tokio::time::sleep(Duration::from_millis(900)).await;
    for old in [
        &issued[0].token,
        &issued[2].token,
        &opened(&held).session_token,
    ] {
        let s = status_of(&mut a, resume(&id, old)).await;
        assert_eq!(s.code(), Code::FailedPrecondition, "{s:?}");
        assert!(s.message().contains("rolled back"), "{}", s.message());
    }
    // ... and the newest one restores it.
    let (back, end) = exchange(&mut a, vec![resume(&id, &newest)]).await;
    end.unwrap();
    assert_eq!(opened(&back).frames_seen, 35);
    server_a.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn resuming_a_live_session_retires_its_stream_on_that_replica() {
    let (server_a, mut a) = start(config(Some(KEY))).await;
    let (tx, rx) = mpsc::channel(32);
    tx.send(open(Kind::Plain)).await.unwrap();
    for t in 0..12 {
        tx.send(frame(t, false)).await.unwrap();
    }
    let mut first = a
        .stream(ReceiverStream::new(rx))
        .await
        .unwrap()
        .into_inner();
    let mut id = String::new();
    let mut token = Vec::new();
    while token.is_empty() {
        match first.message().await.unwrap().unwrap().kind {
            Some(Resp::Opened(o)) => id = o.session_id,
            Some(Resp::Token(t)) => token = t.token,
            _ => {}
        }
    }
    // Newest wins: the resume takes the session, the old stream ends.
    let (second, end) = exchange(&mut a, vec![resume(&id, &token)]).await;
    end.unwrap();
    assert!(opened(&second).resumed);
    let status = loop {
        match first.message().await {
            Ok(Some(_)) => {}
            Ok(None) => panic!("the old stream ended without a status"),
            Err(status) => break status,
        }
    };
    assert_eq!(status.code(), Code::Aborted, "{status:?}");
    assert!(status.message().contains("resumed"), "{}", status.message());
    drop(tx);
    server_a.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_stream_that_never_asked_gets_no_token_at_shutdown() {
    let mut quiet = open(Kind::Plain);
    if let Some(Req::Open(o)) = &mut quiet.kind {
        o.session_tokens = false;
    }
    let (after, status) = drained(quiet).await;
    assert!(tokens(&after).is_empty(), "{after:?}");
    assert_eq!(status.code(), Code::Unavailable, "{status:?}");
    assert!(!status.message().contains("token"), "{}", status.message());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn no_chain_of_restores_outlives_the_first_tokens_ttl() {
    // The fork around the balancer: closed on A, restored on B from a
    // token A issued, B's fresh token restored on C, C's on A. Every token
    // of the chain expires with the first one.
    let ttl = Duration::from_secs(2);
    let replica = || ServerConfig {
        token_ttl: ttl,
        lifter: None,
        ..config(Some(KEY))
    };
    let (server_a, mut a) = start(replica()).await;
    let (server_b, mut b) = start(replica()).await;
    let (server_c, mut c) = start(replica()).await;
    let key = SessionKey::parse(KEY).unwrap();
    let (id, first) = closed_session(&mut a).await;
    let origin = PortableState::open(&first, &key).unwrap().issued_at_ms;
    // Within the TTL the chain restores (documented: a replica that never
    // saw the close cannot know of it) ...
    let mut requests = vec![resume(&id, &first)];
    requests.extend((10..12).map(|t| frame(t, false)));
    let (on_b, end) = exchange(&mut b, requests).await;
    end.unwrap();
    let from_b = opened(&on_b).session_token.clone();
    tokio::time::sleep(Duration::from_millis(700)).await;
    let (on_c, end) = exchange(&mut c, vec![resume(&id, &from_b), token_request()]).await;
    end.unwrap();
    let from_c = tokens(&on_c)[0].token.clone();
    let state = PortableState::open(&from_c, &key).unwrap();
    assert_eq!(state.origin_ms, Some(origin), "the chain keeps its origin");
    assert!(state.issued_at_ms > origin + 500, "a fresh token");
    // ... and once the first token's TTL has run out, no token of the
    // chain restores anywhere, however fresh it is itself.
    let until =
        Duration::from_millis(origin + 2_300).saturating_sub(Duration::from_millis(now_ms()));
    tokio::time::sleep(until).await;
    assert!(
        now_ms() - state.issued_at_ms < 2_000,
        "C's token is younger than the TTL"
    );
    for (replica, client) in [("A", &mut a), ("B", &mut b), ("C", &mut c)] {
        for token in [&from_b, &from_c] {
            let s = status_of(client, resume(&id, token)).await;
            assert_eq!(s.code(), Code::FailedPrecondition, "{replica}: {s:?}");
            assert!(
                s.message().contains("expired"),
                "{replica}: {}",
                s.message()
            );
        }
    }
    server_a.shutdown().await.unwrap();
    server_b.shutdown().await.unwrap();
    server_c.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn churn_forgets_ended_sessions_but_never_revives_them() {
    // 1,100 sessions opened and closed by one client, memory for 1,024:
    // the first is forgotten, and its token still refused (issued before
    // the floor the forgetting raised).
    let (server, mut a) = start(ServerConfig {
        lifter: None,
        protection: blapose_server::protect::Protection {
            max_ended_sessions: 1024,
            ..Default::default()
        },
        ..config(Some(KEY))
    })
    .await;
    let close = pb::StreamRequest {
        kind: Some(Req::Close(pb::CloseSession {})),
    };
    let mut first = None;
    let mut last = None;
    for _ in 0..1100 {
        let (run, end) = exchange(&mut a, vec![open(Kind::Plain), close.clone()]).await;
        end.unwrap();
        let o = opened(&run);
        let pair = (o.session_id.clone(), o.session_token.clone());
        first.get_or_insert_with(|| pair.clone());
        last = Some(pair);
    }
    let (first_id, first_token) = first.unwrap();
    let s = status_of(&mut a, resume(&first_id, &first_token)).await;
    assert_eq!(s.code(), Code::FailedPrecondition, "{s:?}");
    assert!(
        s.message().contains("oldest ended session"),
        "{}",
        s.message()
    );
    let (last_id, last_token) = last.unwrap();
    let s = status_of(&mut a, resume(&last_id, &last_token)).await;
    assert_eq!(s.code(), Code::FailedPrecondition, "{s:?}");
    assert!(s.message().contains("closed"), "{}", s.message());
    server.shutdown().await.unwrap();
}

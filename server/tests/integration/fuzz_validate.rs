//! Fuzzed request handling: arbitrary bytes through prost's decoding of
//! every request message, and arbitrary well-formed messages (sizes right
//! or wrong, values finite or not, cameras plausible or not) through the
//! server's stages: validate (input format, camera against the
//! camera-aware contracts, subject, model, frames, sequences), prepare
//! (missing joints held, the camera applied) and answer (each frame's pose
//! rebuilt with lengths). Nothing may panic; every refusal is a typed
//! `InvalidInput` (or a `Status` from the adjustment).
//!
//! A fixed-seed run of a few hundred cases runs in `cargo test`; a longer
//! one: `PROPTEST_CASES=100000 cargo test --release -p blapose-server --test
//! fuzz_validate` (README.md: Fuzzing and abuse).

use blapose_core::NUM_BONES;
use blapose_proto::v1 as pb;
use blapose_server::{answer, prepare, validate, ModelInput};
use pb::stream_request::Kind as Req;
use proptest::prelude::*;
use prost::Message;

use blapose_test_support::fuzz;

fn config() -> ProptestConfig {
    fuzz::config(256, 0x7661_6c69_6461)
}

/// The contracts a server may serve calibrations with (`None`: no
/// camera-aware model).
fn contracts() -> Vec<Option<ModelInput>> {
    vec![
        None,
        Some(ModelInput::screen()),
        Some(ModelInput::from_training(true, false, false)),
        Some(ModelInput::from_training(true, true, true)),
    ]
}

/// Any f32, plausible ones most often.
fn value(scale: f32) -> impl Strategy<Value = f32> {
    prop_oneof![
        400 => -scale..scale,
        1 => any::<f32>(),
        1 => prop::sample::select(vec![f32::NAN, f32::INFINITY, f32::NEG_INFINITY, f32::MAX, 0.0, 1e-30]),
    ]
}

fn input_format() -> impl Strategy<Value = Option<pb::InputFormat>> {
    let coordinates = prop_oneof![
        1 => Just(None),
        2 => any::<bool>().prop_map(|n| Some(pb::input_format::Coordinates::Normalized(n))),
        12 => (0u32..4000, 0u32..4000).prop_map(|(width, height)| Some(
            pb::input_format::Coordinates::ImageSize(pb::ImageSize { width, height })
        )),
        1 => (any::<u32>(), any::<u32>()).prop_map(|(width, height)| Some(
            pb::input_format::Coordinates::ImageSize(pb::ImageSize { width, height })
        )),
    ];
    let layout = prop_oneof![6 => 1i32..4, 1 => -1i32..6];
    prop_oneof![
        1 => Just(None),
        12 => (layout, coordinates).prop_map(|(layout, coordinates)| Some(pb::InputFormat { layout, coordinates })),
    ]
}

fn camera() -> impl Strategy<Value = Option<pb::CameraCalibration>> {
    let c = (
        prop::collection::vec(value(1.5), 0..5),
        (value(3000.0), value(3000.0), value(3000.0), value(3000.0)),
        prop::option::of((0u32..4000, 0u32..4000)),
        prop_oneof![Just(0.0f32), value(5.0)],
        prop::collection::vec(value(0.3), 0..7),
    )
        .prop_map(
            |(up, (fx, fy, px, py), size, height, distortion)| pb::CameraCalibration {
                up,
                focal_x: fx.abs(),
                focal_y: fy.abs(),
                principal_x: px,
                principal_y: py,
                image_size: size.map(|(width, height)| pb::ImageSize { width, height }),
                height,
                distortion,
            },
        );
    // Near a real camera (the camera-aware models' envelope), so the
    // later checks and the preparation run, not only the first refusal.
    let plausible = (
        (-0.2f32..0.2, -0.2f32..0.4),
        (600.0f32..2500.0, 400.0f32..1500.0, 300.0f32..600.0),
        (0.5f32..3.0, any::<bool>()),
        prop_oneof![Just(Vec::new()), prop::collection::vec(-0.1f32..0.1, 4..6)],
    )
        .prop_map(|((ux, uz), (f, px, py), (height, sized), distortion)| {
            pb::CameraCalibration {
                up: vec![ux, -1.0, uz],
                focal_x: f,
                focal_y: f,
                principal_x: px,
                principal_y: py,
                image_size: sized.then_some(pb::ImageSize {
                    width: 1000,
                    height: 1000,
                }),
                height,
                distortion,
            }
        });
    prop_oneof![2 => Just(None), 2 => c.prop_map(Some), 3 => plausible.prop_map(Some)]
}

fn subject() -> impl Strategy<Value = Option<pb::Subject>> {
    prop::option::of(
        (value(2.5), -1i32..4).prop_map(|(height_m, sex)| pb::Subject { height_m, sex }),
    )
}

/// A sequence request whose arrays are usually the right size.
fn sequence_request() -> impl Strategy<Value = pb::AdjustSequenceRequest> {
    (
        input_format(),
        prop_oneof![6 => 0i32..3, 1 => -1i32..4],
        0u32..6,
        prop::collection::vec(prop_oneof![8 => Just(0i32), 1 => -2i32..3], 3),
        (camera(), subject()),
    )
        .prop_flat_map(|(format, model, frames, skew, (camera, subject))| {
            let joints = match format.as_ref().map(|f| f.layout) {
                Some(2) => 16,
                _ => 17,
            };
            let n = |per: usize, skew: i32| {
                ((frames as usize * per) as i64 + skew as i64).max(0) as usize
            };
            (
                prop::collection::vec(value(2000.0), n(joints * 2, skew[0])),
                prop_oneof![
                    Just(Vec::new()),
                    prop::collection::vec(value(1.0), n(joints, skew[1]))
                ],
                prop::collection::vec(value(1.0), n(51, skew[2])),
            )
                .prop_map(move |(keypoints_2d, confidence, poses_3d)| {
                    pb::AdjustSequenceRequest {
                        input_format: format,
                        model,
                        num_frames: frames,
                        keypoints_2d,
                        confidence,
                        poses_3d,
                        camera: camera.clone(),
                        subject,
                        motion: None,
                    }
                })
        })
}

/// Sequences that passed validation (the strategies must reach the later
/// stages, not only the first refusal).
static REACHED: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);

/// Validate, prepare and answer one sequence request with every contract;
/// refusals must be typed, nothing may panic.
fn run_sequence(req: &pb::AdjustSequenceRequest, lengths: f32) {
    for contract in contracts() {
        let valid = match validate::sequence(req, contract.as_ref()) {
            Ok(v) => v,
            Err(e) => {
                if std::env::var("FUZZ_DEBUG").is_ok() {
                    eprintln!("{e}");
                }
                continue;
            }
        };
        REACHED.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let frames = valid.poses.len();
        assert_eq!(valid.inputs.len() % frames.max(1), 0);
        let prepared = prepare::sequence(valid);
        assert!(
            prepared.inputs.iter().all(|v| v.is_finite()),
            "prepared inputs are finite"
        );
        let per_frame = vec![[lengths; NUM_BONES]; prepared.poses.len()];
        if let Ok(adjusted) = answer::adjust_frames(&prepared.poses, &per_frame) {
            assert_eq!(adjusted.len(), prepared.poses.len());
        }
    }
}

/// Validate a stream's messages the way a session does.
fn run_stream(req: &pb::StreamRequest, frame: Option<&pb::Frame>) {
    let Some(Req::Open(open)) = &req.kind else {
        return;
    };
    let Ok(spec) = validate::input_format(open.input_format.as_ref()) else {
        return;
    };
    let _ = validate::stream_model(open.model);
    let _ = validate::subject(open.subject.as_ref());
    for contract in contracts() {
        let _ = validate::camera(open.camera.as_ref(), &spec, contract.as_ref());
    }
    if let Some(frame) = frame {
        if let Ok(valid) = validate::frame(&spec, frame) {
            assert!(valid.input.iter().all(|v| v.is_finite()));
        }
        let _ = validate::keypoints_frame(&spec, frame);
    }
}

proptest! {
    #![proptest_config(config())]

    #[test]
    fn arbitrary_bytes_decode_or_are_refused(raw in prop::collection::vec(any::<u8>(), 0..400)) {
        if let Ok(req) = pb::AdjustSequenceRequest::decode(raw.as_slice()) {
            run_sequence(&req, 0.25);
        }
        if let Ok(req) = pb::StreamRequest::decode(raw.as_slice()) {
            let frame = match &req.kind {
                Some(Req::Frame(f)) => Some(f.clone()),
                _ => None,
            };
            run_stream(&req, frame.as_ref());
        }
        let _ = pb::CloseSessionRequest::decode(raw.as_slice());
        let _ = pb::ModelInfoRequest::decode(raw.as_slice());
    }

    #[test]
    fn sequence_requests_are_validated_prepared_and_answered(
        req in sequence_request(),
        lengths in prop_oneof![Just(0.25f32), value(1.0)],
    ) {
        run_sequence(&req, lengths);
        // The same request through the wire: decoding what was encoded.
        let back = pb::AdjustSequenceRequest::decode(req.encode_to_vec().as_slice()).unwrap();
        run_sequence(&back, lengths);
    }

    #[test]
    fn stream_opens_and_frames_are_validated(
        format in input_format(),
        model in -1i32..4,
        (camera, subject) in (camera(), subject()),
        keypoints in prop::collection::vec(value(2000.0), 30..36),
        confidence in prop_oneof![Just(Vec::new()), prop::collection::vec(value(1.0), 15..18)],
        pose in prop::collection::vec(value(1.0), 48..53),
    ) {
        let open = pb::StreamRequest {
            kind: Some(Req::Open(pb::OpenSession {
                input_format: format,
                model,
                camera,
                subject,
                ..Default::default()
            })),
        };
        let frame = pb::Frame { frame_index: 0, keypoints_2d: keypoints, confidence, pose_3d: pose };
        run_stream(&open, Some(&frame));
    }
}

#[test]
fn the_strategies_reach_prepare_and_answer() {
    let mut runner = proptest::test_runner::TestRunner::new(config());
    let before = REACHED.load(std::sync::atomic::Ordering::Relaxed);
    runner
        .run(&sequence_request(), |req| {
            run_sequence(&req, 0.25);
            Ok(())
        })
        .unwrap();
    let reached = REACHED.load(std::sync::atomic::Ordering::Relaxed) - before;
    eprintln!("{reached} validated sequences in {} cases", config().cases);
    assert!(reached * 20 >= config().cases as usize, "{reached}");
}

/// Found by the longer run (PROPTEST_CASES=300000): a calibration whose
/// principal point is f32::MAX pixels (finite, so accepted) without a
/// camera height passes validation for the contracts that do not scale to
/// the floor, and preparation then feeds non-finite inputs to the model.
/// Validation now refuses a principal point beyond any image
/// (`blapose_core::level::MAX_PRINCIPAL_ABS`) as it refuses non-finite ones.
#[test]
fn regression_huge_principal_point_prepares_finite_inputs_or_is_refused() {
    let req = pb::AdjustSequenceRequest {
        input_format: Some(pb::InputFormat {
            layout: 1,
            coordinates: Some(pb::input_format::Coordinates::ImageSize(pb::ImageSize {
                width: 1,
                height: 1,
            })),
        }),
        model: 1,
        num_frames: 1,
        keypoints_2d: vec![0.0; 34],
        confidence: Vec::new(),
        poses_3d: (0..17)
            .flat_map(|j| [0.05 * j as f32, -0.1 * j as f32, 3.0 + 0.01 * j as f32])
            .collect(),
        camera: Some(pb::CameraCalibration {
            up: vec![-1.2475443, -1.1749436, 1.3962421],
            focal_x: 624.149,
            focal_y: 67.00182,
            principal_x: -2963.6563,
            principal_y: f32::MAX,
            image_size: None,
            height: 0.0,
            distortion: Vec::new(),
        }),
        subject: None,
        motion: None,
    };
    for contract in contracts() {
        let Ok(valid) = validate::sequence(&req, contract.as_ref()) else {
            continue;
        };
        let prepared = prepare::sequence(valid);
        assert!(
            prepared.inputs.iter().all(|v| v.is_finite()),
            "contract {contract:?}: non-finite prepared inputs"
        );
    }
}

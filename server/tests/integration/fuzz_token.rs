//! Fuzzed session tokens: arbitrary bytes, and valid tokens mutated and
//! signed again with the real key (so the decoder, not the MAC, meets
//! them), through `PortableState::open` and the restore checks
//! (`restore_check::check`). Nothing may panic; every refusal is a typed
//! `TokenError` or `RestoreError`.
//!
//! A fixed-seed run of a few hundred cases runs in `cargo test`; a longer
//! one: `PROPTEST_CASES=100000 cargo test --release -p blapose-server --test
//! fuzz_token` (README.md: Fuzzing and abuse).

use std::time::Duration;

use blapose_core::layouts::{Coordinates, InputFormat, KeypointLayout};
use blapose_core::missing::HeldJoints;
use blapose_core::NUM_JOINTS;
use blapose_model::RunningMean;
use blapose_proto::v1 as pb;
use blapose_server::restore_check;
use blapose_server::session::{SessionId, STATE_DIM};
use blapose_server::token::{
    hmac_sha256, weights_id, PortableState, PortableWindow, SessionKey, TokenError, MAC_BYTES,
    MAGIC, TOKEN_VERSION,
};
use proptest::prelude::*;

use blapose_test_support::fuzz;

const KEY: [u8; 32] = [0x5a; 32];

fn key() -> SessionKey {
    SessionKey::new(&KEY).unwrap()
}

/// A state as a session has it: camera, subject, lifter window or not.
fn state(camera: bool, lifter: bool) -> PortableState {
    let mut lengths = RunningMean::new();
    for k in 0..5 {
        lengths.push(&std::array::from_fn(|b| 0.1 + 0.013 * (b + k) as f32));
    }
    PortableState {
        session_id: SessionId::from_bytes([7; 16]),
        weights_id: weights_id("ab"),
        input: InputFormat {
            layout: KeypointLayout::Coco17,
            coordinates: Coordinates::Pixels {
                width: 1920,
                height: 1080,
            },
        },
        label: "cam".into(),
        camera: camera.then(|| pb::CameraCalibration {
            up: vec![0.0, -1.0, 0.1],
            focal_x: 1000.0,
            focal_y: 1000.0,
            principal_x: 960.0,
            principal_y: 540.0,
            image_size: None,
            height: 1.7,
            distortion: vec![-0.12, 0.03, 0.0005, -0.0002, 0.0],
        }),
        hidden: (0..STATE_DIM).map(|i| (i as f32 * 0.37).sin()).collect(),
        lengths,
        window: lifter.then(|| PortableWindow {
            lifter_id: weights_id("lifter"),
            receptive_field: 27,
            frames: (0..5)
                .map(|f| [[f as f32 * 0.1, -0.5]; NUM_JOINTS])
                .collect(),
        }),
        held: HeldJoints::from_last(std::array::from_fn(|j| {
            (j % 3 != 1).then_some([j as f32 * 0.05, -0.25])
        })),
        skipped: 2,
        subject: camera.then_some(pb::Subject {
            height_m: 1.72,
            sex: 1,
        }),
        issued_at_ms: blapose_server::token::now_ms(),
        motion: None,
        origin_ms: lifter.then(|| blapose_server::token::now_ms() - 1000),
        owner: camera.then_some([3; 16]),
    }
}

/// `body` signed with the real key.
fn signed(body: &[u8]) -> Vec<u8> {
    let mut out = body.to_vec();
    out.extend_from_slice(&hmac_sha256(&KEY, body));
    out
}

/// Open and, when it opens, check for restoring: never a panic.
fn open_and_check(token: &[u8]) -> Result<(), String> {
    match PortableState::open(token, &key()) {
        Ok(state) => {
            let _ = state.frames_seen();
            let _ = state.seal(&key());
            restore_check::check(
                &state,
                blapose_server::token::now_ms(),
                Duration::from_secs(3600),
            )
            .map_err(|e| e.to_string())
        }
        Err(e) => {
            let _ = e.to_status();
            Err(e.to_string())
        }
    }
}

proptest! {
    #![proptest_config(fuzz::config(384, 0x746f_6b65_6e66))]

    #[test]
    fn arbitrary_bytes_are_refused(raw in prop::collection::vec(any::<u8>(), 0..256)) {
        prop_assert!(open_and_check(&raw).is_err());
        let mut prefixed = MAGIC.to_vec();
        prefixed.push(TOKEN_VERSION);
        prefixed.extend_from_slice(&raw);
        let e = PortableState::open(&prefixed, &key()).unwrap_err();
        prop_assert!(matches!(e, TokenError::Unauthenticated), "{e}");
        let _ = open_and_check(&signed(&prefixed));
    }

    #[test]
    fn mutated_tokens_signed_with_the_key_are_decoded_or_refused(
        camera in any::<bool>(),
        lifter in any::<bool>(),
        mutations in prop::collection::vec(fuzz::mutation(), 1..5),
    ) {
        let token = state(camera, lifter).seal(&key());
        let body = &token[..token.len() - MAC_BYTES];
        let _ = open_and_check(&signed(&fuzz::mutate(body.to_vec(), &mutations, 5)));
        // Unsigned, the same mutation is an authentication failure.
        let unsigned = fuzz::mutate(token.clone(), &mutations, 5);
        if unsigned != token {
            prop_assert!(PortableState::open(&unsigned, &key()).is_err());
        }
    }
}

#[test]
fn unmutated_tokens_open_and_pass_the_restore_checks() {
    for (camera, lifter) in [(false, false), (true, false), (false, true), (true, true)] {
        let state = state(camera, lifter);
        let token = state.seal(&key());
        assert_eq!(PortableState::open(&token, &key()).unwrap(), state);
        open_and_check(&token).unwrap();
    }
}

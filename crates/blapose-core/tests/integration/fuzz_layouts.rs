//! Fuzzed keypoint layout conversion: arbitrary joint counts, values
//! (NaN, infinities, extremes), detection masks, flat buffers, image sizes
//! and layout names. Nothing may panic; every refusal is a [`LayoutError`];
//! what converts is finite wherever the server's input bounds hold.
//!
//! A fixed-seed run of a few hundred cases runs in `cargo test`; a longer
//! one: `PROPTEST_CASES=100000 cargo test --release -p blapose-core --test
//! fuzz_layouts` (README.md: Fuzzing and abuse).

use blapose_core::layouts::{Coordinates, KeypointLayout, LayoutError};
use proptest::prelude::*;

use blapose_test_support::fuzz;

/// The server's bound on a keypoint value (validate::MAX_KEYPOINT_ABS).
const MAX_ABS: f32 = 1e6;

fn layout() -> impl Strategy<Value = KeypointLayout> {
    prop::sample::select(KeypointLayout::ALL.to_vec())
}

/// Any f32, the special ones often.
fn value() -> impl Strategy<Value = f32> {
    prop_oneof![
        4 => -MAX_ABS..MAX_ABS,
        1 => any::<f32>(),
        1 => prop::sample::select(vec![f32::NAN, f32::INFINITY, f32::NEG_INFINITY, f32::MAX, f32::MIN, 0.0, -0.0, f32::MIN_POSITIVE]),
    ]
}

proptest! {
    #![proptest_config(fuzz::config(512, 0x626c_6170_6f73))]

    #[test]
    fn frames_convert_or_are_refused(layout in layout(), points in prop::collection::vec([value(), value()], 0..40)) {
        match layout.to_h36m17(&points) {
            Ok(out) => {
                prop_assert_eq!(points.len(), layout.num_joints());
                if points.iter().flatten().all(|v| v.abs() <= MAX_ABS) {
                    prop_assert!(out.iter().flatten().all(|v| v.is_finite()), "{:?}", out);
                }
            }
            Err(LayoutError::WrongJointCount { got, expected, .. }) => {
                prop_assert_eq!(got, points.len());
                prop_assert_ne!(got, expected);
            }
            Err(LayoutError::NonFinite { joint, .. }) => {
                prop_assert!(points[joint].iter().any(|v| !v.is_finite()));
            }
            Err(e) => prop_assert!(false, "unexpected {e}"),
        }
    }

    #[test]
    fn detection_masks_convert_or_are_refused(layout in layout(), present in prop::collection::vec(any::<bool>(), 0..40)) {
        match layout.present_h36m17(&present) {
            Ok(out) => {
                prop_assert_eq!(present.len(), layout.num_joints());
                if present.iter().all(|&p| p) {
                    prop_assert!(out.iter().all(|&p| p));
                }
            }
            Err(e) => prop_assert!(matches!(e, LayoutError::WrongJointCount { .. }), "{e}"),
        }
    }

    #[test]
    fn flat_buffers_convert_or_are_refused(layout in layout(), flat in prop::collection::vec(value(), 0..200)) {
        match layout.sequence_to_h36m17(&flat) {
            Ok(frames) => prop_assert_eq!(frames.len() * layout.num_joints() * 2, flat.len()),
            Err(e) => prop_assert!(
                matches!(e, LayoutError::RaggedBuffer { .. } | LayoutError::NonFinite { .. }),
                "{e}"
            ),
        }
    }

    #[test]
    fn pixels_normalize_to_finite_values(width in 1u32.., height in 1u32.., x in -MAX_ABS..MAX_ABS, y in -MAX_ABS..MAX_ABS) {
        let p = Coordinates::Pixels { width, height }.normalize([x, y]);
        prop_assert!(p.iter().all(|v| v.is_finite()), "{:?}", p);
    }

    #[test]
    fn layout_names_parse_or_are_refused(name in ".{0,12}") {
        match name.parse::<KeypointLayout>() {
            Ok(layout) => prop_assert_eq!(layout.name().parse::<KeypointLayout>().ok(), Some(layout)),
            Err(e) => prop_assert!(matches!(e, LayoutError::Unknown(_)), "{e}"),
        }
    }
}

//! Conversions between the wire messages and blapose-core's types, written
//! once for both ends of the contract.
//!
//! The server validates what clients send and echoes it back; the client
//! library builds what it sends and reads the echoes. Both speak of the same
//! core types ([`KeypointLayout`], [`Coordinates`], [`InputFormat`],
//! [`ModelKind`], [`Sex`]), so the mapping to the generated enums and messages lives here, next to them,
//! and a layout added to the proto fails to compile until it is mapped
//! (every `match` is exhaustive). What is *valid* stays with each end: the
//! server refuses `normalized: false` or an empty image with its own
//! messages before it converts; the client reads whatever the server echoes.

use blapose_core::layouts::{Coordinates, InputFormat, KeypointLayout};
use blapose_core::{ModelKind, Sex};

use crate::v1 as pb;

/// The wire enum of a keypoint layout.
pub const fn layout_to_proto(layout: KeypointLayout) -> pb::KeypointLayout {
    match layout {
        KeypointLayout::H36m17 => pb::KeypointLayout::H36m17,
        KeypointLayout::Sh16 => pb::KeypointLayout::Sh16,
        KeypointLayout::Coco17 => pb::KeypointLayout::Coco17,
    }
}

/// The layout with this wire number (`KeypointLayout` value); `None` for
/// UNSPECIFIED and numbers the proto does not define.
pub fn layout_from_proto(value: i32) -> Option<KeypointLayout> {
    match pb::KeypointLayout::try_from(value).ok()? {
        pb::KeypointLayout::Unspecified => None,
        pb::KeypointLayout::H36m17 => Some(KeypointLayout::H36m17),
        pb::KeypointLayout::Sh16 => Some(KeypointLayout::Sh16),
        pb::KeypointLayout::Coco17 => Some(KeypointLayout::Coco17),
    }
}

impl From<KeypointLayout> for pb::KeypointLayout {
    fn from(layout: KeypointLayout) -> Self {
        layout_to_proto(layout)
    }
}

impl From<Coordinates> for pb::input_format::Coordinates {
    fn from(coordinates: Coordinates) -> Self {
        match coordinates {
            Coordinates::Pixels { width, height } => {
                pb::input_format::Coordinates::ImageSize(pb::ImageSize { width, height })
            }
            Coordinates::Normalized => pb::input_format::Coordinates::Normalized(true),
        }
    }
}

/// The wire's coordinates as they are: an image size is pixels of that
/// image, `normalized` (whatever its value) normalized coordinates.
impl From<pb::input_format::Coordinates> for Coordinates {
    fn from(coordinates: pb::input_format::Coordinates) -> Self {
        match coordinates {
            pb::input_format::Coordinates::ImageSize(s) => Coordinates::Pixels {
                width: s.width,
                height: s.height,
            },
            pb::input_format::Coordinates::Normalized(_) => Coordinates::Normalized,
        }
    }
}

impl From<InputFormat> for pb::InputFormat {
    fn from(format: InputFormat) -> Self {
        pb::InputFormat {
            layout: layout_to_proto(format.layout) as i32,
            coordinates: Some(format.coordinates.into()),
        }
    }
}

/// The wire enum of a bone-length model.
impl From<ModelKind> for pb::Model {
    fn from(kind: ModelKind) -> Self {
        match kind {
            ModelKind::Gru => pb::Model::OnlineGru,
            ModelKind::BiGru => pb::Model::OfflineBigru,
        }
    }
}

/// The model with this wire number (`Model` value); `None` for UNSPECIFIED
/// (whose meaning, the RPC's default, is for the receiver to decide) and
/// numbers the proto does not define.
pub fn model_from_proto(value: i32) -> Option<ModelKind> {
    match pb::Model::try_from(value).ok()? {
        pb::Model::Unspecified => None,
        pb::Model::OnlineGru => Some(ModelKind::Gru),
        pb::Model::OfflineBigru => Some(ModelKind::BiGru),
    }
}

/// The wire enum of a person's sex.
impl From<Sex> for pb::Sex {
    fn from(sex: Sex) -> Self {
        match sex {
            Sex::Female => pb::Sex::Female,
            Sex::Male => pb::Sex::Male,
        }
    }
}

/// The sex with this wire number (`Sex` value); `None` for UNSPECIFIED
/// (not given) and numbers the proto does not define.
pub fn sex_from_proto(value: i32) -> Option<Sex> {
    match pb::Sex::try_from(value).ok()? {
        pb::Sex::Unspecified => None,
        pb::Sex::Female => Some(Sex::Female),
        pb::Sex::Male => Some(Sex::Male),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn layouts_map_to_their_wire_numbers_and_back() {
        let numbers: Vec<i32> = KeypointLayout::ALL
            .into_iter()
            .map(|l| pb::KeypointLayout::from(l) as i32)
            .collect();
        assert_eq!(numbers, [1, 2, 3]);
        for l in KeypointLayout::ALL {
            assert_eq!(layout_from_proto(layout_to_proto(l) as i32), Some(l));
        }
        for unknown in [0, 4, -1] {
            assert_eq!(layout_from_proto(unknown), None, "{unknown}");
        }
    }

    #[test]
    fn input_formats_round_trip() {
        for format in [
            InputFormat::pixels(KeypointLayout::Sh16, 1000, 1002),
            InputFormat {
                layout: KeypointLayout::Coco17,
                coordinates: Coordinates::Normalized,
            },
        ] {
            let msg = pb::InputFormat::from(format);
            assert_eq!(layout_from_proto(msg.layout), Some(format.layout));
            assert_eq!(
                msg.coordinates.map(Coordinates::from),
                Some(format.coordinates)
            );
        }
        assert_eq!(
            Coordinates::from(pb::input_format::Coordinates::Normalized(false)),
            Coordinates::Normalized
        );
    }

    #[test]
    fn models_and_sexes_map_to_their_wire_numbers_and_back() {
        for kind in ModelKind::ALL {
            assert_eq!(model_from_proto(pb::Model::from(kind) as i32), Some(kind));
        }
        assert_eq!(pb::Model::from(ModelKind::Gru) as i32, 1);
        assert_eq!(pb::Model::from(ModelKind::BiGru) as i32, 2);
        for sex in [Sex::Female, Sex::Male] {
            assert_eq!(sex_from_proto(pb::Sex::from(sex) as i32), Some(sex));
        }
        assert_eq!(pb::Sex::from(Sex::Female) as i32, 1);
        assert_eq!(pb::Sex::from(Sex::Male) as i32, 2);
        for unknown in [0, 3, -1] {
            assert_eq!(model_from_proto(unknown), None, "{unknown}");
            assert_eq!(sex_from_proto(unknown), None, "{unknown}");
        }
    }
}

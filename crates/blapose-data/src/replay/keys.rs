//! The replay format's array names and its layout codes.
//!
//! Readers, writers and error messages all name the same keys; keeping them
//! in one place means a key is spelled once. The layout is stored as a
//! number (an npz of float arrays cannot hold a string): the protocol's
//! `KeypointLayout` value, so a file and a request agree on it.

use blapose_core::layouts::KeypointLayout;

/// Key of the 2D keypoints.
pub const KEY_KEYPOINTS: &str = "keypoints_2d";
/// Key of the lifted 3D poses.
pub const KEY_POSE_3D: &str = "pose_3d";
/// Key of `[width, height]`.
pub const KEY_IMAGE_SIZE: &str = "image_size";
/// Key of the optional layout code.
pub const KEY_LAYOUT: &str = "layout";
/// Key of the optional ground truth.
pub const KEY_GT_3D: &str = "gt_3d";
/// Key of the optional confidences.
pub const KEY_CONFIDENCE: &str = "confidence";
/// Key of the optional frame rate.
pub const KEY_FPS: &str = "fps";
/// Key of the optional camera's up direction `(3,)` (camera coordinates).
pub const KEY_CAMERA_UP: &str = "camera_up";
/// Key of the optional camera's focal lengths `(2,)`, pixels.
pub const KEY_CAMERA_FOCAL: &str = "camera_focal";
/// Key of the optional camera's principal point `(2,)`, pixels.
pub const KEY_CAMERA_PRINCIPAL: &str = "camera_principal";
/// Key of the optional camera height above the floor `()` or `(1,)`,
/// metres; only together with [`CAMERA_KEYS`].
pub const KEY_CAMERA_HEIGHT: &str = "camera_height";
/// Key of the optional lens distortion `(4,)` or `(5,)`: OpenCV's `k1, k2,
/// p1, p2[, k3]`, when the keypoints were detected in the raw image; only
/// together with [`CAMERA_KEYS`].
pub const KEY_CAMERA_DISTORTION: &str = "camera_distortion";
/// The camera keys, all present or all absent ([`KEY_CAMERA_HEIGHT`] and
/// [`KEY_CAMERA_DISTORTION`] may join them).
pub const CAMERA_KEYS: [&str; 3] = [KEY_CAMERA_UP, KEY_CAMERA_FOCAL, KEY_CAMERA_PRINCIPAL];
/// Output key: adjusted poses `(T, 17, 3)`.
pub const KEY_ADJUSTED: &str = "adjusted_3d";
/// Output key: bone lengths applied to each frame `(T, 16)`.
pub const KEY_BONE_LENGTHS: &str = "bone_lengths";
/// Output key: the server lifter's poses before adjustment `(T, 17, 3)`
/// (only when the server lifted them).
pub const KEY_LIFTED: &str = "lifted_3d";
/// Output key: the pelvis the motion stage placed, `T x 3`, camera space.
pub const KEY_ROOT: &str = "root_3d";
/// Key of the optional stature `()` or `(1,)`, metres.
pub const KEY_SUBJECT_HEIGHT: &str = "subject_height";
/// Key of the optional sex `()` or `(1,)`: 1 female, 2 male (needs
/// [`KEY_SUBJECT_HEIGHT`]).
pub const KEY_SUBJECT_SEX: &str = "subject_sex";

/// The code a replay file stores in its `layout` array: the protocol's
/// `KeypointLayout` number (1 = H36M-17, 2 = SH-16, 3 = COCO-17).
pub const fn layout_code(layout: KeypointLayout) -> u32 {
    match layout {
        KeypointLayout::H36m17 => 1,
        KeypointLayout::Sh16 => 2,
        KeypointLayout::Coco17 => 3,
    }
}

/// The layout a replay file's `layout` code names.
pub fn layout_from_code(code: u32) -> Option<KeypointLayout> {
    KeypointLayout::ALL
        .into_iter()
        .find(|&l| layout_code(l) == code)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn layout_codes_round_trip() {
        assert_eq!(layout_code(KeypointLayout::H36m17), 1);
        assert_eq!(layout_code(KeypointLayout::Sh16), 2);
        assert_eq!(layout_code(KeypointLayout::Coco17), 3);
        for l in KeypointLayout::ALL {
            assert_eq!(layout_from_code(layout_code(l)), Some(l));
        }
        assert_eq!(layout_from_code(0), None);
        assert_eq!(layout_from_code(9), None);
    }
}

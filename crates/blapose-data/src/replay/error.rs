//! What can be wrong with a replay file, named precisely.
//!
//! A bad file must fail before anything is sent, with a message that names
//! the key, frame and joint at fault; one error type covers reading,
//! checking and writing, so callers match on one enum.

use std::path::{Path, PathBuf};

use blapose_core::layouts::KeypointLayout;

use super::camera::CameraError;
use super::keys::{
    KEY_CAMERA_FOCAL, KEY_CAMERA_HEIGHT, KEY_CAMERA_PRINCIPAL, KEY_CAMERA_UP, KEY_CONFIDENCE,
    KEY_IMAGE_SIZE, KEY_KEYPOINTS, KEY_LAYOUT, KEY_POSE_3D,
};
use crate::npz::NpzError;

/// Why a replay file could not be used.
#[derive(Debug, thiserror::Error)]
pub enum SequenceError {
    /// Reading, parsing or writing the npz failed (missing key, bad shape, ...).
    #[error("{}", npz_message(path, error))]
    Npz {
        /// The file.
        path: PathBuf,
        /// The npz error, naming the key.
        error: NpzError,
    },
    /// The file has no frames.
    #[error("the sequence has no frames")]
    Empty,
    /// A per-frame array's header declares more frames than the limit
    /// (refused before its values are read).
    #[error("{key} has {frames} frames, more than the limit of {max} (max_frames; the client's --max-file-frames)")]
    TooManyFrames {
        /// The array.
        key: &'static str,
        /// Frames its header declares.
        frames: usize,
        /// The limit.
        max: usize,
    },
    /// Two arrays disagree on the number of frames.
    #[error("{key} has {got} frames but {KEY_POSE_3D} has {expected}")]
    FrameCount {
        /// The offending array.
        key: &'static str,
        /// Its frames.
        got: usize,
        /// Frames of `pose_3d`.
        expected: usize,
    },
    /// `image_size` is not two positive integers.
    #[error(
        "{KEY_IMAGE_SIZE} must be [width, height] with positive whole numbers of pixels, got {0:?}"
    )]
    ImageSize(Vec<f32>),
    /// `layout` holds a code that is not 1, 2 or 3.
    #[error("{KEY_LAYOUT} code {0} is unknown (1 = h36m17, 2 = sh16, 3 = coco17)")]
    UnknownLayout(f32),
    /// The keypoints have a joint count that fits no layout.
    #[error("{KEY_KEYPOINTS} has {0} joints per frame; without a {KEY_LAYOUT} array only 17 (h36m17) or 16 (sh16) can be inferred")]
    UnknownJointCount(usize),
    /// The keypoints' joint count disagrees with the declared layout.
    #[error("{KEY_KEYPOINTS} has {joints} joints per frame but layout {layout} has {expected}")]
    LayoutMismatch {
        /// The layout.
        layout: KeypointLayout,
        /// Its joints.
        expected: usize,
        /// Joints in the file.
        joints: usize,
    },
    /// A value is NaN or infinite.
    #[error("{key}: frame {frame}, joint {joint} is not finite")]
    NonFinite {
        /// The array.
        key: &'static str,
        /// Frame index.
        frame: usize,
        /// Joint index.
        joint: usize,
    },
    /// A confidence is negative.
    #[error("{KEY_CONFIDENCE}: frame {frame}, joint {joint} is negative")]
    NegativeConfidence {
        /// Frame index.
        frame: usize,
        /// Joint index.
        joint: usize,
    },
    /// Some of the camera keys are present, but not all (or
    /// `camera_height` without them).
    #[error("{missing} is missing: {KEY_CAMERA_UP}, {KEY_CAMERA_FOCAL} and {KEY_CAMERA_PRINCIPAL} come together, and {KEY_CAMERA_HEIGHT} needs them (found {found})")]
    PartialCamera {
        /// The first absent key of [`CAMERA_KEYS`](super::CAMERA_KEYS).
        missing: &'static str,
        /// The camera keys present (`camera_height` included),
        /// comma-separated.
        found: String,
    },
    /// The subject keys have a bad value.
    #[error("{0}")]
    Subject(String),
    /// The camera calibration has a bad value.
    #[error("{key}: {error}")]
    Camera {
        /// The key at fault (`camera_up`, `camera_focal`, `camera_principal`,
        /// `camera_height` or `image_size`).
        key: &'static str,
        /// What is wrong.
        error: CameraError,
    },
    /// Results and sequence lengths disagree when writing.
    #[error("{poses} adjusted poses but {lengths} rows of bone lengths")]
    OutputMismatch {
        /// Poses.
        poses: usize,
        /// Length rows.
        lengths: usize,
    },
    /// Some but not all frames have a lifted pose when writing.
    #[error("{poses} adjusted poses but {lifted} lifted ones")]
    LiftedMismatch {
        /// Adjusted poses.
        poses: usize,
        /// Lifted poses.
        lifted: usize,
    },
}

/// `path: error`, without repeating the path when the npz error names it
/// already. The npz error is part of the message (not a `source()`), so
/// error chains print it once.
fn npz_message(path: &Path, error: &NpzError) -> String {
    let text = error.to_string();
    let shown = path.display().to_string();
    if text.contains(&shown) {
        text
    } else {
        format!("{shown}: {text}")
    }
}

/// An npz error from arrays not (yet) tied to a file.
pub(super) fn npz_err(error: NpzError) -> SequenceError {
    SequenceError::Npz {
        path: PathBuf::from("<arrays>"),
        error,
    }
}

//! One error type for every export: what was wrong with the request (no
//! poses, a non-finite pose, bad lengths, frame rate or axes) or with the
//! place it was to be written, named so a command line can print it as is.
//! Each message already holds its cause, so no variant has a `source`: a
//! printed error chain (anyhow's `{:#}`) says everything once.

use std::path::PathBuf;

use blapose_core::bones::BoneError;

/// Why a motion could not be exported.
#[derive(Debug, thiserror::Error)]
pub enum ExportError {
    /// The sequence holds no poses (an empty file, or a file without 3D poses).
    #[error("nothing to export: the sequence has no poses")]
    NoPoses,
    /// A pose could not be re-posed with the export's lengths: a non-finite
    /// coordinate or a zero-length bone (the error names frame and joint).
    #[error("cannot export: {0}")]
    Pose(BoneError),
    /// The bone lengths are not finite and `>= 0`.
    #[error("cannot export: {0}")]
    Lengths(BoneError),
    /// The frame rate is not finite and positive.
    #[error("cannot export: the frame rate must be finite and > 0, got {0}")]
    FrameRate(f64),
    /// The "up" direction is not finite or is zero.
    #[error("cannot export: up must be 3 finite values, not all zero, got {0:?}")]
    Up([f64; 3]),
    /// More frames than the format can hold.
    #[error("cannot export: {format} holds at most {max} frames, the sequence has {frames}")]
    TooManyFrames {
        /// The format.
        format: &'static str,
        /// Its limit.
        max: usize,
        /// The sequence's frame count.
        frames: usize,
    },
    /// Writing the output failed (the path names the file when there is one).
    #[error("cannot write {}: {cause}", path.display())]
    Io {
        /// The file (empty when writing to a stream).
        path: PathBuf,
        /// The operating system's error (in the message, so not also a
        /// `source`: error chains would print it twice).
        cause: std::io::Error,
    },
}

impl From<std::io::Error> for ExportError {
    fn from(cause: std::io::Error) -> Self {
        ExportError::Io {
            path: PathBuf::from("<stream>"),
            cause,
        }
    }
}

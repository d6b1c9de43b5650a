//! `POST /v1/export/{format}`: the live page's take as a file, written by
//! the writers the CLI and Python use, not a third copy in JavaScript.
//!
//! The page keeps what it sent and what came back (the keypoints, the
//! lifter's poses, the adjusted poses, the last bone lengths) and posts them
//! here as one JSON object ([`Take`]); the answer is the file: BVH, C3D or
//! TRC from [`blapose_export`] (the adjusted poses re-posed with the last
//! lengths, as `blapose-client --bvh` writes them), or the replay file
//! (`npz`: keypoints, confidence and the lifter's poses, which
//! `blapose-client replay` and Python's `load_replay` read back).
//!
//! The take is untrusted input: the bearer token is checked as for the
//! socket, at most [`EXPORTS_AT_ONCE`] are read and written at a time (more
//! get 503 before their body is read), the body is at most
//! [`MAX_TAKE_BYTES`] (the page's five minutes at 30 frames/s fit; 413), and every
//! array's length must agree with the frame count. Errors are
//! a status with one line of text naming what is wrong.

use std::collections::HashMap;
use std::io::Cursor;
use std::sync::Arc;

use axum::body::Body;
use axum::extract::{Path, Query, State};
use axum::http::{header, HeaderMap, StatusCode};
use axum::response::{IntoResponse, Response};
use blapose_core::layouts::{InputFormat, KeypointLayout};
use blapose_core::pose::poses_from_flat;
use blapose_core::{BoneLengths, NUM_BONES, NUM_JOINTS};
use blapose_data::replay::sequence::Sequence;
use blapose_export::{Format, Motion};
use serde::Deserialize;
use tokio::sync::Semaphore;

use crate::auth::BearerAuth;

use super::token::presented_token;

/// The largest take the page may post: 32 MB of JSON. The page keeps 5
/// minutes at 30 frames/s and rounds its numbers: about 12 MB.
pub const MAX_TAKE_BYTES: usize = 32 << 20;

/// Exports written at once; more are answered 503.
pub const EXPORTS_AT_ONCE: usize = 2;

/// A take as the page posts it: flat arrays, frame-major.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Take {
    /// Frames per second of the take.
    pub fps: f64,
    /// The keypoints' layout (`coco17`, `h36m17`, `sh16`).
    pub layout: String,
    /// The image's width and height in pixels (the keypoints are pixels).
    pub image_size: [u32; 2],
    /// `T x J x 2` keypoints, pixels.
    pub keypoints_2d: Vec<f32>,
    /// `T x J` confidences, or empty.
    #[serde(default)]
    pub confidence: Vec<f32>,
    /// `T x 17 x 3`: the lifter's poses (metres).
    pub pose_3d: Vec<f32>,
    /// `T x 17 x 3`: the adjusted poses the server answered (metres).
    pub adjusted: Vec<f32>,
    /// The 16 bone lengths of the last answer (metres).
    pub bone_lengths: Vec<f32>,
}

/// What can be wrong with a take.
#[derive(Debug, thiserror::Error)]
pub enum TakeError {
    /// Not the JSON of a take.
    #[error("the take is not valid JSON of the expected shape: {0}")]
    Json(#[from] serde_json::Error),
    /// An unknown format.
    #[error("unknown export format {0:?}: use bvh, c3d, trc or npz")]
    Format(String),
    /// An unknown layout.
    #[error("{0}")]
    Layout(String),
    /// No frames.
    #[error("the take has no frames")]
    Empty,
    /// Not one length per bone.
    #[error("the take's bone_lengths has {0} values, not {NUM_BONES}")]
    BoneLengths(usize),
    /// Arrays that disagree with the frame count.
    #[error("the take's {name} has {got} values, but {frames} frames need {want}")]
    Length {
        /// The array.
        name: &'static str,
        /// Its length.
        got: usize,
        /// Frames in the take.
        frames: usize,
        /// The length they need.
        want: usize,
    },
    /// The writers refused the motion (non-finite values, zero-length bones,
    /// a bad frame rate).
    #[error("{0}")]
    Export(#[from] blapose_export::ExportError),
    /// The replay file could not be written.
    #[error("{0}")]
    Replay(#[from] blapose_data::replay::SequenceError),
}

/// What the export route shares: the token rule and the writers' slots.
#[derive(Debug)]
pub struct Exports {
    auth: BearerAuth,
    slots: Semaphore,
}

impl Exports {
    /// Exports checked against `auth`.
    pub fn new(auth: BearerAuth) -> Self {
        Self {
            auth,
            slots: Semaphore::new(EXPORTS_AT_ONCE),
        }
    }
}

/// `POST /v1/export/{format}`.
pub async fn export(
    State(exports): State<Arc<Exports>>,
    Path(format): Path<String>,
    Query(query): Query<HashMap<String, String>>,
    headers: HeaderMap,
    body: Body,
) -> Response {
    if let Err(status) = exports.auth.check(
        presented_token(&headers, &query).as_deref(),
        "missing bearer token (send it as an authorization header or a `token` query parameter)",
    ) {
        return (StatusCode::UNAUTHORIZED, status.message().to_string()).into_response();
    }
    let Ok(_slot) = exports.slots.try_acquire() else {
        return (
            StatusCode::SERVICE_UNAVAILABLE,
            format!("{EXPORTS_AT_ONCE} exports are being written; retry in a moment"),
        )
            .into_response();
    };
    // The body is read only with a slot held: requests beyond the slots
    // cost no memory.
    let Ok(body) = axum::body::to_bytes(body, MAX_TAKE_BYTES).await else {
        return (
            StatusCode::PAYLOAD_TOO_LARGE,
            format!(
                "the take is over {} MB, or its upload failed",
                MAX_TAKE_BYTES >> 20
            ),
        )
            .into_response();
    };
    // Parsing and writing a take is milliseconds of CPU per thousand
    // frames: off the async workers.
    let written = tokio::task::spawn_blocking(move || write(&format, &body)).await;
    match written {
        Ok(Ok(Written {
            bytes,
            ext,
            content_type,
        })) => (
            [
                (header::CONTENT_TYPE, content_type.to_string()),
                (
                    header::CONTENT_DISPOSITION,
                    format!("attachment; filename=\"blapose-take.{ext}\""),
                ),
            ],
            bytes,
        )
            .into_response(),
        Ok(Err(e)) => (StatusCode::BAD_REQUEST, e.to_string()).into_response(),
        Err(e) => (
            StatusCode::INTERNAL_SERVER_ERROR,
            format!("export failed: {e}"),
        )
            .into_response(),
    }
}

/// A written take.
#[derive(Debug)]
pub struct Written {
    /// The file.
    pub bytes: Vec<u8>,
    /// Its extension.
    pub ext: &'static str,
    /// Its media type.
    pub content_type: &'static str,
}

/// The file of `take` (JSON) in `format`.
pub fn write(format: &str, take: &[u8]) -> Result<Written, TakeError> {
    let chosen = match format {
        "bvh" => Some(Format::Bvh),
        "c3d" => Some(Format::C3d),
        "trc" => Some(Format::Trc),
        "npz" => None,
        other => return Err(TakeError::Format(other.to_string())),
    };
    let take: Take = serde_json::from_slice(take)?;
    let layout: KeypointLayout = take
        .layout
        .parse()
        .map_err(|e: blapose_core::layouts::LayoutError| TakeError::Layout(e.to_string()))?;
    let joints = layout.num_joints();
    let frames = take.keypoints_2d.len() / (2 * joints);
    if frames == 0 {
        return Err(TakeError::Empty);
    }
    let check = |name, got: usize, per_frame: usize| {
        let want = frames * per_frame;
        (got == want).then_some(()).ok_or(TakeError::Length {
            name,
            got,
            frames,
            want,
        })
    };
    check("keypoints_2d", take.keypoints_2d.len(), 2 * joints)?;
    if !take.confidence.is_empty() {
        check("confidence", take.confidence.len(), joints)?;
    }
    check("pose_3d", take.pose_3d.len(), 3 * NUM_JOINTS)?;
    check("adjusted", take.adjusted.len(), 3 * NUM_JOINTS)?;
    let lengths: BoneLengths = take
        .bone_lengths
        .as_slice()
        .try_into()
        .map_err(|_| TakeError::BoneLengths(take.bone_lengths.len()))?;
    // The pose arrays' lengths are checked above: whole poses.
    let poses = |flat: &[f32]| poses_from_flat(flat).unwrap_or_default();
    let mut out = Vec::new();
    match chosen {
        Some(format) => {
            let motion = Motion::new(&poses(&take.adjusted), &lengths, take.fps)?;
            const TEXT: &str = "text/plain; charset=utf-8";
            let (ext, content_type) = match format {
                Format::Bvh => {
                    blapose_export::write_bvh(&motion, &mut out)?;
                    ("bvh", TEXT)
                }
                Format::C3d => {
                    blapose_export::write_c3d(&motion, &mut out)?;
                    ("c3d", "application/octet-stream")
                }
                Format::Trc => {
                    blapose_export::write_trc(&motion, &mut out, "blapose-take.trc")?;
                    ("trc", TEXT)
                }
            };
            Ok(Written {
                bytes: out,
                ext,
                content_type,
            })
        }
        None => {
            let [width, height] = take.image_size;
            let sequence = Sequence {
                input_format: InputFormat::pixels(layout, width, height),
                keypoints_2d: take.keypoints_2d,
                confidence: take.confidence,
                pose_3d: poses(&take.pose_3d),
                gt_3d: None,
                fps: Some(take.fps as f32),
                camera: None,
                subject: None,
            };
            let npz = sequence.to_npz()?;
            blapose_data::npz::write_npz_to(Cursor::new(&mut out), &npz, "<take>".as_ref())
                .map_err(|error| blapose_data::replay::SequenceError::Npz {
                    path: "<take>".into(),
                    error,
                })?;
            Ok(Written {
                bytes: out,
                ext: "npz",
                content_type: "application/zip",
            })
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A take of `frames` frames: a person standing, swaying.
    fn take(frames: usize) -> serde_json::Value {
        let pose: Vec<f32> = (0..frames)
            .flat_map(|t| {
                (0..NUM_JOINTS).flat_map(move |j| {
                    [
                        0.01 * t as f32 + 0.05 * j as f32,
                        -0.1 * j as f32,
                        3.0 + 0.02 * (j % 3) as f32,
                    ]
                })
            })
            .collect();
        let pose0: blapose_core::Pose = std::array::from_fn(|j| {
            [
                0.05 * j as f32,
                -0.1 * j as f32,
                3.0 + 0.02 * (j % 3) as f32,
            ]
        });
        serde_json::json!({
            "fps": 30.0,
            "layout": "coco17",
            "image_size": [640, 480],
            "keypoints_2d": vec![100.0f32; frames * 17 * 2],
            "confidence": vec![0.9f32; frames * 17],
            "pose_3d": pose,
            "adjusted": pose,
            "bone_lengths": blapose_core::bones::bone_lengths(&pose0).to_vec(),
        })
    }

    #[test]
    fn every_format_is_written_by_the_shared_writers() {
        let body = serde_json::to_vec(&take(12)).unwrap();
        let bvh = write("bvh", &body).unwrap();
        assert_eq!(bvh.ext, "bvh");
        let text = String::from_utf8(bvh.bytes).unwrap();
        assert!(text.starts_with("HIERARCHY"), "{}", &text[..40]);
        assert!(text.contains("Frames: 12"), "{text}");
        let c3d = write("c3d", &body).unwrap().bytes;
        assert_eq!(c3d[1], 0x50, "C3D's parameter-section key");
        let trc = write("trc", &body).unwrap().bytes;
        assert!(String::from_utf8(trc).unwrap().starts_with("PathFileType"));
        let npz = write("npz", &body).unwrap().bytes;
        let back = Sequence::read_from(Cursor::new(npz), "take.npz", None, 1000).unwrap();
        assert_eq!((back.pose_3d.len(), back.fps), (12, Some(30.0)));
        assert_eq!(back.input_format.layout, KeypointLayout::Coco17);
    }

    #[test]
    fn bad_takes_are_named() {
        let body = |v: serde_json::Value| serde_json::to_vec(&v).unwrap();
        let err = |format: &str, b: &[u8]| write(format, b).unwrap_err().to_string();
        assert!(err("gif", &body(take(2))).contains("unknown export format"));
        assert!(err("bvh", b"{").contains("not valid JSON"));
        let mut short = take(4);
        short["adjusted"] = serde_json::json!(vec![0.0f32; 3 * 17 * 3]);
        assert_eq!(
            err("bvh", &body(short)),
            "the take's adjusted has 153 values, but 4 frames need 204"
        );
        let mut none = take(1);
        none["keypoints_2d"] = serde_json::json!([]);
        assert_eq!(err("npz", &body(none)), "the take has no frames");
        let mut nan = take(3);
        nan["adjusted"][5] = serde_json::json!(null);
        assert!(err("bvh", &body(nan)).contains("not valid JSON"));
        let mut layout = take(2);
        layout["layout"] = serde_json::json!("openpose25");
        assert!(err("c3d", &body(layout)).contains("openpose25"));
    }
}

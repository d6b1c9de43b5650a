//! A recorded sequence: reading, checking and writing a replay file.
//!
//! [`Sequence`] is the file's content, validated; loading checks everything
//! a server would refuse and names the key, frame and joint, so a bad file
//! fails before any network traffic. [`FrameInput`] is one of its frames
//! as a session sends it.

use std::io::{Read, Seek};
use std::path::{Path, PathBuf};

use blapose_core::layouts::{Coordinates, InputFormat, KeypointLayout};
use blapose_core::missing::MISSING_CONFIDENCE;
use blapose_core::pose::poses_as_flat;
use blapose_core::skeleton::NUM_JOINTS;
use blapose_core::{Pose, Sex};

use super::camera::{CameraCalibration, CameraError};
use super::camera_keys::camera_from;
use super::error::{npz_err, SequenceError};
use super::keys::*;
use super::source::{scalar, ArraySource};
use super::subject::Subject;
use crate::npz::{check_declared_shape, write_npz, Array, Npz, NpzArchive};

/// The most frames [`Sequence::load`] accepts (an hour at 250 fps: about
/// 350 MB of keypoints and poses), as Python's `load_replay` does; every
/// per-frame array is bounded by it before any value is read.
/// [`Sequence::load_with_max_frames`] sets another.
pub const DEFAULT_MAX_FRAMES: usize = 900_000;

/// A recorded sequence, validated.
#[derive(Debug, Clone, PartialEq)]
pub struct Sequence {
    /// Layout and image size of the keypoints.
    pub input_format: InputFormat,
    /// `T * J * 2` keypoint values, frame-major then joint-major.
    pub keypoints_2d: Vec<f32>,
    /// Empty, or `T * J` confidences.
    pub confidence: Vec<f32>,
    /// The lifter's poses.
    pub pose_3d: Vec<Pose>,
    /// Ground truth in the same frame as `pose_3d`, if known.
    pub gt_3d: Option<Vec<Pose>>,
    /// Frame rate of the recording, if known.
    pub fps: Option<f32>,
    /// The camera's calibration, if known (sent to the server, which then
    /// serves the sequence with its camera-aware models). Its image size is
    /// the keypoints' (`None` or equal for pixel keypoints).
    pub camera: Option<CameraCalibration>,
    /// The person's stature (and sex), if known (`subject_height`,
    /// `subject_sex`; sent to the server, which then answers with the
    /// stature regression's lengths).
    pub subject: Option<Subject>,
}

/// One frame to send on a session.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameInput {
    /// Client's frame number, echoed back in the answer.
    pub frame_index: u64,
    /// 2D keypoints, `J` joints in the session's layout.
    pub keypoints_2d: Vec<[f32; 2]>,
    /// Optional per-joint confidence (empty or `J` values).
    pub confidence: Vec<f32>,
    /// The lifted 3D pose to adjust (metres, Human3.6M order); `None` in a
    /// session whose poses the server lifts (keypoints only).
    pub pose_3d: Option<Pose>,
}

/// The file's subject, if any.
fn subject_from(npz: &mut impl ArraySource) -> Result<Option<Subject>, SequenceError> {
    let bad = |what: String| SequenceError::Subject(what);
    if !npz.has(KEY_SUBJECT_HEIGHT) {
        if npz.has(KEY_SUBJECT_SEX) {
            return Err(bad(format!("{KEY_SUBJECT_SEX} needs {KEY_SUBJECT_HEIGHT}")));
        }
        return Ok(None);
    }
    let height_m = scalar(npz, KEY_SUBJECT_HEIGHT).map_err(npz_err)?;
    if !(height_m.is_finite() && height_m > 0.0) {
        return Err(bad(format!(
            "{KEY_SUBJECT_HEIGHT} is {height_m}; a stature in metres"
        )));
    }
    let sex = if npz.has(KEY_SUBJECT_SEX) {
        match scalar(npz, KEY_SUBJECT_SEX).map_err(npz_err)? {
            1.0 => Some(Sex::Female),
            2.0 => Some(Sex::Male),
            v => return Err(bad(format!("{KEY_SUBJECT_SEX} is {v}; 1 female or 2 male"))),
        }
    } else {
        None
    };
    Ok(Some(Subject { height_m, sex }))
}

/// The replay-file key of a calibration field.
fn camera_key(error: &CameraError) -> &'static str {
    match error.field() {
        "up" => KEY_CAMERA_UP,
        "focal" => KEY_CAMERA_FOCAL,
        "principal" => KEY_CAMERA_PRINCIPAL,
        "height" => KEY_CAMERA_HEIGHT,
        "distortion" => KEY_CAMERA_DISTORTION,
        _ => KEY_IMAGE_SIZE,
    }
}

fn first_non_finite(values: &[f32], per_frame: usize, per_joint: usize) -> Option<(usize, usize)> {
    values
        .iter()
        .position(|v| !v.is_finite())
        .map(|i| (i / per_frame, (i % per_frame) / per_joint))
}

impl Sequence {
    /// Number of frames.
    pub fn len(&self) -> usize {
        self.pose_3d.len()
    }

    /// Whether there are no frames (never true for a validated sequence).
    pub fn is_empty(&self) -> bool {
        self.pose_3d.is_empty()
    }

    /// Joints per keypoint frame.
    pub fn num_joints(&self) -> usize {
        self.input_format.layout.num_joints()
    }

    /// Frame `t` as a message for a session (`t < len()`).
    pub fn frame(&self, t: usize) -> FrameInput {
        FrameInput {
            pose_3d: Some(self.pose_3d[t]),
            ..self.keypoints_frame(t)
        }
    }

    /// Frame `t` without its pose, for a session whose poses the server
    /// lifts (`t < len()`).
    pub fn keypoints_frame(&self, t: usize) -> FrameInput {
        let j = self.num_joints();
        let kp = &self.keypoints_2d[t * j * 2..(t + 1) * j * 2];
        FrameInput {
            frame_index: t as u64,
            keypoints_2d: kp.chunks_exact(2).map(|c| [c[0], c[1]]).collect(),
            confidence: if self.confidence.is_empty() {
                Vec::new()
            } else {
                self.confidence[t * j..(t + 1) * j].to_vec()
            },
            pose_3d: None,
        }
    }

    /// Check every invariant the file format promises.
    pub fn validate(&self) -> Result<(), SequenceError> {
        let t = self.len();
        if t == 0 {
            return Err(SequenceError::Empty);
        }
        let j = self.num_joints();
        if let Coordinates::Pixels { width, height } = self.input_format.coordinates {
            if width == 0 || height == 0 {
                return Err(SequenceError::ImageSize(vec![width as f32, height as f32]));
            }
        }
        if self.keypoints_2d.len() != t * j * 2 {
            return Err(SequenceError::FrameCount {
                key: KEY_KEYPOINTS,
                got: self.keypoints_2d.len() / (j * 2),
                expected: t,
            });
        }
        // A missing joint's coordinates are not read (the server's rule),
        // so any value, NaN included, is fine there.
        let missing = |i: usize| {
            self.confidence
                .get(i / 2)
                .is_some_and(|&c| c < MISSING_CONFIDENCE)
        };
        if let Some((frame, joint)) = self
            .keypoints_2d
            .iter()
            .enumerate()
            .position(|(i, v)| !v.is_finite() && !missing(i))
            .map(|i| (i / (j * 2), (i % (j * 2)) / 2))
        {
            return Err(SequenceError::NonFinite {
                key: KEY_KEYPOINTS,
                frame,
                joint,
            });
        }
        if let Some((frame, joint)) =
            first_non_finite(poses_as_flat(&self.pose_3d), NUM_JOINTS * 3, 3)
        {
            return Err(SequenceError::NonFinite {
                key: KEY_POSE_3D,
                frame,
                joint,
            });
        }
        if let Some(gt) = &self.gt_3d {
            if gt.len() != t {
                return Err(SequenceError::FrameCount {
                    key: KEY_GT_3D,
                    got: gt.len(),
                    expected: t,
                });
            }
            if let Some((frame, joint)) = first_non_finite(poses_as_flat(gt), NUM_JOINTS * 3, 3) {
                return Err(SequenceError::NonFinite {
                    key: KEY_GT_3D,
                    frame,
                    joint,
                });
            }
        }
        if !self.confidence.is_empty() {
            if self.confidence.len() != t * j {
                return Err(SequenceError::FrameCount {
                    key: KEY_CONFIDENCE,
                    got: self.confidence.len() / j,
                    expected: t,
                });
            }
            if let Some((frame, joint)) = first_non_finite(&self.confidence, j, 1) {
                return Err(SequenceError::NonFinite {
                    key: KEY_CONFIDENCE,
                    frame,
                    joint,
                });
            }
            if let Some(i) = self.confidence.iter().position(|&c| c < 0.0) {
                return Err(SequenceError::NegativeConfidence {
                    frame: i / j,
                    joint: i % j,
                });
            }
        }
        if let Some(camera) = &self.camera {
            camera
                .validate_for(self.input_format.coordinates)
                .map_err(|error| SequenceError::Camera {
                    key: camera_key(&error),
                    error,
                })?;
        }
        Ok(())
    }

    /// Build from npz arrays; `layout_override` wins over the file's
    /// `layout` array and the inference from `J`. The arrays are in memory
    /// already, so no frame limit applies.
    pub fn from_npz(
        npz: &Npz,
        layout_override: Option<KeypointLayout>,
    ) -> Result<Self, SequenceError> {
        Self::from_source(&mut { npz }, layout_override, usize::MAX)
    }

    /// The frames of per-frame array `key` of shape `shape`, which must
    /// match `(_, rest..)` and hold at most `max_frames` frames.
    fn frames_of(
        key: &'static str,
        shape: &[usize],
        rest: &[Option<usize>],
        max_frames: usize,
    ) -> Result<usize, SequenceError> {
        let pattern: Vec<Option<usize>> = [None].into_iter().chain(rest.iter().copied()).collect();
        check_declared_shape(key, shape, &pattern).map_err(npz_err)?;
        if shape[0] > max_frames {
            return Err(SequenceError::TooManyFrames {
                key,
                frames: shape[0],
                max: max_frames,
            });
        }
        Ok(shape[0])
    }

    /// Build from `source`, checking every shape and frame count (at most
    /// `max_frames`) before reading any values.
    fn from_source(
        npz: &mut impl ArraySource,
        layout_override: Option<KeypointLayout>,
        max_frames: usize,
    ) -> Result<Self, SequenceError> {
        let pose_shape = npz.shape_of(KEY_POSE_3D).map_err(npz_err)?;
        let frames = Self::frames_of(
            KEY_POSE_3D,
            &pose_shape,
            &[Some(NUM_JOINTS), Some(3)],
            max_frames,
        )?;
        let kp_shape = npz.shape_of(KEY_KEYPOINTS).map_err(npz_err)?;
        let kp_frames = Self::frames_of(KEY_KEYPOINTS, &kp_shape, &[None, Some(2)], max_frames)?;
        let joints = kp_shape[1];
        if kp_frames != frames {
            return Err(SequenceError::FrameCount {
                key: KEY_KEYPOINTS,
                got: kp_frames,
                expected: frames,
            });
        }
        let layout = match layout_override {
            Some(l) => l,
            None if npz.has(KEY_LAYOUT) => {
                let code = scalar(npz, KEY_LAYOUT).map_err(npz_err)?;
                let valid = code.is_finite() && code.fract() == 0.0 && code >= 0.0;
                valid
                    .then(|| layout_from_code(code as u32))
                    .flatten()
                    .ok_or(SequenceError::UnknownLayout(code))?
            }
            None => match joints {
                17 => KeypointLayout::H36m17,
                16 => KeypointLayout::Sh16,
                j => return Err(SequenceError::UnknownJointCount(j)),
            },
        };
        if layout.num_joints() != joints {
            return Err(SequenceError::LayoutMismatch {
                layout,
                expected: layout.num_joints(),
                joints,
            });
        }
        let size_shape = npz.shape_of(KEY_IMAGE_SIZE).map_err(npz_err)?;
        check_declared_shape(KEY_IMAGE_SIZE, &size_shape, &[Some(2)]).map_err(npz_err)?;
        let gt_shape = if npz.has(KEY_GT_3D) {
            let shape = npz.shape_of(KEY_GT_3D).map_err(npz_err)?;
            let got = Self::frames_of(KEY_GT_3D, &shape, &[Some(NUM_JOINTS), Some(3)], max_frames)?;
            if got != frames {
                return Err(SequenceError::FrameCount {
                    key: KEY_GT_3D,
                    got,
                    expected: frames,
                });
            }
            Some(shape)
        } else {
            None
        };
        let confidence_shape = if npz.has(KEY_CONFIDENCE) {
            let shape = npz.shape_of(KEY_CONFIDENCE).map_err(npz_err)?;
            let got = Self::frames_of(KEY_CONFIDENCE, &shape, &[Some(joints)], max_frames)?;
            if got != frames {
                return Err(SequenceError::FrameCount {
                    key: KEY_CONFIDENCE,
                    got,
                    expected: frames,
                });
            }
            Some(shape)
        } else {
            None
        };
        // Every shape is known and bounded: now the values.
        let size = npz.read(KEY_IMAGE_SIZE, &size_shape).map_err(npz_err)?;
        let size = size.data();
        let whole = |v: f32| v.is_finite() && v >= 1.0 && v.fract() == 0.0 && v <= u32::MAX as f32;
        if !size.iter().all(|&v| whole(v)) {
            return Err(SequenceError::ImageSize(size.to_vec()));
        }
        let image_size = (size[0] as u32, size[1] as u32);
        let input_format = InputFormat::pixels(layout, image_size.0, image_size.1);
        let pose_3d = npz
            .read(KEY_POSE_3D, &pose_shape)
            .and_then(|a| a.to_frames(KEY_POSE_3D))
            .map_err(npz_err)?;
        let (_, keypoints_2d) = npz
            .read(KEY_KEYPOINTS, &kp_shape)
            .map_err(npz_err)?
            .into_parts();
        let gt_3d = match gt_shape {
            Some(shape) => Some(
                npz.read(KEY_GT_3D, &shape)
                    .and_then(|a| a.to_frames(KEY_GT_3D))
                    .map_err(npz_err)?,
            ),
            None => None,
        };
        let confidence = match confidence_shape {
            Some(shape) => {
                npz.read(KEY_CONFIDENCE, &shape)
                    .map_err(npz_err)?
                    .into_parts()
                    .1
            }
            None => Vec::new(),
        };
        let fps = if npz.has(KEY_FPS) {
            Some(scalar(npz, KEY_FPS).map_err(npz_err)?)
        } else {
            None
        };
        let camera = camera_from(npz, image_size)?;
        let subject = subject_from(npz)?;
        let seq = Sequence {
            input_format,
            keypoints_2d,
            confidence,
            pose_3d,
            gt_3d,
            fps,
            camera,
            subject,
        };
        seq.validate()?;
        Ok(seq)
    }

    /// Read and validate a replay file of at most [`DEFAULT_MAX_FRAMES`]
    /// frames (see [`Sequence::load_with_max_frames`]).
    pub fn load(
        path: impl AsRef<Path>,
        layout_override: Option<KeypointLayout>,
    ) -> Result<Self, SequenceError> {
        Self::load_with_max_frames(path, layout_override, DEFAULT_MAX_FRAMES)
    }

    /// Read and validate a replay file of at most `max_frames` frames.
    ///
    /// A replay file may come from anywhere, so only the format's members
    /// are opened, each one's header is checked (shape, frames against
    /// `max_frames` and the other arrays) before its values are read, and a
    /// member is never inflated past what its checked shape needs: the
    /// memory used is about that of the arrays returned, whatever the file
    /// declares.
    pub fn load_with_max_frames(
        path: impl AsRef<Path>,
        layout_override: Option<KeypointLayout>,
        max_frames: usize,
    ) -> Result<Self, SequenceError> {
        let path = path.as_ref();
        let archive = NpzArchive::open(path).map_err(|error| SequenceError::Npz {
            path: path.to_owned(),
            error,
        })?;
        Self::from_archive(archive, layout_override, max_frames)
    }

    /// Read and validate a replay file from `reader` (e.g. bytes in
    /// memory), `name` naming it in errors, as
    /// [`Sequence::load_with_max_frames`] reads a file.
    pub fn read_from<R: Read + Seek>(
        reader: R,
        name: impl Into<PathBuf>,
        layout_override: Option<KeypointLayout>,
        max_frames: usize,
    ) -> Result<Self, SequenceError> {
        let name = name.into();
        let archive = NpzArchive::new(reader, &name).map_err(|error| SequenceError::Npz {
            path: name.clone(),
            error,
        })?;
        Self::from_archive(archive, layout_override, max_frames)
    }

    fn from_archive<R: Read + Seek>(
        mut archive: NpzArchive<R>,
        layout_override: Option<KeypointLayout>,
        max_frames: usize,
    ) -> Result<Self, SequenceError> {
        let path = archive.path().to_owned();
        Sequence::from_source(&mut archive, layout_override, max_frames).map_err(|e| match e {
            SequenceError::Npz { error, .. } => SequenceError::Npz { path, error },
            e => e,
        })
    }

    /// The arrays of this sequence in the replay format.
    pub fn to_npz(&self) -> Result<Npz, SequenceError> {
        let npz_err = |source| SequenceError::Npz {
            path: PathBuf::from("<arrays>"),
            error: source,
        };
        let t = self.len();
        let j = self.num_joints();
        let mut npz = Npz::new();
        npz.insert(
            KEY_KEYPOINTS,
            Array::new(vec![t, j, 2], self.keypoints_2d.clone()).map_err(npz_err)?,
        );
        npz.insert(KEY_POSE_3D, Array::from_poses(&self.pose_3d));
        if let Coordinates::Pixels { width, height } = self.input_format.coordinates {
            npz.insert(
                KEY_IMAGE_SIZE,
                Array::new(vec![2], vec![width as f32, height as f32]).map_err(npz_err)?,
            );
        }
        npz.insert(
            KEY_LAYOUT,
            Array::new(vec![1], vec![layout_code(self.input_format.layout) as f32])
                .map_err(npz_err)?,
        );
        if let Some(gt) = &self.gt_3d {
            npz.insert(KEY_GT_3D, Array::from_poses(gt));
        }
        if !self.confidence.is_empty() {
            npz.insert(
                KEY_CONFIDENCE,
                Array::new(vec![t, j], self.confidence.clone()).map_err(npz_err)?,
            );
        }
        if let Some(fps) = self.fps {
            npz.insert(KEY_FPS, Array::new(vec![1], vec![fps]).map_err(npz_err)?);
        }
        if let Some(c) = &self.camera {
            npz.insert(
                KEY_CAMERA_UP,
                Array::new(vec![3], c.up.to_vec()).map_err(npz_err)?,
            );
            npz.insert(
                KEY_CAMERA_FOCAL,
                Array::new(vec![2], c.focal.to_vec()).map_err(npz_err)?,
            );
            npz.insert(
                KEY_CAMERA_PRINCIPAL,
                Array::new(vec![2], c.principal.to_vec()).map_err(npz_err)?,
            );
            if let Some(height) = c.height {
                npz.insert(
                    KEY_CAMERA_HEIGHT,
                    Array::new(vec![1], vec![height]).map_err(npz_err)?,
                );
            }
            if let Some(distortion) = c.distortion {
                npz.insert(
                    KEY_CAMERA_DISTORTION,
                    Array::new(vec![5], distortion.to_vec()).map_err(npz_err)?,
                );
            }
        }
        if let Some(subject) = &self.subject {
            npz.insert(
                KEY_SUBJECT_HEIGHT,
                Array::new(vec![1], vec![subject.height_m]).map_err(npz_err)?,
            );
            if let Some(sex) = subject.sex {
                let code = match sex {
                    Sex::Female => 1.0,
                    Sex::Male => 2.0,
                };
                npz.insert(
                    KEY_SUBJECT_SEX,
                    Array::new(vec![1], vec![code]).map_err(npz_err)?,
                );
            }
        }
        Ok(npz)
    }

    /// Validate and write as a replay file.
    pub fn save(&self, path: impl AsRef<Path>) -> Result<(), SequenceError> {
        self.validate()?;
        let path = path.as_ref();
        write_npz(path, &self.to_npz()?).map_err(|source| SequenceError::Npz {
            path: path.to_owned(),
            error: source,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::npz::read_npz;
    use crate::replay::output::{read_adjusted, read_lifted, write_adjusted};
    use blapose_core::skeleton::NUM_BONES;

    fn pose(t: usize) -> Pose {
        std::array::from_fn(|j| [0.01 * j as f32, 0.1 * j as f32 + t as f32 * 1e-3, 0.02])
    }

    fn npz(frames: usize, joints: usize) -> Npz {
        let mut npz = Npz::new();
        let kp: Vec<f32> = (0..frames * joints * 2).map(|i| (i % 997) as f32).collect();
        npz.insert(
            KEY_KEYPOINTS,
            Array::new(vec![frames, joints, 2], kp).unwrap(),
        );
        let poses: Vec<Pose> = (0..frames).map(pose).collect();
        npz.insert(KEY_POSE_3D, Array::from_poses(&poses));
        npz.insert(
            KEY_IMAGE_SIZE,
            Array::new(vec![2], vec![1000.0, 1002.0]).unwrap(),
        );
        npz
    }

    #[test]
    fn layout_is_inferred_from_joint_count() {
        let s = Sequence::from_npz(&npz(3, 17), None).unwrap();
        assert_eq!(
            s.input_format,
            InputFormat::pixels(KeypointLayout::H36m17, 1000, 1002)
        );
        let s = Sequence::from_npz(&npz(3, 16), None).unwrap();
        assert_eq!(s.input_format.layout, KeypointLayout::Sh16);
        assert_eq!(s.frame(2).keypoints_2d.len(), 16);
        assert_eq!(s.frame(1).keypoints_2d[0], [32.0, 33.0]);
        let e = Sequence::from_npz(&npz(3, 15), None).unwrap_err();
        assert!(matches!(e, SequenceError::UnknownJointCount(15)), "{e}");
    }

    #[test]
    fn layout_code_and_override() {
        let mut n = npz(2, 17);
        n.insert(KEY_LAYOUT, Array::new(vec![1], vec![3.0]).unwrap());
        assert_eq!(
            Sequence::from_npz(&n, None).unwrap().input_format.layout,
            KeypointLayout::Coco17
        );
        assert_eq!(
            Sequence::from_npz(&n, Some(KeypointLayout::H36m17))
                .unwrap()
                .input_format
                .layout,
            KeypointLayout::H36m17
        );
        n.insert(KEY_LAYOUT, Array::new(vec![], vec![2.0]).unwrap());
        let e = Sequence::from_npz(&n, None).unwrap_err();
        assert!(
            matches!(
                e,
                SequenceError::LayoutMismatch {
                    expected: 16,
                    joints: 17,
                    ..
                }
            ),
            "{e}"
        );
        n.insert(KEY_LAYOUT, Array::new(vec![1], vec![7.0]).unwrap());
        assert!(matches!(
            Sequence::from_npz(&n, None),
            Err(SequenceError::UnknownLayout(_))
        ));
        n.insert(KEY_LAYOUT, Array::new(vec![1], vec![1.5]).unwrap());
        assert!(matches!(
            Sequence::from_npz(&n, None),
            Err(SequenceError::UnknownLayout(_))
        ));
    }

    #[test]
    fn missing_keys_and_shapes_are_named() {
        let mut n = npz(2, 17);
        n.remove(KEY_IMAGE_SIZE).unwrap();
        let e = Sequence::from_npz(&n, None).unwrap_err().to_string();
        assert!(e.contains("image_size"), "{e}");
        let mut n = npz(2, 17);
        n.insert(
            KEY_POSE_3D,
            Array::new(vec![2, 16, 3], vec![0.0; 96]).unwrap(),
        );
        let e = Sequence::from_npz(&n, None).unwrap_err().to_string();
        assert!(e.contains("pose_3d") && e.contains("(_, 17, 3)"), "{e}");
        let mut n = npz(2, 17);
        n.insert(
            KEY_KEYPOINTS,
            Array::new(vec![3, 17, 2], vec![0.0; 102]).unwrap(),
        );
        let e = Sequence::from_npz(&n, None).unwrap_err();
        assert!(
            matches!(
                e,
                SequenceError::FrameCount {
                    got: 3,
                    expected: 2,
                    ..
                }
            ),
            "{e}"
        );
        let mut n = npz(2, 17);
        n.insert(KEY_GT_3D, Array::from_poses(&[pose(0)]));
        assert!(matches!(
            Sequence::from_npz(&n, None),
            Err(SequenceError::FrameCount { key: KEY_GT_3D, .. })
        ));
        let n = npz(0, 17);
        assert!(matches!(
            Sequence::from_npz(&n, None),
            Err(SequenceError::Empty)
        ));
    }

    #[test]
    fn a_subject_round_trips_and_bad_ones_are_refused() {
        let mut n = npz(2, 17);
        assert_eq!(Sequence::from_npz(&n, None).unwrap().subject, None);
        n.insert(KEY_SUBJECT_HEIGHT, Array::new(vec![1], vec![1.74]).unwrap());
        n.insert(KEY_SUBJECT_SEX, Array::new(vec![1], vec![1.0]).unwrap());
        let s = Sequence::from_npz(&n, None).unwrap();
        let want = Subject {
            height_m: 1.74,
            sex: Some(Sex::Female),
        };
        assert_eq!(s.subject, Some(want));
        let back = Sequence::from_npz(&s.to_npz().unwrap(), None).unwrap();
        assert_eq!(back.subject, Some(want));
        n.insert(KEY_SUBJECT_SEX, Array::new(vec![1], vec![3.0]).unwrap());
        assert!(matches!(
            Sequence::from_npz(&n, None),
            Err(SequenceError::Subject(_))
        ));
        let mut n = npz(2, 17);
        n.insert(KEY_SUBJECT_SEX, Array::new(vec![1], vec![2.0]).unwrap());
        let e = Sequence::from_npz(&n, None).unwrap_err();
        assert!(e.to_string().contains(KEY_SUBJECT_HEIGHT), "{e}");
    }

    #[test]
    fn bad_values_are_refused() {
        for size in [
            vec![0.0, 10.0],
            vec![-5.0, 10.0],
            vec![10.5, 10.0],
            vec![f32::NAN, 1.0],
        ] {
            let mut n = npz(2, 17);
            n.insert(KEY_IMAGE_SIZE, Array::new(vec![2], size).unwrap());
            assert!(matches!(
                Sequence::from_npz(&n, None),
                Err(SequenceError::ImageSize(_))
            ));
        }
        let mut n = npz(2, 17);
        let mut poses: Vec<Pose> = (0..2).map(pose).collect();
        poses[1][5][2] = f32::INFINITY;
        n.insert(KEY_POSE_3D, Array::from_poses(&poses));
        let e = Sequence::from_npz(&n, None).unwrap_err();
        assert!(
            matches!(
                e,
                SequenceError::NonFinite {
                    key: KEY_POSE_3D,
                    frame: 1,
                    joint: 5
                }
            ),
            "{e}"
        );
        let mut n = npz(2, 17);
        let mut kp = vec![1.0; 2 * 17 * 2];
        kp[34 + 2 * 4 + 1] = f32::NAN;
        n.insert(KEY_KEYPOINTS, Array::new(vec![2, 17, 2], kp).unwrap());
        let e = Sequence::from_npz(&n, None).unwrap_err();
        assert!(
            matches!(
                e,
                SequenceError::NonFinite {
                    key: KEY_KEYPOINTS,
                    frame: 1,
                    joint: 4
                }
            ),
            "{e}"
        );
        // The same NaN on a missing joint (confidence below 0.1) is fine:
        // its keypoint is not read.
        let mut c = vec![0.9; 34];
        c[17 + 4] = 0.05;
        n.insert(KEY_CONFIDENCE, Array::new(vec![2, 17], c).unwrap());
        assert!(Sequence::from_npz(&n, None).is_ok());
        let mut n = npz(2, 17);
        let mut c = vec![0.5; 34];
        c[20] = -1.0;
        n.insert(KEY_CONFIDENCE, Array::new(vec![2, 17], c).unwrap());
        let e = Sequence::from_npz(&n, None).unwrap_err();
        assert!(
            matches!(e, SequenceError::NegativeConfidence { frame: 1, joint: 3 }),
            "{e}"
        );
    }

    fn with_camera(mut n: Npz) -> Npz {
        n.insert(
            KEY_CAMERA_UP,
            Array::new(vec![3], vec![0.02, -0.97, 0.24]).unwrap(),
        );
        n.insert(
            KEY_CAMERA_FOCAL,
            Array::new(vec![2], vec![1150.0, 1148.5]).unwrap(),
        );
        n.insert(
            KEY_CAMERA_PRINCIPAL,
            Array::new(vec![2], vec![500.0, 501.0]).unwrap(),
        );
        n
    }

    #[test]
    fn camera_keys_load_and_round_trip() {
        let s = Sequence::from_npz(&npz(2, 17), None).unwrap();
        assert_eq!(s.camera, None, "no camera keys, no calibration");
        assert!(CAMERA_KEYS.iter().all(|k| !s.to_npz().unwrap().contains(k)));

        let s = Sequence::from_npz(&with_camera(npz(3, 17)), None).unwrap();
        let expected = CameraCalibration {
            up: [0.02, -0.97, 0.24],
            focal: [1150.0, 1148.5],
            principal: [500.0, 501.0],
            image_size: Some((1000, 1002)),
            height: None,
            distortion: None,
        };
        assert_eq!(s.camera, Some(expected));
        assert!(!s.to_npz().unwrap().contains(KEY_CAMERA_HEIGHT));
        let arrays = s.to_npz().unwrap();
        assert_eq!(arrays.get(KEY_CAMERA_UP).unwrap().shape(), &[3]);
        assert_eq!(
            arrays.get(KEY_CAMERA_UP).unwrap().data(),
            &[0.02, -0.97, 0.24]
        );
        assert_eq!(
            arrays.get(KEY_CAMERA_FOCAL).unwrap().data(),
            &[1150.0, 1148.5]
        );
        assert_eq!(
            arrays.get(KEY_CAMERA_PRINCIPAL).unwrap().data(),
            &[500.0, 501.0]
        );

        let dir = std::env::temp_dir().join(format!("blapose-replay-cam-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("cam.npz");
        s.save(&path).unwrap();
        let back = Sequence::load(&path, None).unwrap();
        assert_eq!(back, s);
        assert_eq!(back.camera, Some(expected));
        // A calibration set in code is saved and read back the same.
        let mut other = Sequence::from_npz(&npz(2, 16), None).unwrap();
        other.camera = Some(CameraCalibration {
            up: [0.0, -1.0, 0.0],
            ..expected
        });
        other.save(&path).unwrap();
        assert_eq!(Sequence::load(&path, None).unwrap(), other);
        std::fs::remove_dir_all(&dir).ok();
    }

    fn with_height(mut n: Npz, shape: Vec<usize>, height: f32) -> Npz {
        n.insert(KEY_CAMERA_HEIGHT, Array::new(shape, vec![height]).unwrap());
        n
    }

    #[test]
    fn camera_height_loads_and_round_trips() {
        for shape in [vec![1], vec![]] {
            let n = with_height(with_camera(npz(3, 17)), shape.clone(), 1.4);
            let s = Sequence::from_npz(&n, None).unwrap();
            let cal = s.camera.expect("a calibration");
            assert_eq!(cal.height, Some(1.4), "shape {shape:?}");
            assert_eq!(cal.up, [0.02, -0.97, 0.24]);
            let arrays = s.to_npz().unwrap();
            let h = arrays.get(KEY_CAMERA_HEIGHT).unwrap();
            assert_eq!((h.shape(), h.data()), (&[1][..], &[1.4][..]));
            assert_eq!(Sequence::from_npz(&arrays, None).unwrap(), s);
        }

        let dir =
            std::env::temp_dir().join(format!("blapose-replay-height-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("height.npz");
        let s =
            Sequence::from_npz(&with_height(with_camera(npz(2, 17)), vec![], 2.25), None).unwrap();
        s.save(&path).unwrap();
        let back = Sequence::load(&path, None).unwrap();
        assert_eq!(back, s);
        assert_eq!(back.camera.unwrap().height, Some(2.25));
        // A height set in code is written; clearing it drops the key.
        let mut other = s.clone();
        other.camera = other.camera.map(|c| CameraCalibration {
            height: Some(0.75),
            ..c
        });
        other.save(&path).unwrap();
        assert_eq!(Sequence::load(&path, None).unwrap(), other);
        other.camera = other
            .camera
            .map(|c| CameraCalibration { height: None, ..c });
        other.save(&path).unwrap();
        assert!(!read_npz(&path).unwrap().contains(KEY_CAMERA_HEIGHT));
        assert_eq!(Sequence::load(&path, None).unwrap(), other);
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn camera_distortion_loads_pads_and_round_trips() {
        let mut n = with_camera(npz(3, 17));
        n.insert(
            KEY_CAMERA_DISTORTION,
            Array::new(vec![4], vec![-0.2, 0.05, 0.001, -0.002]).unwrap(),
        );
        let s = Sequence::from_npz(&n, None).unwrap();
        let cal = s.camera.expect("a calibration");
        assert_eq!(cal.distortion, Some([-0.2, 0.05, 0.001, -0.002, 0.0]));
        let arrays = s.to_npz().unwrap();
        assert_eq!(arrays.get(KEY_CAMERA_DISTORTION).unwrap().shape(), &[5]);
        assert_eq!(Sequence::from_npz(&arrays, None).unwrap(), s);
        // Three values are no OpenCV model: a shape error naming the key.
        n.insert(
            KEY_CAMERA_DISTORTION,
            Array::new(vec![3], vec![-0.2, 0.05, 0.001]).unwrap(),
        );
        let e = Sequence::from_npz(&n, None).unwrap_err().to_string();
        assert!(e.contains(KEY_CAMERA_DISTORTION), "{e}");
        // Alone it needs the calibration, like the height.
        let mut alone = npz(2, 17);
        alone.insert(
            KEY_CAMERA_DISTORTION,
            Array::new(vec![4], vec![-0.2, 0.05, 0.0, 0.0]).unwrap(),
        );
        assert!(matches!(
            Sequence::from_npz(&alone, None),
            Err(SequenceError::PartialCamera {
                missing: KEY_CAMERA_UP,
                ..
            })
        ));
    }

    #[test]
    fn camera_height_without_the_calibration_is_refused() {
        // Alone: the first calibration key is named, the height as found.
        let n = with_height(npz(2, 17), vec![1], 1.4);
        let e = Sequence::from_npz(&n, None).unwrap_err();
        assert!(
            matches!(&e, SequenceError::PartialCamera { missing: KEY_CAMERA_UP, found } if found == KEY_CAMERA_HEIGHT),
            "{e}"
        );
        let text = e.to_string();
        assert!(
            text.starts_with("camera_up is missing") && text.contains("found camera_height"),
            "{text}"
        );
        // With some of the three: the first absent one is named.
        for missing in CAMERA_KEYS {
            let mut n = with_height(with_camera(npz(2, 17)), vec![1], 1.4);
            n.remove(missing).unwrap();
            let e = Sequence::from_npz(&n, None).unwrap_err();
            assert!(
                matches!(&e, SequenceError::PartialCamera { missing: m, found } if *m == missing && found.contains(KEY_CAMERA_HEIGHT)),
                "{e}"
            );
        }
    }

    #[test]
    fn bad_camera_heights_are_refused_naming_the_key() {
        for height in [f32::NAN, f32::INFINITY, 0.1, 50.0, 0.0, -1.4] {
            let n = with_height(with_camera(npz(2, 17)), vec![1], height);
            let e = Sequence::from_npz(&n, None).unwrap_err();
            assert!(
                matches!(&e, SequenceError::Camera { key: KEY_CAMERA_HEIGHT, error } if error.field() == "height"),
                "{height}: {e}"
            );
            assert!(e.to_string().starts_with("camera_height: "), "{e}");
        }
        // Wrong shape: an npz error naming the key.
        let mut n = with_camera(npz(2, 17));
        n.insert(
            KEY_CAMERA_HEIGHT,
            Array::new(vec![2], vec![1.4, 1.5]).unwrap(),
        );
        let e = Sequence::from_npz(&n, None).unwrap_err().to_string();
        assert!(e.contains("camera_height") && e.contains("(1,)"), "{e}");
        // A bad height set in code is refused before writing.
        let mut s = Sequence::from_npz(&with_camera(npz(2, 17)), None).unwrap();
        s.camera = s.camera.map(|c| CameraCalibration {
            height: Some(50.0),
            ..c
        });
        assert!(matches!(
            s.validate(),
            Err(SequenceError::Camera {
                key: KEY_CAMERA_HEIGHT,
                error: CameraError::Height(_)
            })
        ));
    }

    #[test]
    fn a_partial_camera_is_refused_naming_the_missing_key() {
        for missing in CAMERA_KEYS {
            let mut n = with_camera(npz(2, 17));
            n.remove(missing).unwrap();
            let e = Sequence::from_npz(&n, None).unwrap_err();
            assert!(
                matches!(&e, SequenceError::PartialCamera { missing: m, .. } if *m == missing),
                "{e}"
            );
            assert!(e.to_string().starts_with(missing), "{e}");
        }
        // Only one key present: the first absent one is named.
        let mut n = npz(2, 17);
        n.insert(
            KEY_CAMERA_PRINCIPAL,
            Array::new(vec![2], vec![500.0, 500.0]).unwrap(),
        );
        let e = Sequence::from_npz(&n, None).unwrap_err().to_string();
        assert!(
            e.contains("camera_up is missing") && e.contains("found camera_principal"),
            "{e}"
        );
    }

    #[test]
    fn bad_camera_values_are_refused_naming_the_key() {
        let cases: [(&str, Vec<f32>, &str); 8] = [
            (KEY_CAMERA_FOCAL, vec![0.0, 1150.0], KEY_CAMERA_FOCAL),
            (KEY_CAMERA_FOCAL, vec![1150.0, -1.0], KEY_CAMERA_FOCAL),
            (KEY_CAMERA_FOCAL, vec![f32::NAN, 1150.0], KEY_CAMERA_FOCAL),
            (
                KEY_CAMERA_FOCAL,
                vec![f32::INFINITY, 1150.0],
                KEY_CAMERA_FOCAL,
            ),
            (KEY_CAMERA_UP, vec![0.0, f32::NAN, 0.0], KEY_CAMERA_UP),
            (KEY_CAMERA_UP, vec![0.0, 0.0, 0.0], KEY_CAMERA_UP),
            (
                KEY_CAMERA_PRINCIPAL,
                vec![500.0, f32::NEG_INFINITY],
                KEY_CAMERA_PRINCIPAL,
            ),
            (
                KEY_CAMERA_PRINCIPAL,
                vec![f32::NAN, 500.0],
                KEY_CAMERA_PRINCIPAL,
            ),
        ];
        for (key, values, named) in cases {
            let mut n = with_camera(npz(2, 17));
            n.insert(key, Array::new(vec![values.len()], values.clone()).unwrap());
            let e = Sequence::from_npz(&n, None).unwrap_err();
            assert!(
                matches!(&e, SequenceError::Camera { key: k, .. } if *k == named),
                "{key} = {values:?}: {e}"
            );
            assert!(e.to_string().starts_with(named), "{e}");
        }
        // Wrong shapes are npz errors naming the key.
        let mut n = with_camera(npz(2, 17));
        n.insert(KEY_CAMERA_UP, Array::new(vec![2], vec![0.0, -1.0]).unwrap());
        let e = Sequence::from_npz(&n, None).unwrap_err().to_string();
        assert!(e.contains("camera_up") && e.contains("(3)"), "{e}");
        // A calibration set in code must match the keypoints' image.
        let mut s = Sequence::from_npz(&with_camera(npz(2, 17)), None).unwrap();
        s.camera = s.camera.map(|c| CameraCalibration {
            image_size: Some((1002, 1000)),
            ..c
        });
        assert!(matches!(
            s.validate(),
            Err(SequenceError::Camera {
                key: KEY_IMAGE_SIZE,
                error: CameraError::ImageSizeMismatch { .. }
            })
        ));
        assert!(s
            .save(std::env::temp_dir().join("never-written.npz"))
            .is_err());
    }

    #[test]
    fn save_load_round_trip_and_outputs() {
        let dir = std::env::temp_dir().join(format!("blapose-replay-seq-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let mut seq = Sequence::from_npz(&npz(4, 16), None).unwrap();
        seq.gt_3d = Some(seq.pose_3d.clone());
        seq.fps = Some(50.0);
        seq.confidence = vec![0.9; 4 * 16];
        let path = dir.join("seq.npz");
        seq.save(&path).unwrap();
        assert_eq!(Sequence::load(&path, None).unwrap(), seq);

        let out = dir.join("out.npz");
        let lengths = vec![[0.25f32; NUM_BONES]; 4];
        write_adjusted(&out, &seq.pose_3d, &lengths, &[]).unwrap();
        let (a, l) = read_adjusted(&out).unwrap();
        assert_eq!((a, l), (seq.pose_3d.clone(), lengths.clone()));
        assert_eq!(
            read_lifted(&out).unwrap(),
            None,
            "client poses: no lifted_3d"
        );
        assert!(matches!(
            write_adjusted(&out, &seq.pose_3d, &[], &[]),
            Err(SequenceError::OutputMismatch { .. })
        ));
        // A server lifter's poses are written beside the adjusted ones.
        let lifted: Vec<Pose> = (10..14).map(pose).collect();
        write_adjusted(&out, &seq.pose_3d, &lengths, &lifted).unwrap();
        assert_eq!(read_lifted(&out).unwrap(), Some(lifted.clone()));
        assert_eq!(read_adjusted(&out).unwrap().0, seq.pose_3d);
        assert!(matches!(
            write_adjusted(&out, &seq.pose_3d, &lengths, &lifted[..3]),
            Err(SequenceError::LiftedMismatch {
                poses: 4,
                lifted: 3
            })
        ));
        let e = Sequence::load(dir.join("absent.npz"), None)
            .unwrap_err()
            .to_string();
        assert!(e.contains("absent.npz"), "{e}");
        std::fs::remove_dir_all(&dir).ok();
    }
}

//! Human3.6M as the trainer and the evaluator need it.
//!
//! Training sees the **training subjects only**: [`TrainingSet::load`] has
//! no subject argument, it reads [`TRAIN_SUBJECTS`] (S1 S5 S6 S7 S8), so no
//! test statistic can reach a length sampler, the ANSUR calibration or the
//! residual bank by accident. Evaluation inputs ([`EvalSequence`]) are built
//! for any subject list: the real Stacked Hourglass detections converted to
//! the 17 Human3.6M joints ([`KeypointLayout::Sh16`]) or the ground truth
//! projected with the real camera, both in normalized screen coordinates.

use std::collections::BTreeMap;
use std::path::Path;
use std::sync::Arc;

use blapose_core::bones::{decompose, mean_bone_lengths};
use blapose_core::camera::{normalize_keypoints, Camera};
use blapose_core::layouts::KeypointLayout;
use blapose_core::pose::flip_bone_lengths;
use blapose_core::{BoneLengths, Keypoints2d, Pose};
use blapose_data::h36m::{H36m, Parts, ShKeypoints};
pub use blapose_data::h36m::{TEST_SUBJECTS, TRAIN_SUBJECTS};
use blapose_model::input::{ModelInput, ViewCalibration};
use rayon::prelude::*;

use crate::error::TrainError;
use crate::noise::{metric_residual, MetricResidual, ResidualBank};
use crate::synth::MotionSequence;

/// Which 2D input an evaluation feeds the model (`--input`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, clap::ValueEnum)]
pub enum InputKind {
    /// Real Stacked Hourglass detections mapped to 17 joints.
    Sh,
    /// Ground-truth 3D projected with the real camera (with distortion).
    Gt,
}

impl InputKind {
    /// Flag spelling.
    pub fn name(self) -> &'static str {
        match self {
            Self::Sh => "sh",
            Self::Gt => "gt",
        }
    }
}

/// One sequence seen by one camera, ready to feed a model.
#[derive(Debug, Clone, PartialEq)]
pub struct EvalSequence {
    /// Subject, e.g. `"S9"`.
    pub subject: String,
    /// Sequence name, e.g. `"Walking 1"`.
    pub sequence: String,
    /// Camera id.
    pub camera: String,
    /// `frames * 34` normalized screen coordinates, H36M-17 order.
    pub input: Vec<f32>,
    /// The subject's true lengths (metres).
    pub gt: BoneLengths,
}

/// The calibration of a stream's camera, by its subject and camera id.
fn stream_camera<'a>(
    camera: &impl Fn(&str, &str) -> Option<&'a Camera>,
    stream: &EvalSequence,
) -> Result<&'a Camera, TrainError> {
    camera(&stream.subject, &stream.camera).ok_or_else(|| {
        TrainError::Data(format!(
            "no camera {} for {}",
            stream.camera, stream.subject
        ))
    })
}

/// Every stream made into what weights with the input contract `input`
/// read ([`ModelInput::camera`], then [`InputCamera::prepare_frames`]):
/// rectified with its camera (and scaled to the floor) for camera-aware
/// weights, untouched for calibration-free ones. `camera(subject, id)`
/// finds each stream's calibration, a Human3.6M-convention camera whose
/// keypoints are already undistorted ([`undistort_streams`]).
///
/// [`InputCamera::prepare_frames`]: blapose_model::input::InputCamera::prepare_frames
pub fn prepare_streams<'a>(
    streams: &mut [EvalSequence],
    input: &ModelInput,
    camera: &impl Fn(&str, &str) -> Option<&'a Camera>,
) -> Result<(), TrainError> {
    if !input.framing.needs_calibration() {
        return Ok(());
    }
    for t in streams {
        let view = ViewCalibration::from_camera(stream_camera(camera, t)?);
        let prepared = input
            .camera(&view)
            .map_err(|e| TrainError::Data(format!("{} camera {}: {e}", t.subject, t.camera)))?;
        if let Some(prepared) = prepared {
            prepared.prepare_frames(&mut t.input);
        }
    }
    Ok(())
}

/// Undo each stream's lens distortion: its keypoints (normalized screen
/// coordinates of the camera's image) become what a distortion-free
/// camera with the same intrinsics shows, the pinhole picture the
/// rectification and the served protocol assume. The input contract's
/// step for a client that undistorts its own keypoints
/// ([`ViewCalibration::undistort_frames`] with the camera's lens).
pub fn undistort_streams<'a>(
    streams: &mut [EvalSequence],
    camera: &impl Fn(&str, &str) -> Option<&'a Camera>,
) -> Result<(), TrainError> {
    for t in streams {
        ViewCalibration::from_camera_through_lens(stream_camera(camera, t)?)
            .undistort_frames(&mut t.input);
    }
    Ok(())
}

impl EvalSequence {
    /// Number of frames.
    pub fn frames(&self) -> usize {
        self.input.len() / crate::synth::FRAME_DIM
    }

    /// The same trial as a stream of `fps` frames per second: the 50 Hz
    /// keypoints linearly interpolated at `50 / fps` source frames per
    /// output frame (`fps` 25 keeps every other frame; 60 interpolates).
    /// This is how the evaluation measures the served model on 25-60 fps
    /// cameras. `fps` must be positive and finite.
    pub fn resampled(&self, fps: f32) -> Result<EvalSequence, TrainError> {
        use crate::synth::FRAME_DIM;
        if !(fps.is_finite() && fps > 0.0) {
            return Err(TrainError::InvalidArgument(format!(
                "frame rate must be positive, got {fps}"
            )));
        }
        let n = self.frames();
        let step = f64::from(SOURCE_FPS) / f64::from(fps);
        let out_frames = if n == 0 {
            0
        } else {
            ((n - 1) as f64 / step).floor() as usize + 1
        };
        let mut input = Vec::with_capacity(out_frames * FRAME_DIM);
        for i in 0..out_frames {
            let u = i as f64 * step;
            let a = (u.floor() as usize).min(n - 1);
            let b = (a + 1).min(n - 1);
            let t = (u - a as f64) as f32;
            let (fa, fb) = (
                &self.input[a * FRAME_DIM..(a + 1) * FRAME_DIM],
                &self.input[b * FRAME_DIM..(b + 1) * FRAME_DIM],
            );
            input.extend(fa.iter().zip(fb).map(|(x, y)| x + (y - x) * t));
        }
        Ok(self.with_input(input, self.gt))
    }

    /// The same trial seen in a mirror: every frame's keypoints flipped
    /// horizontally ([`crate::synth::flip_input`], the training flip) and
    /// the left/right lengths swapped, so the mirrored trial's truth is
    /// still `gt` up to the swap. Twice is the identity.
    pub fn mirrored(&self) -> EvalSequence {
        self.with_input(
            crate::synth::flip_input(&self.input),
            flip_bone_lengths(&self.gt),
        )
    }

    /// This trial's labels with another input stream and truth.
    fn with_input(&self, input: Vec<f32>, gt: BoneLengths) -> EvalSequence {
        EvalSequence {
            subject: self.subject.clone(),
            sequence: self.sequence.clone(),
            camera: self.camera.clone(),
            input,
            gt,
        }
    }
}

/// Frame rate of Human3.6M's poses and detections.
pub const SOURCE_FPS: f32 = 50.0;

/// Each subject's bone lengths: the mean over all its frames (Human3.6M
/// lengths are constant per subject to well under a millimetre).
pub fn subject_lengths(h36m: &H36m) -> BTreeMap<String, BoneLengths> {
    h36m.poses
        .iter()
        .filter_map(|(s, acts)| {
            let all: Vec<Pose> = acts.values().flatten().copied().collect();
            mean_bone_lengths(&all).map(|l| (s.clone(), l))
        })
        .collect()
}

/// The mean of the named subjects' bone lengths ([`subject_lengths`]), each
/// subject weighted once: with [`TRAIN_SUBJECTS`], the constant baseline
/// every estimate is read against. `None` if a subject is missing.
pub fn mean_subject_lengths(
    lengths: &BTreeMap<String, BoneLengths>,
    subjects: &[&str],
) -> Option<BoneLengths> {
    let ls: Vec<&BoneLengths> = subjects
        .iter()
        .map(|s| lengths.get(*s))
        .collect::<Option<_>>()?;
    (!ls.is_empty())
        .then(|| std::array::from_fn(|b| ls.iter().map(|l| l[b]).sum::<f32>() / ls.len() as f32))
}

/// SH16 pixel detections to H36M-17 normalized screen coordinates.
pub fn sh_to_normalized(
    frames: &[ShKeypoints],
    camera: &Camera,
) -> Result<Vec<Keypoints2d>, TrainError> {
    frames
        .iter()
        .map(|f| {
            let kp = KeypointLayout::Sh16.to_h36m17(f)?;
            Ok(normalize_keypoints(&kp, camera.width, camera.height))
        })
        .collect()
}

/// Everything training needs, from the training subjects only.
#[derive(Debug, Clone)]
pub struct TrainingSet {
    /// Pre-decomposed 3D sequences.
    pub sequences: Vec<MotionSequence>,
    /// The training subjects' lengths.
    pub subject_lengths: BTreeMap<String, BoneLengths>,
    /// Real detection residuals, `track(seq, cam)` aligned with `sequences`.
    pub residuals: ResidualBank,
    /// The training subjects' real SH input with their true lengths (for
    /// validation on real detector input).
    pub real_sh: Vec<EvalSequence>,
}

impl TrainingSet {
    /// Load S1 S5 S6 S7 S8 from the data root.
    pub fn load(root: &Path) -> Result<Self, TrainError> {
        let h36m = H36m::load(root, &TRAIN_SUBJECTS, Parts::ALL)?;
        Self::from_h36m(&h36m)
    }

    /// Build from already loaded data; every subject not in
    /// [`TRAIN_SUBJECTS`] is ignored.
    pub fn from_h36m(h36m: &H36m) -> Result<Self, TrainError> {
        let lengths: BTreeMap<String, BoneLengths> = subject_lengths(h36m)
            .into_iter()
            .filter(|(s, _)| TRAIN_SUBJECTS.contains(&s.as_str()))
            .collect();
        let keys: Vec<(&str, &str, &[Pose])> = h36m
            .sequences()
            .filter(|(s, _, p)| TRAIN_SUBJECTS.contains(s) && p.len() >= 2)
            .collect();
        if keys.is_empty() {
            return Err(TrainError::Data("no training sequences found".into()));
        }
        let mut cams_by_subject: BTreeMap<&str, Arc<Vec<Camera>>> = BTreeMap::new();
        for (s, _, _) in &keys {
            if !cams_by_subject.contains_key(s) {
                let cams = h36m
                    .cameras
                    .subject(s)
                    .ok_or_else(|| TrainError::Data(format!("no cameras for {s}")))?;
                cams_by_subject.insert(s, Arc::new(cams.to_vec()));
            }
        }
        type Built = (
            MotionSequence,
            Vec<Option<Vec<MetricResidual>>>,
            Vec<EvalSequence>,
        );
        let built: Vec<Built> = keys
            .par_iter()
            .map(|&(s, a, poses)| -> Result<Built, TrainError> {
                let cameras = cams_by_subject[s].clone();
                let subject_len = lengths
                    .get(s)
                    .copied()
                    .ok_or_else(|| TrainError::Data(format!("no lengths for {s}")))?;
                let motion = decompose_sequence(s, a, poses, subject_len, cameras.clone())?;
                let mut tracks = Vec::with_capacity(cameras.len());
                let mut real = Vec::new();
                for cam in cameras.iter() {
                    let Some(det) = h36m.detections(s, a, &cam.id) else {
                        tracks.push(None);
                        continue;
                    };
                    let sh = sh_to_normalized(det, cam)?;
                    tracks.push(Some(residual_track(&sh, poses, cam)));
                    real.push(EvalSequence {
                        subject: s.to_string(),
                        sequence: a.to_string(),
                        camera: cam.id.clone(),
                        input: sh.iter().flatten().flatten().copied().collect(),
                        gt: subject_len,
                    });
                }
                Ok((motion, tracks, real))
            })
            .collect::<Result<_, _>>()?;
        let mut sequences = Vec::with_capacity(built.len());
        let mut tracks = Vec::with_capacity(built.len());
        let mut real_sh = Vec::new();
        for (m, t, r) in built {
            sequences.push(m);
            tracks.push(t);
            real_sh.extend(r);
        }
        Ok(Self {
            sequences,
            subject_lengths: lengths,
            residuals: ResidualBank::new(tracks),
            real_sh,
        })
    }

    /// The training subjects' lengths as a list (for the statistics).
    pub fn lengths_list(&self) -> Vec<BoneLengths> {
        self.subject_lengths.values().copied().collect()
    }
}

/// Roots and unit directions of every frame. A frame that cannot be
/// decomposed (a collapsed bone) reuses the previous frame's directions.
pub fn decompose_sequence(
    subject: &str,
    action: &str,
    poses: &[Pose],
    lengths: BoneLengths,
    cameras: Arc<Vec<Camera>>,
) -> Result<MotionSequence, TrainError> {
    let mut roots = Vec::with_capacity(poses.len());
    let mut dirs = Vec::with_capacity(poses.len());
    for (t, p) in poses.iter().enumerate() {
        roots.push(p[0]);
        match decompose(p) {
            Ok((_, d)) => dirs.push(d),
            Err(e) => match dirs.last() {
                Some(&prev) => dirs.push(prev),
                None => {
                    return Err(TrainError::Data(format!(
                        "{subject}/{action} frame {t}: {e}"
                    )))
                }
            },
        }
    }
    Ok(MotionSequence {
        subject: subject.into(),
        action: action.into(),
        roots,
        dirs,
        lengths,
        cameras,
    })
}

/// The metric residual track of one sequence's real detections against
/// one projection of its ground truth per frame (see [`crate::noise`]; the
/// shorter of the two streams bounds it, frames that give no finite
/// residual repeat the previous one, or zero).
pub fn residual_track(sh: &[Keypoints2d], poses: &[Pose], cam: &Camera) -> Vec<MetricResidual> {
    let k = cam.normalized_intrinsics();
    let n = sh.len().min(poses.len());
    let mut track: Vec<MetricResidual> = Vec::with_capacity(n);
    for t in 0..n {
        let cp = cam.world_to_camera_pose(&poses[t]);
        let gt = k.project_pose(&cp);
        let r = metric_residual(&sh[t], &gt, cp[0][2], k.focal)
            .or_else(|| track.last().copied())
            .unwrap_or([[0.0; 2]; blapose_core::NUM_JOINTS]);
        track.push(r);
    }
    track
}

/// Evaluation inputs for `subjects`: every sequence, every camera.
/// `lengths` must hold each subject's true lengths.
pub fn eval_sequences(
    h36m: &H36m,
    subjects: &[&str],
    input: InputKind,
    lengths: &BTreeMap<String, BoneLengths>,
) -> Result<Vec<EvalSequence>, TrainError> {
    let mut out = Vec::new();
    for (s, a, poses) in h36m.sequences() {
        if !subjects.contains(&s) {
            continue;
        }
        let gt = *lengths
            .get(s)
            .ok_or_else(|| TrainError::Data(format!("no lengths for {s}")))?;
        let cams = h36m
            .cameras
            .subject(s)
            .ok_or_else(|| TrainError::Data(format!("no cameras for {s}")))?;
        for cam in cams {
            let kp: Vec<Keypoints2d> = match input {
                InputKind::Gt => poses
                    .iter()
                    .map(|p| cam.project_world_pose_normalized(p))
                    .collect(),
                InputKind::Sh => match h36m.detections(s, a, &cam.id) {
                    Some(det) => sh_to_normalized(det, cam)?,
                    None => continue,
                },
            };
            if kp.is_empty() {
                continue;
            }
            out.push(EvalSequence {
                subject: s.into(),
                sequence: a.into(),
                camera: cam.id.clone(),
                input: kp.iter().flatten().flatten().copied().collect(),
                gt,
            });
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synth::FRAME_DIM;

    #[test]
    fn undistorted_streams_are_the_pinhole_projection() {
        let cam = Camera {
            id: "c".into(),
            rotation: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            center: [0.0; 3],
            focal: [1145.0, 1143.8],
            principal: [512.5, 515.5],
            radial: [-0.207, 0.248, -0.003],
            tangential: [-0.001, -0.0014],
            width: 1000,
            height: 1002,
        };
        let pinhole = Camera {
            radial: [0.0; 3],
            tangential: [0.0; 2],
            ..cam.clone()
        };
        // Two frames of 17 camera-space points spread over the image.
        let points: Vec<[f64; 3]> = (0..2 * 17)
            .map(|i| [-1.5 + 0.09 * i as f64, 1.4 - 0.08 * i as f64, 4.0])
            .collect();
        let normalized = |c: &Camera| -> Vec<f32> {
            points
                .iter()
                .flat_map(|&p| {
                    let px = c.project_camera_to_pixels(p);
                    blapose_core::camera::normalize_screen(
                        [px[0] as f32, px[1] as f32],
                        c.width,
                        c.height,
                    )
                })
                .collect()
        };
        let mut streams = vec![EvalSequence {
            subject: "S1".into(),
            sequence: "s".into(),
            camera: "c".into(),
            input: normalized(&cam),
            gt: [0.3; 16],
        }];
        let want = normalized(&pinhole);
        let moved = streams[0]
            .input
            .iter()
            .zip(&want)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0f32, f32::max);
        assert!(moved > 0.01, "the lens moves the points: {moved}");
        undistort_streams(&mut streams, &|_: &str, _: &str| Some(&cam)).unwrap();
        for (a, b) in streams[0].input.iter().zip(&want) {
            assert!((a - b).abs() < 1e-5, "{a} vs {b}");
        }
        // A stream without a calibration is an error, not a panic.
        assert!(undistort_streams(&mut streams, &|_: &str, _: &str| None).is_err());
    }

    fn ramp(frames: usize) -> EvalSequence {
        EvalSequence {
            subject: "S9".into(),
            sequence: "Walking 1".into(),
            camera: "54138969".into(),
            input: (0..frames * FRAME_DIM)
                .map(|i| (i / FRAME_DIM) as f32)
                .collect(),
            gt: [0.2; 16],
        }
    }

    #[test]
    fn mirroring_flips_x_swaps_sides_and_twice_is_the_identity() {
        let mut s = ramp(3);
        for (i, v) in s.input.iter_mut().enumerate() {
            *v = i as f32 * 0.01;
        }
        s.gt[0] = 0.13; // r_hip
        s.gt[3] = 0.12; // l_hip
        let m = s.mirrored();
        assert_eq!(m.frames(), 3);
        // Joint 1 (r_hip) lands on joint 4 (l_hip), x negated, y kept.
        let (rx, ry) = (s.input[2], s.input[3]);
        assert_eq!(m.input[2 * 4], -rx);
        assert_eq!(m.input[2 * 4 + 1], ry);
        // The pelvis stays the pelvis.
        assert_eq!(m.input[0], -s.input[0]);
        assert_eq!((m.gt[0], m.gt[3]), (0.12, 0.13));
        assert_eq!(m.mirrored(), s);
    }

    #[test]
    fn resampling_keeps_every_other_frame_at_25_fps_and_interpolates_at_60() {
        let s = ramp(11);
        let half = s.resampled(25.0).unwrap();
        assert_eq!(half.frames(), 6);
        for i in 0..6 {
            assert_eq!(half.input[i * FRAME_DIM], 2.0 * i as f32);
        }
        let fast = s.resampled(60.0).unwrap();
        // 10 source intervals at 50/60 source frames per output frame.
        assert_eq!(fast.frames(), 13);
        assert!((fast.input[FRAME_DIM] - 50.0 / 60.0).abs() < 1e-6);
        assert_eq!(fast.input[fast.input.len() - 1], 10.0);
        assert_eq!(s.resampled(50.0).unwrap(), s);
        assert!(s.resampled(0.0).is_err());
        assert!(s.resampled(f32::NAN).is_err());
        assert_eq!(ramp(0).resampled(30.0).unwrap().frames(), 0);
    }
}

//! What a lifter reads and what it must output, per (sequence, camera).
//!
//! The input is exactly what the bone-length models read in evaluation
//! ([`eval_sequences`] with [`InputKind::Sh`]: Stacked Hourglass detections
//! mapped to the 17 Human3.6M joints, normalized screen coordinates), so
//! eval-adjust feeds one stream to both models and no second conversion can
//! drift from the first. The target is the ground-truth pose in that
//! camera's space (`X_c = R (X_w - center)`), root-relative, metres.
//!
//! * **Subsampling.** Consecutive 50 Hz frames are nearly identical, so
//!   training uses every `every`-th frame of each stream
//!   ([`training_samples`]); validation takes frames *between* them
//!   ([`held_out_samples`]), which the optimizer never sees (with
//!   `every = 1` there are none and validation reuses training frames).
//! * **Flip.** A horizontally mirrored image shows the mirrored person: input
//!   `x -> -x` with left/right joints swapped ([`flip_input`]), target camera
//!   `X -> -X` with left/right swapped ([`flip_pose`]). Both are their own
//!   inverse. Test-time flip ([`average_flipped`]) averages the prediction
//!   with the flipped-back prediction of the flipped input.

use blapose_core::camera::Camera;
use blapose_core::pose::{flip_pose, root_relative};
use blapose_core::Pose;
use blapose_data::h36m::H36m;
use rand::Rng;

use super::{output_to_pose, pose_to_target, OUTPUT_DIM};
use crate::dataset::{eval_sequences, subject_lengths, EvalSequence, InputKind};
use crate::error::TrainError;
pub use crate::synth::flip_input;
use crate::synth::FRAME_DIM;

/// One stream: the 2D input (and the subject's true lengths) with the
/// camera-space 3D target of every frame.
#[derive(Debug, Clone, PartialEq)]
pub struct LifterSequence {
    /// Input frames (`trial.input`, `frames * 34`) and identification.
    pub trial: EvalSequence,
    /// Root-relative camera-space ground truth, one pose per input frame.
    pub target: Vec<Pose>,
}

impl LifterSequence {
    /// Number of frames.
    pub fn frames(&self) -> usize {
        self.target.len()
    }
}

/// Ground-truth world poses as root-relative poses in `cam`'s space.
pub fn camera_targets(poses: &[Pose], cam: &Camera) -> Vec<Pose> {
    poses
        .iter()
        .map(|p| root_relative(&cam.world_to_camera_pose(p)))
        .collect()
}

/// Every (sequence, camera) of `subjects` that has detections. Input and
/// target are cut to the shorter of the two streams (they are frame-aligned
/// from the first frame).
pub fn lifter_sequences(h36m: &H36m, subjects: &[&str]) -> Result<Vec<LifterSequence>, TrainError> {
    let lengths = subject_lengths(h36m);
    let trials = eval_sequences(h36m, subjects, InputKind::Sh, &lengths)?;
    trials
        .into_iter()
        .map(|mut trial| {
            let poses = h36m
                .sequence(&trial.subject, &trial.sequence)
                .ok_or_else(|| {
                    TrainError::Data(format!("no poses for {}/{}", trial.subject, trial.sequence))
                })?;
            let cam = h36m
                .cameras
                .get(&trial.subject, &trial.camera)
                .ok_or_else(|| {
                    TrainError::Data(format!("no camera {}/{}", trial.subject, trial.camera))
                })?;
            let n = trial.frames().min(poses.len());
            trial.input.truncate(n * FRAME_DIM);
            Ok(LifterSequence {
                target: camera_targets(&poses[..n], cam),
                trial,
            })
        })
        .collect()
}

/// A training sample: `(sequence index, frame)`.
pub type SampleIndex = (usize, usize);

/// Every `every`-th frame of every sequence (`every >= 1`).
pub fn training_samples(seqs: &[LifterSequence], every: usize) -> Vec<SampleIndex> {
    let every = every.max(1);
    seqs.iter()
        .enumerate()
        .flat_map(|(s, q)| (0..q.frames()).step_by(every).map(move |t| (s, t)))
        .collect()
}

/// Up to `max` frames spread evenly over the frames half-way between the
/// training frames of [`training_samples`] (the training frames themselves
/// when `every` is 1).
pub fn held_out_samples(seqs: &[LifterSequence], every: usize, max: usize) -> Vec<SampleIndex> {
    let every = every.max(1);
    let offset = every / 2;
    let all: Vec<SampleIndex> = seqs
        .iter()
        .enumerate()
        .flat_map(|(s, q)| (offset..q.frames()).step_by(every).map(move |t| (s, t)))
        .collect();
    if all.len() <= max {
        return all;
    }
    (0..max).map(|i| all[i * all.len() / max]).collect()
}

/// The input frames a lifter reads for one output frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Window {
    /// Frames per window (the receptive field; odd).
    pub frames: usize,
    /// The output belongs to the window's last frame (online use) rather
    /// than its centre.
    pub causal: bool,
}

impl Window {
    /// One frame: the output is that frame.
    pub const SINGLE_FRAME: Window = Window {
        frames: 1,
        causal: false,
    };

    /// Frames before the output frame.
    pub fn past(&self) -> usize {
        if self.causal {
            self.frames - 1
        } else {
            self.frames / 2
        }
    }

    /// Input values per window.
    pub fn values(&self) -> usize {
        self.frames * FRAME_DIM
    }
}

/// Append the window of output frame `t` to `out`: frames `t - past ..`,
/// with the first and last frames repeated beyond the stream's ends (the
/// reference's edge padding, and what an online window holds before it
/// fills).
pub fn push_window(trial: &EvalSequence, t: usize, window: Window, out: &mut Vec<f32>) {
    let n = trial.frames();
    let past = window.past();
    for k in 0..window.frames {
        let f = (t + k).saturating_sub(past).min(n - 1);
        out.extend_from_slice(&trial.input[f * FRAME_DIM..(f + 1) * FRAME_DIM]);
    }
}

/// A batch of windows and targets.
#[derive(Debug, Clone, PartialEq)]
pub struct LifterBatch {
    /// Samples.
    pub batch: usize,
    /// `batch * window.values()` inputs.
    pub inputs: Vec<f32>,
    /// `batch * OUTPUT_DIM` targets (joints 1..17, metres).
    pub targets: Vec<f32>,
    /// Where each sample comes from.
    pub samples: Vec<SampleIndex>,
    /// Whether each sample was mirrored.
    pub flipped: Vec<bool>,
}

/// Gather `idx` into a batch; sample `i` is mirrored when `flip[i]`.
pub fn gather(
    seqs: &[LifterSequence],
    idx: &[SampleIndex],
    spec: Window,
    flip: &[bool],
) -> LifterBatch {
    let mut inputs = Vec::with_capacity(idx.len() * spec.values());
    let mut targets = Vec::with_capacity(idx.len() * OUTPUT_DIM);
    let mut window = Vec::with_capacity(spec.values());
    let flipped: Vec<bool> = (0..idx.len())
        .map(|i| flip.get(i).copied().unwrap_or(false))
        .collect();
    for (&(s, t), &mirrored) in idx.iter().zip(&flipped) {
        let q = &seqs[s];
        window.clear();
        push_window(&q.trial, t, spec, &mut window);
        if mirrored {
            inputs.extend(flip_input(&window));
            targets.extend(pose_to_target(&flip_pose(&q.target[t])));
        } else {
            inputs.extend_from_slice(&window);
            targets.extend(pose_to_target(&q.target[t]));
        }
    }
    LifterBatch {
        batch: idx.len(),
        inputs,
        targets,
        samples: idx.to_vec(),
        flipped,
    }
}

/// A random training batch: `batch` samples drawn with replacement from
/// `pool`, each mirrored with probability `flip_prob`.
pub fn random_batch(
    seqs: &[LifterSequence],
    pool: &[SampleIndex],
    window: Window,
    batch: usize,
    flip_prob: f32,
    rng: &mut impl Rng,
) -> LifterBatch {
    let idx: Vec<SampleIndex> = (0..batch)
        .map(|_| pool[rng.random_range(0..pool.len())])
        .collect();
    let flip: Vec<bool> = (0..batch)
        .map(|_| rng.random::<f32>() < flip_prob)
        .collect();
    gather(seqs, &idx, window, &flip)
}

/// Test-time flip: the mean of `pred[t]` and the mirrored-back
/// `pred_of_flipped[t]`.
pub fn average_flipped(pred: &[Pose], pred_of_flipped: &[Pose]) -> Vec<Pose> {
    pred.iter()
        .zip(pred_of_flipped)
        .map(|(a, b)| {
            let b = flip_pose(b);
            std::array::from_fn(|j| std::array::from_fn(|k| 0.5 * (a[j][k] + b[j][k])))
        })
        .collect()
}

/// Network output rows (`n * OUTPUT_DIM`) as poses.
pub fn outputs_to_poses(out: &[f32]) -> Vec<Pose> {
    out.chunks_exact(OUTPUT_DIM).map(output_to_pose).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn seq(frames: usize) -> LifterSequence {
        LifterSequence {
            trial: EvalSequence {
                subject: "S1".into(),
                sequence: "Walking 1".into(),
                camera: "c".into(),
                input: (0..frames * FRAME_DIM)
                    .map(|i| (i / FRAME_DIM) as f32)
                    .collect(),
                gt: [0.2; 16],
            },
            target: (0..frames)
                .map(|t| std::array::from_fn(|j| [t as f32, j as f32, 0.0]))
                .collect(),
        }
    }

    #[test]
    fn subsampling_and_held_out_frames_do_not_overlap() {
        let seqs = vec![seq(10), seq(7)];
        let train = training_samples(&seqs, 4);
        assert_eq!(train, vec![(0, 0), (0, 4), (0, 8), (1, 0), (1, 4)]);
        let val = held_out_samples(&seqs, 4, 100);
        assert_eq!(val, vec![(0, 2), (0, 6), (1, 2), (1, 6)]);
        assert_eq!(held_out_samples(&seqs, 4, 2), vec![(0, 2), (1, 2)]);
        assert_eq!(training_samples(&seqs, 1).len(), 17);
    }

    #[test]
    fn windows_repeat_the_edges() {
        let q = seq(3);
        let firsts = |t: usize, frames: usize, causal: bool| {
            let mut w = Vec::new();
            push_window(&q.trial, t, Window { frames, causal }, &mut w);
            w.chunks(FRAME_DIM).map(|f| f[0]).collect::<Vec<f32>>()
        };
        assert_eq!(firsts(0, 3, false), vec![0.0, 0.0, 1.0]);
        assert_eq!(firsts(2, 5, false), vec![0.0, 1.0, 2.0, 2.0, 2.0]);
        // Causal: the output frame is the last of its window.
        assert_eq!(firsts(1, 3, true), vec![0.0, 0.0, 1.0]);
        assert_eq!(firsts(2, 3, true), vec![0.0, 1.0, 2.0]);
        assert_eq!(firsts(2, 1, false), vec![2.0]);
    }
}

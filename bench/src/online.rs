//! The per-frame work of a real-time pipeline, as `fps-table` times it:
//! one stream through a reference lifter ([`LifterStream`]: slide the
//! window, lift, read the pose back) and BLAPose's adjustment
//! ([`Adjuster`]: one online GRU step, the running mean of the lengths,
//! the rebuilt pose), fed by a deterministic 2D stream
//! ([`synthetic_stream`]).
//!
//! Why a module: these are the steps being measured, so they are kept
//! apart from the table's bookkeeping and tested on their own, and the
//! state each holds is exactly what a server keeps per session.

use anyhow::{Context, Result};
use blapose_core::bones::adjust_pose_lenient;
use blapose_core::{BoneLengths, Keypoints2d, Pose, NUM_BONES, NUM_JOINTS};
use blapose_lifters::{poses_from_tensor, Anatomy3d, Lifter, OnlineBoneLengths, SlidingWindow};
use blapose_model::fast::{OnlineGruEngine, StepScratch};
use blapose_model::{RunningMean, INPUT_DIM, OUTPUT_DIM, STATE_DIM};

/// BLAPose's per-frame work: GRU step, running mean, adjustment.
pub struct Adjuster<'a> {
    engine: &'a OnlineGruEngine,
    scratch: StepScratch,
    hidden: Vec<f32>,
    out: [f32; OUTPUT_DIM],
    /// The estimate, averaged as the server does.
    running: RunningMean,
}

impl<'a> Adjuster<'a> {
    /// A fresh stream (zero hidden state) on `engine`, batch 1.
    pub fn new(engine: &'a OnlineGruEngine) -> Self {
        Self {
            engine,
            scratch: engine.scratch(1),
            hidden: vec![0.0; STATE_DIM],
            out: [0.0; OUTPUT_DIM],
            running: RunningMean::new(),
        }
    }

    /// One GRU step; returns the mean prediction over the stream so far.
    pub fn lengths(&mut self, frame: &Keypoints2d) -> Result<BoneLengths> {
        let input: &[f32] = frame.as_flattened();
        debug_assert_eq!(input.len(), INPUT_DIM);
        self.engine
            .step(input, &mut self.hidden, &mut self.out, &mut self.scratch)?;
        // Random weights can predict negative lengths; a length is >= 0.
        Ok(self.running.push(&self.out).map(|l| l.max(0.0)))
    }

    /// One GRU step, then `pose` rebuilt with the lengths so far.
    pub fn adjust(&mut self, frame: &Keypoints2d, pose: &Pose) -> Result<Pose> {
        let lengths = self.lengths(frame)?;
        Ok(adjust_pose_lenient(pose, &lengths)?)
    }
}

/// One stream through a lifter (state that a server would keep per session).
pub struct LifterStream<'a> {
    lifter: &'a dyn Lifter,
    anatomy: Option<&'a Anatomy3d>,
    window: SlidingWindow,
    lengths: OnlineBoneLengths,
}

impl<'a> LifterStream<'a> {
    /// A fresh stream through `lifter`; with `anatomy` (the same model as
    /// `lifter`), Anatomy3D's bone-length branch advances on every frame
    /// and its running lengths condition the pose (the online form of its
    /// video-level prediction).
    pub fn new(lifter: &'a dyn Lifter, anatomy: Option<&'a Anatomy3d>) -> Self {
        Self {
            lifter,
            anatomy,
            window: SlidingWindow::new(lifter.receptive_field()),
            lengths: OnlineBoneLengths::new(),
        }
    }

    /// Append `frame` to the window and lift the window's pose.
    pub fn step(&mut self, frame: &Keypoints2d) -> Result<Pose> {
        self.window.push(*frame);
        let window = self
            .window
            .tensor()?
            .context("window is empty after a push")?;
        let out = match self.anatomy {
            Some(a) => {
                let frame_t = blapose_lifters::keypoints_tensor(std::slice::from_ref(frame))?;
                let lengths = a.bone_length().step(&frame_t, &mut self.lengths)?;
                let lengths = candle_core::Tensor::from_slice(
                    &lengths,
                    (1, NUM_BONES),
                    &candle_core::Device::Cpu,
                )?;
                a.predict_frame_with(&window, None, &lengths)?
            }
            None => self.lifter.predict_frame(&window)?,
        };
        poses_from_tensor(&out)?
            .pop()
            .context("lifter returned no pose")
    }
}

/// A deterministic 2D stream: a standing figure in normalized screen
/// coordinates, swaying and breathing a little.
pub fn synthetic_stream(frames: usize) -> Vec<Keypoints2d> {
    const BASE: [[f32; 2]; NUM_JOINTS] = [
        [0.0, 0.0],
        [-0.06, 0.0],
        [-0.07, 0.22],
        [-0.07, 0.44],
        [0.06, 0.0],
        [0.07, 0.22],
        [0.07, 0.44],
        [0.0, -0.12],
        [0.0, -0.24],
        [0.0, -0.29],
        [0.0, -0.34],
        [0.08, -0.23],
        [0.12, -0.11],
        [0.13, 0.0],
        [-0.08, -0.23],
        [-0.12, -0.11],
        [-0.13, 0.0],
    ];
    (0..frames)
        .map(|t| {
            let phase = t as f32 * 0.05;
            std::array::from_fn(|j| {
                let s = 0.02 * (phase + j as f32 * 0.3).sin();
                [BASE[j][0] + s + 0.05 * phase.sin(), BASE[j][1] + 0.5 * s]
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use blapose_lifters::ReferenceLifter;
    use blapose_model::{LoadedWeights, ModelKind};

    #[test]
    fn stream_is_deterministic_and_in_normalized_range() {
        let a = synthetic_stream(50);
        assert_eq!(a, synthetic_stream(50));
        assert_ne!(a[0], a[49]);
        assert!(a.iter().flatten().flatten().all(|v| v.abs() < 1.0));
    }

    #[test]
    fn a_lifter_stream_and_the_adjuster_answer_every_frame() {
        let lifter = ReferenceLifter::PoseFormer.random(false, 1).unwrap();
        let weights = LoadedWeights::random(ModelKind::Gru, 2).unwrap();
        let engine = OnlineGruEngine::new(&weights, 1).unwrap();
        let mut stream = LifterStream::new(lifter.as_ref(), None);
        let mut adjuster = Adjuster::new(&engine);
        for frame in &synthetic_stream(3) {
            let pose = stream.step(frame).unwrap();
            assert!(pose.iter().flatten().all(|v| v.is_finite()));
            let adjusted = adjuster.adjust(frame, &pose).unwrap();
            assert!(adjusted.iter().flatten().all(|v| v.is_finite()));
        }
        assert!(adjuster
            .lengths(&synthetic_stream(1)[0])
            .unwrap()
            .iter()
            .all(|l| *l >= 0.0));
    }
}

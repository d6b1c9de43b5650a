//! The sliding window of 2D frames an online lifter sees, and conversions
//! between blapose-core's pose types and tensors.
//!
//! Online, a lifter with receptive field `F` is run once per new frame on
//! the last `F` frames. Before `F` frames have arrived, the window is
//! filled in front with copies of the first frame — the reference pads a
//! sequence's start the same way (numpy `edge` padding), so the first
//! outputs of a stream match an offline evaluation of the same prefix.

use std::collections::VecDeque;

use candle_core::{Device, Tensor};

use blapose_core::pose::{pose_from_flat, POSE_VALUES};
use blapose_core::{Keypoints2d, Pose, NUM_JOINTS};

use crate::error::{expect_dims, Result};
use crate::INPUT_FEATURES;

/// The last `frames` 2D keypoint frames of one stream.
#[derive(Debug, Clone)]
pub struct SlidingWindow {
    frames: usize,
    buf: VecDeque<Keypoints2d>,
    flat: Vec<f32>,
}

impl SlidingWindow {
    /// An empty window of `frames` frames (at least 1). The scratch buffer
    /// of [`SlidingWindow::tensor`] is allocated on first use, so a window
    /// only read through [`SlidingWindow::extend_with_next`] (the server's
    /// batched path) holds just its frames.
    pub fn new(frames: usize) -> Self {
        let frames = frames.max(1);
        Self {
            frames,
            buf: VecDeque::with_capacity(frames),
            flat: Vec::new(),
        }
    }

    /// Frames the window holds when full.
    pub fn frames(&self) -> usize {
        self.frames
    }

    /// Frames pushed so far, up to [`SlidingWindow::frames`].
    pub fn len(&self) -> usize {
        self.buf.len()
    }

    /// The frames held, oldest first (pushing them in this order into an
    /// empty window of the same size rebuilds this one).
    pub fn iter(&self) -> impl ExactSizeIterator<Item = &Keypoints2d> {
        self.buf.iter()
    }

    /// Whether no frame has been pushed.
    pub fn is_empty(&self) -> bool {
        self.buf.is_empty()
    }

    /// Append the newest frame, dropping the oldest when full.
    pub fn push(&mut self, frame: Keypoints2d) {
        if self.buf.len() == self.frames {
            self.buf.pop_front();
        }
        self.buf.push_back(frame);
    }

    /// Append to `out` the window as it will be after `push(next)`:
    /// `frames x 17 x 2` values, oldest frame first, edge-padded in front
    /// while not yet full (exactly what [`SlidingWindow::tensor`] would
    /// hold after the push). The window itself is not changed, so a caller
    /// can lift a frame first and `push` it only once everything else about
    /// that frame has succeeded (a refused frame must leave a stream's
    /// state as it was).
    pub fn extend_with_next(&self, next: &Keypoints2d, out: &mut Vec<f32>) {
        // Frames kept from the buffer: the newest `frames - 1` at most.
        let kept = self.buf.len().min(self.frames - 1);
        let skip = self.buf.len() - kept;
        let first = self.buf.get(skip).unwrap_or(next);
        out.reserve(self.frames * NUM_JOINTS * INPUT_FEATURES);
        for _ in kept + 1..self.frames {
            out.extend(first.iter().flatten());
        }
        for frame in self.buf.iter().skip(skip) {
            out.extend(frame.iter().flatten());
        }
        out.extend(next.iter().flatten());
    }

    /// The window as a `(1, frames, 17, 2)` tensor, oldest frame first,
    /// edge-padded in front while not yet full; `None` while empty.
    pub fn tensor(&mut self) -> Result<Option<Tensor>> {
        let Some(first) = self.buf.front() else {
            return Ok(None);
        };
        self.flat.clear();
        for _ in self.buf.len()..self.frames {
            self.flat.extend(first.iter().flatten());
        }
        for frame in &self.buf {
            self.flat.extend(frame.iter().flatten());
        }
        let t = Tensor::from_slice(
            &self.flat,
            (1, self.frames, NUM_JOINTS, INPUT_FEATURES),
            &Device::Cpu,
        )?;
        Ok(Some(t))
    }
}

/// Stack 2D frames into a `(1, T, 17, 2)` tensor.
pub fn keypoints_tensor(frames: &[Keypoints2d]) -> Result<Tensor> {
    let flat: Vec<f32> = frames.iter().flatten().flatten().copied().collect();
    Ok(Tensor::from_vec(
        flat,
        (1, frames.len(), NUM_JOINTS, INPUT_FEATURES),
        &Device::Cpu,
    )?)
}

/// Read `(B, 17, 3)` lifter output as poses.
pub fn poses_from_tensor(t: &Tensor) -> Result<Vec<Pose>> {
    expect_dims(t, "poses", &[None, Some(NUM_JOINTS), Some(3)])?;
    let flat: Vec<f32> = t.flatten_all()?.to_vec1()?;
    // `(B, 17, 3)` was checked: whole poses, each of the right length.
    Ok(flat
        .chunks_exact(POSE_VALUES)
        .filter_map(pose_from_flat)
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(v: f32) -> Keypoints2d {
        [[v, -v]; NUM_JOINTS]
    }

    fn firsts(t: &Tensor) -> Vec<f32> {
        let v: Vec<f32> = t.flatten_all().unwrap().to_vec1().unwrap();
        v.chunks(NUM_JOINTS * 2).map(|f| f[0]).collect()
    }

    #[test]
    fn window_pads_with_first_frame_then_slides() {
        let mut w = SlidingWindow::new(4);
        assert!(w.tensor().unwrap().is_none());
        w.push(frame(1.0));
        w.push(frame(2.0));
        let t = w.tensor().unwrap().unwrap();
        assert_eq!(t.dims(), &[1, 4, NUM_JOINTS, 2]);
        assert_eq!(firsts(&t), [1.0, 1.0, 1.0, 2.0]);
        for v in 3..=6 {
            w.push(frame(v as f32));
        }
        assert_eq!(w.len(), 4);
        assert_eq!(firsts(&w.tensor().unwrap().unwrap()), [3.0, 4.0, 5.0, 6.0]);
    }

    #[test]
    fn extend_with_next_is_the_window_after_a_push_and_changes_nothing() {
        for frames in [1, 2, 4] {
            let mut w = SlidingWindow::new(frames);
            for v in 1..=6 {
                let next = frame(v as f32);
                let mut got = Vec::new();
                w.extend_with_next(&next, &mut got);
                assert_eq!(w.len(), (v - 1).min(frames), "unchanged");
                let mut pushed = w.clone();
                pushed.push(next);
                let want: Vec<f32> = pushed
                    .tensor()
                    .unwrap()
                    .unwrap()
                    .flatten_all()
                    .unwrap()
                    .to_vec1()
                    .unwrap();
                assert_eq!(got, want, "frames {frames}, after {v} pushes");
                w.push(next);
            }
        }
    }

    #[test]
    fn tensors_round_trip_poses_and_keypoints() {
        let t = keypoints_tensor(&[frame(1.0), frame(2.0)]).unwrap();
        assert_eq!(t.dims(), &[1, 2, NUM_JOINTS, 2]);
        let pose_t = Tensor::arange(0f32, (2 * NUM_JOINTS * 3) as f32, &Device::Cpu)
            .unwrap()
            .reshape((2, NUM_JOINTS, 3))
            .unwrap();
        let poses = poses_from_tensor(&pose_t).unwrap();
        assert_eq!(poses.len(), 2);
        assert_eq!(poses[1][16], [99.0, 100.0, 101.0]);
        assert!(poses_from_tensor(&t).is_err());
    }
}

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
    /// An empty window of `frames` frames (at least 1).
    pub fn new(frames: usize) -> Self {
        let frames = frames.max(1);
        Self {
            frames,
            buf: VecDeque::with_capacity(frames),
            flat: Vec::with_capacity(frames * NUM_JOINTS * 2),
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
    Ok(flat
        .chunks_exact(NUM_JOINTS * 3)
        .map(|p| std::array::from_fn(|j| [p[3 * j], p[3 * j + 1], p[3 * j + 2]]))
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

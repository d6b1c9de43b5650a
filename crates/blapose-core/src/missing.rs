//! Missing joints: what a model reads for a joint the detector lost.
//!
//! Why: real 2D detectors lose joints (occlusion, a limb out of frame) and
//! say so with a low confidence, while the coordinates they still report
//! for it are anywhere. The bone-length models were trained on complete
//! skeletons, and a length estimate is an average over many frames, so the
//! simplest faithful input for a missing joint is where it was last seen:
//! *hold* it. A joint missing from the start of a sequence takes its first
//! later position (offline) or, online, the centroid of the joints seen in
//! that frame until it appears.
//!
//! Coordinates are the models' normalized screen coordinates, H36M-17
//! order, `NUM_JOINTS * 2` values per frame.

use crate::skeleton::NUM_JOINTS;

/// A joint whose detector confidence is below this is *missing*: its
/// coordinates are not read (any value, NaN included), and the models read
/// it held (this module). The server and the clients share this one value.
pub const MISSING_CONFIDENCE: f32 = 0.1;

/// Values per frame.
const FRAME: usize = NUM_JOINTS * 2;

/// Fill every missing joint of a whole sequence (`frames * 34` values;
/// `present`, `frames * 17`, says which joints were detected): held from
/// its last detection, or from its first one for the frames before it; a
/// joint never detected takes each frame's centroid of the detected joints.
/// Returns the number of frames with no joint detected (held whole).
///
/// # Panics
/// If the lengths disagree (`frames * 34` against `frames * 17`): a caller
/// bug, not bad input.
pub fn hold_fill_sequence(frames: &mut [f32], present: &[bool]) -> usize {
    assert_eq!(frames.len() / FRAME, present.len() / NUM_JOINTS);
    assert_eq!(frames.len() % FRAME, 0);
    let t_len = frames.len() / FRAME;
    for j in 0..NUM_JOINTS {
        let first = (0..t_len).find(|&t| present[t * NUM_JOINTS + j]);
        let Some(first) = first else {
            continue;
        };
        let mut last = [
            frames[first * FRAME + 2 * j],
            frames[first * FRAME + 2 * j + 1],
        ];
        for t in 0..t_len {
            let i = t * FRAME + 2 * j;
            if present[t * NUM_JOINTS + j] {
                last = [frames[i], frames[i + 1]];
            } else {
                frames[i] = last[0];
                frames[i + 1] = last[1];
            }
        }
    }
    let never: Vec<usize> = (0..NUM_JOINTS)
        .filter(|&j| !(0..t_len).any(|s| present[s * NUM_JOINTS + j]))
        .collect();
    let mut empty = 0;
    for t in 0..t_len {
        let mask = &present[t * NUM_JOINTS..(t + 1) * NUM_JOINTS];
        if !mask.iter().any(|&p| p) {
            empty += 1;
        }
        if never.is_empty() {
            continue;
        }
        if let Some(c) = centroid(&frames[t * FRAME..(t + 1) * FRAME], mask) {
            for &j in &never {
                frames[t * FRAME + 2 * j] = c[0];
                frames[t * FRAME + 2 * j + 1] = c[1];
            }
        }
    }
    empty
}

/// The mean position of the joints `present` in one frame.
fn centroid(frame: &[f32], present: &[bool]) -> Option<[f32; 2]> {
    let mut sum = [0.0f32; 2];
    let mut n = 0;
    for j in (0..NUM_JOINTS).filter(|&j| present[j]) {
        sum[0] += frame[2 * j];
        sum[1] += frame[2 * j + 1];
        n += 1;
    }
    (n > 0).then(|| [sum[0] / n as f32, sum[1] / n as f32])
}

/// The online form of [`hold_fill_sequence`]: each joint's last detected
/// position, carried from frame to frame of one stream (a session's state:
/// session tokens carry it).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HeldJoints {
    last: [Option<[f32; 2]>; NUM_JOINTS],
}

impl Default for HeldJoints {
    fn default() -> Self {
        Self {
            last: [None; NUM_JOINTS],
        }
    }
}

impl HeldJoints {
    /// From each joint's last detected position (`None`: not yet seen).
    pub fn from_last(last: [Option<[f32; 2]>; NUM_JOINTS]) -> Self {
        Self { last }
    }

    /// Each joint's last detected position (`None`: not yet seen).
    pub fn last(&self) -> &[Option<[f32; 2]>; NUM_JOINTS] {
        &self.last
    }

    /// Fill the missing joints of `frame` (34 values) in place: held at
    /// their last detection, or at the centroid of this frame's detected
    /// joints if never seen. `false` when no joint was detected: the frame
    /// carries nothing to read, and is left as it was. Changes nothing
    /// here (see [`Self::remember`]).
    pub fn fill(&self, frame: &mut [f32; FRAME], present: &[bool; NUM_JOINTS]) -> bool {
        let Some(c) = centroid(frame, present) else {
            return false;
        };
        for j in (0..NUM_JOINTS).filter(|&j| !present[j]) {
            let held = self.last[j].unwrap_or(c);
            frame[2 * j..2 * j + 2].copy_from_slice(&held);
        }
        true
    }

    /// Remember the detected joints of `frame` (once it was read).
    pub fn remember(&mut self, frame: &[f32; FRAME], present: &[bool; NUM_JOINTS]) {
        for j in (0..NUM_JOINTS).filter(|&j| present[j]) {
            self.last[j] = Some([frame[2 * j], frame[2 * j + 1]]);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(t: usize) -> Vec<f32> {
        (0..FRAME).map(|i| (t * 100 + i) as f32).collect()
    }

    #[test]
    fn missing_joints_are_held_and_leading_gaps_take_the_first_detection() {
        let t_len = 4;
        let mut frames: Vec<f32> = (0..t_len).flat_map(frame).collect();
        let mut present = vec![true; t_len * NUM_JOINTS];
        // Joint 3 lost at frames 1 and 2; joint 5 missing until frame 2.
        present[NUM_JOINTS + 3] = false;
        present[2 * NUM_JOINTS + 3] = false;
        present[5] = false;
        present[NUM_JOINTS + 5] = false;
        let truth = frames.clone();
        assert_eq!(hold_fill_sequence(&mut frames, &present), 0);
        for t in 1..3 {
            assert_eq!(frames[t * FRAME + 6], truth[6], "held from frame 0");
            assert_eq!(frames[t * FRAME + 7], truth[7]);
        }
        for t in 0..2 {
            assert_eq!(
                frames[t * FRAME + 10],
                truth[2 * FRAME + 10],
                "first detection"
            );
        }
        assert_eq!(
            frames[3 * FRAME..],
            truth[3 * FRAME..],
            "complete frame kept"
        );
    }

    #[test]
    fn a_joint_never_detected_takes_the_centroid_and_empty_frames_are_counted() {
        let mut frames: Vec<f32> = (0..2).flat_map(frame).collect();
        let mut present = vec![true; 2 * NUM_JOINTS];
        present[0] = false;
        present[NUM_JOINTS] = false;
        for p in &mut present[NUM_JOINTS..] {
            *p = false;
        }
        let before = frames.clone();
        assert_eq!(hold_fill_sequence(&mut frames, &present), 1);
        let mean_x = (1..NUM_JOINTS).map(|j| before[2 * j]).sum::<f32>() / 16.0;
        assert!((frames[0] - mean_x).abs() < 1e-3);
    }

    #[test]
    fn online_holding_matches_and_an_empty_frame_is_reported() {
        let mut held = HeldJoints::default();
        let mut present = [true; NUM_JOINTS];
        present[4] = false;
        // Never seen yet: the centroid of the detected joints.
        let mut f0: [f32; FRAME] = std::array::from_fn(|i| i as f32);
        assert!(held.fill(&mut f0, &present));
        let cx = (0..NUM_JOINTS)
            .filter(|&j| j != 4)
            .map(|j| 2.0 * j as f32)
            .sum::<f32>()
            / 16.0;
        assert!((f0[8] - cx).abs() < 1e-4);
        held.remember(&f0, &[true; NUM_JOINTS]);
        let mut f1: [f32; FRAME] = std::array::from_fn(|i| 1000.0 + i as f32);
        assert!(held.fill(&mut f1, &present));
        assert_eq!(&f1[8..10], &f0[8..10], "joint 4 held from frame 0");
        assert_eq!(f1[10], 1010.0, "detected joints untouched");
        let mut f2 = [7.0; FRAME];
        assert!(!held.fill(&mut f2, &[false; NUM_JOINTS]));
        assert_eq!(f2, [7.0; FRAME], "an empty frame is left alone");
        let copy = HeldJoints::from_last(*held.last());
        assert_eq!(copy, held);
    }
}

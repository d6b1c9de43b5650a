//! [`Motion`]: what every format writes, one person's poses with ONE set of
//! bone lengths.
//!
//! A BVH skeleton has fixed offsets, so a sequence whose lengths change over
//! time (an online session's estimate converging) cannot be written as it
//! is. Every export therefore re-poses each frame with one set of lengths
//! (keeping the frame's root position and bone directions, exactly the
//! adjustment blapose applies) and writes that same motion to every format,
//! so a BVH, a C3D and a TRC of one request agree. For the offline Bi-GRU's
//! output the lengths are already constant and re-posing changes nothing
//! beyond float rounding; [`Motion::repose_shift`] says how far it moved any
//! joint.

use blapose_core::bones::{adjust_sequence, validate_lengths, BoneError};
use blapose_core::{BoneLengths, Pose};

use crate::axes::Axes;
use crate::error::ExportError;

/// One person's motion, ready to export: poses (metres, the poses' own
/// coordinates, Human3.6M joint order) that all have exactly `lengths`.
#[derive(Debug, Clone)]
pub struct Motion {
    poses: Vec<Pose>,
    lengths: BoneLengths,
    fps: f64,
    axes: Axes,
    repose_shift: f64,
}

impl Motion {
    /// Re-pose every frame of `poses` with `lengths` (root and bone
    /// directions kept) at `fps` frames per second, with camera axes (up is
    /// `-y`; see [`Motion::with_up`]).
    ///
    /// Errors: no poses; a non-finite coordinate or a zero-length bone
    /// (naming frame and joint); lengths that are not finite and `>= 0`; a
    /// frame rate that is not finite and positive.
    pub fn new(poses: &[Pose], lengths: &BoneLengths, fps: f64) -> Result<Motion, ExportError> {
        if poses.is_empty() {
            return Err(ExportError::NoPoses);
        }
        if !(fps.is_finite() && fps > 0.0) {
            return Err(ExportError::FrameRate(fps));
        }
        validate_lengths(lengths).map_err(ExportError::Lengths)?;
        let reposed = adjust_sequence(poses, lengths).map_err(|e| match e {
            e @ BoneError::InFrame { .. } => ExportError::Pose(e),
            e => ExportError::Lengths(e),
        })?;
        let repose_shift = poses
            .iter()
            .zip(&reposed)
            .flat_map(|(a, b)| a.iter().zip(b))
            .map(|(a, b)| {
                let d: [f64; 3] = std::array::from_fn(|k| a[k] as f64 - b[k] as f64);
                (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt()
            })
            .fold(0.0, f64::max);
        Ok(Motion {
            poses: reposed,
            lengths: *lengths,
            fps,
            axes: Axes::default(),
            repose_shift,
        })
    }

    /// The same motion exported for a world whose up direction is `up` in
    /// the poses' coordinates (e.g. a replay file's `camera_up`).
    pub fn with_up(mut self, up: [f64; 3]) -> Result<Motion, ExportError> {
        self.axes = Axes::from_up(up)?;
        Ok(self)
    }

    /// The re-posed poses (metres, the poses' own coordinates).
    pub fn poses(&self) -> &[Pose] {
        &self.poses
    }

    /// The one set of bone lengths every frame has.
    pub fn lengths(&self) -> &BoneLengths {
        &self.lengths
    }

    /// Frames per second.
    pub fn fps(&self) -> f64 {
        self.fps
    }

    /// The export frames.
    pub fn axes(&self) -> &Axes {
        &self.axes
    }

    /// Number of frames.
    pub fn len(&self) -> usize {
        self.poses.len()
    }

    /// Never true (a motion has at least one frame); for clippy's sake.
    pub fn is_empty(&self) -> bool {
        self.poses.is_empty()
    }

    /// The largest distance (metres) re-posing moved any joint of any frame:
    /// about 1e-7 for poses that already had these lengths.
    pub fn repose_shift(&self) -> f64 {
        self.repose_shift
    }

    /// Frame `t`'s joints in the Y-up frame, metres.
    pub fn y_up(&self, t: usize) -> [[f64; 3]; 17] {
        self.poses[t].map(|p| self.axes.to_y_up(p.map(f64::from)))
    }

    /// Frame `t`'s joints in the Z-up frame, millimetres.
    pub fn z_up_mm(&self, t: usize) -> [[f64; 3]; 17] {
        self.poses[t].map(|p| self.axes.to_z_up(p.map(|v| 1000.0 * v as f64)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pose() -> Pose {
        std::array::from_fn(|j| {
            [
                0.1 * j as f32,
                -0.05 * (j * j) as f32,
                0.02 * j as f32 + 0.3,
            ]
        })
    }

    #[test]
    fn reposes_with_the_given_lengths() {
        let lengths = [0.2; 16];
        let m = Motion::new(&[pose(), pose()], &lengths, 50.0).unwrap();
        let got = blapose_core::bones::bone_lengths(&m.poses()[1]);
        assert!(got.iter().all(|l| (l - 0.2).abs() < 1e-6));
        assert!(m.repose_shift() > 0.01);
        assert_eq!(m.poses()[0][0], pose()[0]);
        let again = Motion::new(m.poses(), &lengths, 50.0).unwrap();
        assert!(again.repose_shift() < 1e-6);
    }

    #[test]
    fn bad_requests_are_named() {
        let lengths = [0.2; 16];
        assert!(matches!(
            Motion::new(&[], &lengths, 50.0),
            Err(ExportError::NoPoses)
        ));
        let mut bad = pose();
        bad[3][1] = f32::NAN;
        let e = Motion::new(&[pose(), bad], &lengths, 50.0).unwrap_err();
        assert_eq!(
            e.to_string(),
            "cannot export: frame 1: joint 3 (r_ankle) has a non-finite coordinate"
        );
        let mut l = lengths;
        l[2] = -1.0;
        assert!(matches!(
            Motion::new(&[pose()], &l, 50.0),
            Err(ExportError::Lengths(_))
        ));
        assert!(matches!(
            Motion::new(&[pose()], &lengths, 0.0),
            Err(ExportError::FrameRate(_))
        ));
        assert!(Motion::new(&[pose()], &lengths, 50.0)
            .unwrap()
            .with_up([0.0; 3])
            .is_err());
    }
}

//! A learned linear refiner of bone directions, measured and not served:
//! each frame's directions one linear map of the lifter's directions over
//! the last [`RefinerWindow::past`] frames (every bone together), of the
//! 2D keypoints of the last [`RefinerWindow::past_2d`] frames (root-relative
//! and scale-free) and, offline, of [`RefinerWindow::future`] frames after
//! it; fitted by least squares with velocity and acceleration terms
//! against the true directions ([`RefinerFit`]).
//!
//! Why it is not served (docs/research.md, "Motion: a learned refiner"):
//! fitted on camera 0 of some training recordings and scored on camera 0
//! of others it beat every filter (MPJPE 61.32 against the plain GRU's
//! 61.68 at MPJVE 4.28); fitted across all four cameras it is no better
//! than the per-channel Kalman filter. What it learned was the lifter's
//! errors as one camera sees them, on subjects the lifter was trained on.

use blapose_core::bones::{decompose, rebuild};
use blapose_core::motion::{direction_values, DIRECTION_CHANNELS};
use blapose_core::skeleton::NUM_JOINTS;
use blapose_core::Pose;
use blapose_train::synth::FRAME_DIM;
use nalgebra::DMatrix;

/// Values of one frame's 2D keypoints as the refiner reads them: every
/// joint but the root, relative to it, divided by their RMS distance.
pub const KEYS_2D: usize = 2 * (NUM_JOINTS - 1);

/// One frame's bone directions as values (16 bones x 3).
pub type DirectionValues = [f64; DIRECTION_CHANNELS];

/// One frame's keypoints as the refiner reads them ([`scale_free_keys`]).
pub type ScaleFreeKeys = [f64; KEYS_2D];

/// Which frames a refiner reads around the one it answers.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RefinerWindow {
    /// Frames of directions up to and including this one (at least 1).
    pub past: usize,
    /// Frames of directions after this one (0: causal).
    pub future: usize,
    /// Frames of 2D keypoints up to and including this one (0: none).
    pub past_2d: usize,
}

impl RefinerWindow {
    /// Features per frame, the constant included.
    pub const fn features(&self) -> usize {
        (self.past + self.future) * DIRECTION_CHANNELS + self.past_2d * KEYS_2D + 1
    }

    /// Append the features of one frame to `out`: `dirs(k)` is the
    /// directions `k` frames from it (`k <= 0` before, `k > 0` after),
    /// `keys(k)` the keypoints `k` frames before it. The one definition of
    /// the features, for fitting and refining alike.
    pub fn features_into<'a>(
        &self,
        dirs: impl Fn(isize) -> &'a DirectionValues,
        keys: impl Fn(usize) -> &'a ScaleFreeKeys,
        out: &mut Vec<f64>,
    ) {
        for k in 0..self.past {
            out.extend_from_slice(dirs(-(k as isize)));
        }
        for k in 1..=self.future {
            out.extend_from_slice(dirs(k as isize));
        }
        for k in 0..self.past_2d {
            out.extend_from_slice(keys(k));
        }
        out.push(1.0);
    }
}

/// A frame's 2D keypoints (`2 * NUM_JOINTS` values, any units) as the
/// refiner reads them; `None` when not finite or all at the root.
pub fn scale_free_keys(frame: &[f32]) -> Option<ScaleFreeKeys> {
    if frame.len() != 2 * NUM_JOINTS {
        return None;
    }
    let (rx, ry) = (frame[0] as f64, frame[1] as f64);
    let rel: [f64; KEYS_2D] = std::array::from_fn(|i| {
        let (j, axis) = (1 + i / 2, i % 2);
        frame[2 * j + axis] as f64 - if axis == 0 { rx } else { ry }
    });
    let rms = (rel.iter().map(|v| v * v).sum::<f64>() / KEYS_2D as f64).sqrt();
    (rms.is_finite() && rms > 0.0).then(|| rel.map(|v| v / rms))
}

/// Keypoints per frame with gaps (`None`: a missing joint, bad values)
/// filled the way a stream fills them: the frame before, or zeros before
/// any.
pub fn held_keys(frames: impl IntoIterator<Item = Option<ScaleFreeKeys>>) -> Vec<ScaleFreeKeys> {
    let mut last = [0.0; KEYS_2D];
    frames
        .into_iter()
        .map(|k| {
            if let Some(k) = k {
                last = k;
            }
            last
        })
        .collect()
}

/// A fitted refiner: its window and its map.
#[derive(Debug, Clone, PartialEq)]
pub struct Refiner {
    /// Frames it reads.
    pub window: RefinerWindow,
    /// The map, `features x DIRECTION_CHANNELS`, row-major.
    pub weights: Vec<f64>,
}

impl Refiner {
    /// Whether it reads frames after the one it answers.
    pub fn is_causal(&self) -> bool {
        self.window.future == 0
    }

    /// The directions of one frame from its features (unnormalized).
    pub fn apply(&self, features: &[f64]) -> DirectionValues {
        let mut y = [0.0; DIRECTION_CHANNELS];
        for (f, row) in features
            .iter()
            .zip(self.weights.chunks_exact(DIRECTION_CHANNELS))
        {
            for (y, w) in y.iter_mut().zip(row) {
                *y += f * w;
            }
        }
        y
    }

    /// A whole recording refined: `dirs` and `keys` per frame (as
    /// [`held_keys`] fills them), edges held.
    pub fn refine_sequence(
        &self,
        dirs: &[DirectionValues],
        keys: &[ScaleFreeKeys],
    ) -> Vec<DirectionValues> {
        let n = dirs.len().min(keys.len());
        let mut features = Vec::with_capacity(self.window.features());
        (0..n)
            .map(|t| {
                features.clear();
                self.window.features_into(
                    |k| &dirs[(t as isize + k).clamp(0, n as isize - 1) as usize],
                    |k| &keys[t.saturating_sub(k)],
                    &mut features,
                );
                self.apply(&features)
            })
            .collect()
    }
}

/// A trial's refiner inputs: the lifted poses' directions (a frame with a
/// zero bone repeats the one before) and its keypoints (`frames * 34`).
pub fn refiner_inputs(
    lifted: &[Pose],
    input: &[f32],
) -> (Vec<DirectionValues>, Vec<ScaleFreeKeys>) {
    (
        held_directions(lifted),
        held_keys(input.chunks_exact(FRAME_DIM).map(scale_free_keys)),
    )
}

fn held_directions(poses: &[Pose]) -> Vec<DirectionValues> {
    let mut last = [0.0; DIRECTION_CHANNELS];
    poses
        .iter()
        .map(|p| {
            if let Some(d) = direction_values(p) {
                last = d;
            }
            last
        })
        .collect()
}

/// `lifted` with each frame's directions refined by `refiner` (offline:
/// the whole trial at once), each pose keeping its own lengths and root.
pub fn refine_poses(refiner: &Refiner, lifted: &[Pose], input: &[f32]) -> Vec<Pose> {
    let (dirs, keys) = refiner_inputs(lifted, input);
    let refined = refiner.refine_sequence(&dirs, &keys);
    lifted
        .iter()
        .zip(&refined)
        .map(|(p, y)| match decompose(p) {
            Ok((lengths, _)) => {
                let d = std::array::from_fn(|b| {
                    let v: [f64; 3] = std::array::from_fn(|i| y[3 * b + i]);
                    let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
                    if n > 0.0 && n.is_finite() {
                        v.map(|x| (x / n) as f32)
                    } else {
                        v.map(|x| x as f32)
                    }
                });
                rebuild(p[0], &d, &lengths)
            }
            Err(_) => *p,
        })
        .collect()
}

/// The normal equations of the three terms, summed over trials.
#[derive(Debug, Clone)]
pub struct RefinerFit {
    window: RefinerWindow,
    normal: [DMatrix<f64>; 3],
    rhs: [DMatrix<f64>; 3],
    frames: usize,
}

fn diff(m: &DMatrix<f64>) -> DMatrix<f64> {
    let n = m.nrows();
    if n < 2 {
        return DMatrix::zeros(0, m.ncols());
    }
    m.rows(1, n - 1) - m.rows(0, n - 1)
}

impl RefinerFit {
    /// Empty sums for a refiner reading `window`.
    pub fn new(window: RefinerWindow) -> Self {
        let d = window.features();
        Self {
            window,
            normal: std::array::from_fn(|_| DMatrix::zeros(d, d)),
            rhs: std::array::from_fn(|_| DMatrix::zeros(d, DIRECTION_CHANNELS)),
            frames: 0,
        }
    }

    /// Frames summed so far.
    pub fn frames(&self) -> usize {
        self.frames
    }

    /// Add one trial: the lifter's poses, its keypoints and the truth.
    pub fn add(&mut self, lifted: &[Pose], input: &[f32], truth: &[Pose]) {
        let (dirs, keys) = refiner_inputs(lifted, input);
        let n = dirs.len().min(keys.len()).min(truth.len());
        if n < 3 {
            return;
        }
        let d = self.window.features();
        let mut f = DMatrix::zeros(n, d);
        let mut row = Vec::with_capacity(d);
        for t in 0..n {
            row.clear();
            self.window.features_into(
                |k| &dirs[(t as isize + k).clamp(0, n as isize - 1) as usize],
                |k| &keys[t.saturating_sub(k)],
                &mut row,
            );
            for (c, v) in row.iter().enumerate() {
                f[(t, c)] = *v;
            }
        }
        let truth = held_directions(&truth[..n]);
        let g = DMatrix::from_fn(n, DIRECTION_CHANNELS, |t, c| truth[t][c]);
        let (fv, gv) = (diff(&f), diff(&g));
        let (fa, ga) = (diff(&fv), diff(&gv));
        for (i, (x, y)) in [(f, g), (fv, gv), (fa, ga)].into_iter().enumerate() {
            self.normal[i] += x.tr_mul(&x);
            self.rhs[i] += x.tr_mul(&y);
        }
        self.frames += n;
    }

    /// The refiner for velocity and acceleration weights, with a ridge of
    /// `ridge` times the mean diagonal; `None` when the sums are singular.
    pub fn solve(&self, velocity_weight: f64, accel_weight: f64, ridge: f64) -> Option<Refiner> {
        let w = [1.0, velocity_weight, accel_weight];
        let mut a = &self.normal[0] * w[0] + &self.normal[1] * w[1] + &self.normal[2] * w[2];
        let b = &self.rhs[0] * w[0] + &self.rhs[1] * w[1] + &self.rhs[2] * w[2];
        let mean_diag = a.diagonal().mean();
        for i in 0..a.nrows() {
            a[(i, i)] += ridge * mean_diag;
        }
        let x = a.cholesky()?.solve(&b);
        // Row-major features x channels.
        let weights = (0..x.nrows())
            .flat_map(|r| (0..x.ncols()).map(move |c| (r, c)))
            .map(|(r, c)| x[(r, c)])
            .collect();
        Some(Refiner {
            window: self.window,
            weights,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use blapose_core::skeleton::NUM_JOINTS;

    fn pose(t: usize, wobble: f32) -> Pose {
        std::array::from_fn(|j| {
            let j = j as f32;
            let s = if t.is_multiple_of(2) { wobble } else { -wobble };
            [
                0.1 * j + s * (j % 3.0),
                0.05 * j * j.sin() + 0.01 * (t as f32 * 0.05).sin(),
                0.02 * j + 0.1,
            ]
        })
    }

    #[test]
    fn the_fit_learns_to_remove_a_jitter_it_was_shown() {
        let truth: Vec<Pose> = (0..300).map(|t| pose(t, 0.0)).collect();
        let lifted: Vec<Pose> = (0..300).map(|t| pose(t, 0.01)).collect();
        let input: Vec<f32> = (0..300 * 2 * NUM_JOINTS)
            .map(|i| (i % 34) as f32 * 0.01)
            .collect();
        let w = RefinerWindow {
            past: 2,
            future: 0,
            past_2d: 1,
        };
        let mut fit = RefinerFit::new(w);
        fit.add(&lifted, &input, &truth);
        assert_eq!(fit.frames(), 300);
        let r = fit.solve(0.0, 0.0, 1e-9).expect("solvable");
        // Direction error (the lifted lengths are kept, so positions would
        // measure the lengths' wobble too).
        let err = |a: &[Pose]| -> f64 {
            a.iter()
                .zip(&truth)
                .map(|(p, g)| {
                    let (p, g) = (direction_values(p).unwrap(), direction_values(g).unwrap());
                    p.iter().zip(&g).map(|(x, y)| (x - y).abs()).sum::<f64>()
                })
                .sum()
        };
        let refined = refine_poses(&r, &lifted, &input);
        assert!(
            err(&refined) < 0.2 * err(&lifted),
            "refined {} vs lifted {}",
            err(&refined),
            err(&lifted)
        );
    }
}

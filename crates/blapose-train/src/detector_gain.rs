//! How strongly the 2D detector's bones follow a person's real bone lengths.
//!
//! The synthetic input is `project(body with the drawn lengths) + residual of
//! the original subject` ([`crate::synth`]). That assumes the detector shows
//! a longer bone exactly as much longer as it is. The training subjects'
//! real Stacked Hourglass detections say otherwise: across S1 S5 S6 S7 S8
//! the detected hip width moves about a third as much as the mocap hip
//! width, the thigh about half as much, while the shoulders follow one to
//! one. A model trained on full-gain bodies reads a big person's compressed
//! detections as an average one (the shipped Bi-GRU under-estimated S9's
//! thighs by centimetres).
//!
//! The model here is one gain `g_b` per bone: the detector shows bone `b` of
//! a person with length `L` as long as it would show a person of the
//! original subject's length `X` scaled by `X + g_b (L - X)`. The synthetic
//! input is rebuilt with those *shown* lengths ([`DetectorGain::shown`])
//! while the target stays `L`; with the subject's own lengths nothing
//! changes, so the real residual still reproduces the real detection
//! exactly.
//!
//! **Fitted on the training subjects only** ([`DetectorGain::fit`]): for
//! each subject and bone, the ratio of the summed 2D bone lengths of its
//! real detections to those of its ground truth projected with the same
//! camera ([`ImageBoneSums`]) turns its true length `L_s` into a detected
//! length `D_s = ratio * L_s`; the gain is the least-squares slope of `D`
//! on `L` over the subjects (symmetric pairs pooled), shrunk towards 1 (the
//! old assumption) by its standard error under a `N(1, PRIOR_STD^2)` prior:
//! five subjects give a noisy slope, and a bone with no evidence keeps the
//! full gain. Bones that are the same for every subject (the head) have
//! gain 1.

use std::collections::BTreeMap;

use blapose_core::skeleton::{bone_child, bone_parent, NUM_BONES, SYMMETRIC_BONE_PAIRS};
use blapose_core::{BoneLengths, Keypoints2d};

use crate::error::TrainError;
use crate::lengths::FIXED_BONE_STD;

/// Standard deviation of the prior on each gain around 1 (chosen before
/// looking at any result: a detector that halves or doubles a bone's
/// variation is plausible, one that reverses it is not).
pub const PRIOR_STD: f64 = 0.5;

/// One subject's 2D bone lengths summed over frames: its real detections
/// and its ground truth projected with the same cameras. Only the ratio
/// matters, so any common 2D unit (normalized screen coordinates) works.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ImageBoneSums {
    /// Summed detected 2D bone lengths.
    pub detected: [f64; NUM_BONES],
    /// Summed projected ground-truth 2D bone lengths.
    pub projected: [f64; NUM_BONES],
}

impl Default for ImageBoneSums {
    fn default() -> Self {
        Self {
            detected: [0.0; NUM_BONES],
            projected: [0.0; NUM_BONES],
        }
    }
}

fn image_bone_length(kp: &Keypoints2d, bone: usize) -> f64 {
    let (c, p) = (kp[bone_child(bone)], kp[bone_parent(bone)]);
    f64::from(c[0] - p[0]).hypot(f64::from(c[1] - p[1]))
}

impl ImageBoneSums {
    /// Add one frame (skipped when any coordinate is not finite).
    pub fn add_frame(&mut self, detected: &Keypoints2d, projected: &Keypoints2d) {
        let finite = |kp: &Keypoints2d| kp.iter().flatten().all(|v| v.is_finite());
        if !finite(detected) || !finite(projected) {
            return;
        }
        for b in 0..NUM_BONES {
            self.detected[b] += image_bone_length(detected, b);
            self.projected[b] += image_bone_length(projected, b);
        }
    }

    /// Add another subject-part's sums.
    pub fn merge(&mut self, other: &ImageBoneSums) {
        for b in 0..NUM_BONES {
            self.detected[b] += other.detected[b];
            self.projected[b] += other.projected[b];
        }
    }

    /// Detected over projected length per bone (`None` where nothing was
    /// projected).
    pub fn ratio(&self, bone: usize) -> Option<f64> {
        (self.projected[bone] > 0.0).then(|| self.detected[bone] / self.projected[bone])
    }
}

/// The per-bone gains (see the module docs).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DetectorGain {
    /// `g_b`: 1 = the detector follows bone `b` one to one.
    pub gain: [f32; NUM_BONES],
}

impl Default for DetectorGain {
    fn default() -> Self {
        Self::unit()
    }
}

impl DetectorGain {
    /// Every bone shown as it is (the pipeline before this module).
    pub fn unit() -> Self {
        Self {
            gain: [1.0; NUM_BONES],
        }
    }

    /// Fit the gains to the training subjects' true lengths and image sums.
    /// Callers pass training subjects only (the data loader's
    /// [`crate::dataset::TrainingSet`] holds nothing else).
    pub fn fit(
        lengths: &BTreeMap<String, BoneLengths>,
        sums: &BTreeMap<String, ImageBoneSums>,
    ) -> Result<Self, TrainError> {
        // (true, detected) length pairs per bone, one per subject.
        let mut points: Vec<[(f64, f64); NUM_BONES]> = Vec::new();
        for (subject, l) in lengths {
            let s = sums.get(subject).ok_or_else(|| {
                TrainError::Data(format!(
                    "no detections of {subject} to fit the detector gain"
                ))
            })?;
            let mut row = [(0.0, 0.0); NUM_BONES];
            for (b, r) in row.iter_mut().enumerate() {
                let ratio = s.ratio(b).ok_or_else(|| {
                    TrainError::Data(format!("{subject}: bone {b} never seen in 2D"))
                })?;
                *r = (f64::from(l[b]), ratio * f64::from(l[b]));
            }
            points.push(row);
        }
        if points.len() < 3 {
            return Err(TrainError::Data(format!(
                "the detector gain needs at least 3 subjects, got {}",
                points.len()
            )));
        }
        let mut gain = [1.0f32; NUM_BONES];
        let mut done = [false; NUM_BONES];
        for b in 0..NUM_BONES {
            if done[b] {
                continue;
            }
            let pair = SYMMETRIC_BONE_PAIRS
                .iter()
                .find(|&&(l, r)| l == b || r == b)
                .map(|&(l, r)| [l, r]);
            let bones: Vec<usize> = pair.map_or(vec![b], |p| p.to_vec());
            let xy: Vec<(f64, f64)> = points
                .iter()
                .map(|row| {
                    let n = bones.len() as f64;
                    let x = bones.iter().map(|&k| row[k].0).sum::<f64>() / n;
                    let y = bones.iter().map(|&k| row[k].1).sum::<f64>() / n;
                    (x, y)
                })
                .collect();
            let g = shrunk_slope(&xy).unwrap_or(1.0) as f32;
            for &k in &bones {
                gain[k] = g;
                done[k] = true;
            }
        }
        Ok(Self { gain })
    }

    /// The lengths the detector shows for a person of `drawn` lengths, the
    /// sample having been built from a subject of `original` lengths:
    /// `X + g (L - X)` per bone.
    pub fn shown(&self, original: &BoneLengths, drawn: &BoneLengths) -> BoneLengths {
        std::array::from_fn(|b| original[b] + self.gain[b] * (drawn[b] - original[b]))
    }

    /// True when every gain is 1 (the synthesis is unchanged).
    pub fn is_unit(&self) -> bool {
        self.gain.iter().all(|&g| g == 1.0)
    }
}

/// The least-squares slope of `y` on `x`, shrunk towards 1 under a
/// `N(1, PRIOR_STD^2)` prior by its standard error; `None` when `x` does not
/// vary (a fixed bone) or there are too few points for an error.
fn shrunk_slope(xy: &[(f64, f64)]) -> Option<f64> {
    let n = xy.len() as f64;
    if xy.len() < 3 {
        return None;
    }
    let mx = xy.iter().map(|p| p.0).sum::<f64>() / n;
    let my = xy.iter().map(|p| p.1).sum::<f64>() / n;
    let sxx: f64 = xy.iter().map(|p| (p.0 - mx).powi(2)).sum();
    if (sxx / n).sqrt() < f64::from(FIXED_BONE_STD) {
        return None;
    }
    let slope = xy.iter().map(|p| (p.0 - mx) * (p.1 - my)).sum::<f64>() / sxx;
    let rss: f64 = xy
        .iter()
        .map(|p| (p.1 - my - slope * (p.0 - mx)).powi(2))
        .sum();
    let se2 = (rss / (n - 2.0) / sxx).max(1e-12);
    let prior = PRIOR_STD * PRIOR_STD;
    Some((slope / se2 + 1.0 / prior) / (1.0 / se2 + 1.0 / prior))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn subjects(
        gain: f64,
        bone: usize,
    ) -> (
        BTreeMap<String, BoneLengths>,
        BTreeMap<String, ImageBoneSums>,
    ) {
        let mut lengths = BTreeMap::new();
        let mut sums = BTreeMap::new();
        for (i, delta) in [-0.02f64, -0.01, 0.0, 0.012, 0.018].iter().enumerate() {
            let mut l = [0.3f32; NUM_BONES];
            l[bone] = (0.3 + delta) as f32;
            let mut s = ImageBoneSums::default();
            for b in 0..NUM_BONES {
                s.projected[b] = 100.0;
                // Detected length 0.3 + gain * delta, as a ratio of the true one.
                let shown = if b == bone { 0.3 + gain * delta } else { 0.3 };
                s.detected[b] = 100.0 * shown / f64::from(l[b]);
            }
            lengths.insert(format!("S{i}"), l);
            sums.insert(format!("S{i}"), s);
        }
        (lengths, sums)
    }

    #[test]
    fn an_exact_slope_is_recovered_and_unvarying_bones_keep_gain_one() {
        // Bone 7 (thorax) has no symmetric partner.
        let (lengths, sums) = subjects(0.4, 7);
        let g = DetectorGain::fit(&lengths, &sums).unwrap();
        assert!((g.gain[7] - 0.4).abs() < 1e-3, "{:?}", g.gain);
        for b in (0..NUM_BONES).filter(|&b| b != 7) {
            assert_eq!(g.gain[b], 1.0, "bone {b} does not vary");
        }
    }

    #[test]
    fn symmetric_bones_share_one_gain() {
        let (lengths, sums) = subjects(0.5, 1); // r_thigh varies, l_thigh not
        let g = DetectorGain::fit(&lengths, &sums).unwrap();
        assert_eq!(g.gain[1], g.gain[4]);
        assert!(g.gain[1] < 1.0 && g.gain[1] > 0.5, "{:?}", g.gain);
    }

    #[test]
    fn noisy_slopes_are_pulled_towards_one() {
        let xy = [
            (0.40, 0.30),
            (0.42, 0.36),
            (0.44, 0.28),
            (0.46, 0.37),
            (0.48, 0.29),
        ];
        let g = shrunk_slope(&xy).unwrap();
        let n = xy.len() as f64;
        let (mx, my) = (
            xy.iter().map(|p| p.0).sum::<f64>() / n,
            xy.iter().map(|p| p.1).sum::<f64>() / n,
        );
        let ols = xy.iter().map(|p| (p.0 - mx) * (p.1 - my)).sum::<f64>()
            / xy.iter().map(|p| (p.0 - mx).powi(2)).sum::<f64>();
        assert!((g - 1.0).abs() < (ols - 1.0).abs(), "ols {ols}, shrunk {g}");
    }

    #[test]
    fn shown_lengths_keep_the_original_and_scale_the_change() {
        let mut g = DetectorGain::unit();
        g.gain[1] = 0.5;
        let original = [0.4f32; NUM_BONES];
        let drawn = [0.5f32; NUM_BONES];
        let shown = g.shown(&original, &drawn);
        assert!((shown[1] - 0.45).abs() < 1e-6);
        assert_eq!(shown[0], 0.5);
        assert_eq!(g.shown(&original, &original), original);
        assert!(DetectorGain::unit().is_unit() && !g.is_unit());
    }

    #[test]
    fn a_missing_subject_or_too_few_subjects_is_an_error() {
        let (lengths, mut sums) = subjects(0.5, 7);
        sums.remove("S0");
        assert!(DetectorGain::fit(&lengths, &sums).is_err());
        let (mut lengths, sums) = subjects(0.5, 7);
        lengths.retain(|k, _| k == "S0" || k == "S1");
        assert!(DetectorGain::fit(&lengths, &sums).is_err());
    }

    #[test]
    fn image_sums_skip_non_finite_frames() {
        let mut s = ImageBoneSums::default();
        let a: Keypoints2d = std::array::from_fn(|j| [j as f32 * 0.01, 0.0]);
        let mut bad = a;
        bad[3][0] = f32::NAN;
        s.add_frame(&a, &a);
        s.add_frame(&bad, &a);
        assert_eq!(s.ratio(0), Some(1.0));
        let mut t = ImageBoneSums::default();
        t.merge(&s);
        assert_eq!(t, s);
    }
}

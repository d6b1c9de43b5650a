//! The proportion reader: a person's 16 bone lengths from their stature
//! (and sex) *and* the proportions their 2D keypoints show, as the server
//! answers a session or request that gives the stature.
//!
//! Why: the stature regression ([`crate::stature`]) knows only the height,
//! so it gives everyone of one height the same body; what is left is
//! proportion given height (a long-legged person against a long-bodied one
//! of the same stature), and that *is* visible in 2D, where absolute size
//! is not. Each frame's bones are measured as fractions of the frame's
//! summed bone length (so distance, lens and image size cancel); over the
//! stream the reader keeps each fraction's mean and spread, and one linear
//! model per bone maps stature and stature times those statistics to
//! lengths. On the many-bodies benchmark this takes the error given the
//! height well below the regression's, where the recurrent models added
//! nothing (models/README.md, "The proportion reader").
//!
//! Streams start at the population: the statistics are shrunk towards the
//! fitting set's mean by [`SHRINK_FRAMES`] pseudo-frames, so the first
//! answer is close to the regression's and later ones follow the video.
//! Only frames with every joint detected count (a held joint would show a
//! stale proportion).
//!
//! The file (`models/proportion_reader.json`) is written by `blapose
//! fit-proportions` (`blapose_train::proportions`, fitted on ANSUR
//! training-split bodies on the training subjects' motion through wide
//! cameras with real-detector noise) and embedded in the server; this
//! module defines the statistics and applies the file, so fitting and
//! serving share one definition.

use blapose_core::skeleton::{bone_child, bone_parent, NUM_BONES};
use blapose_core::{BoneLengths, Keypoints2d};
use serde::{Deserialize, Serialize};

use crate::stature::Sex;

/// The file's `format`.
pub const PROPORTIONS_FORMAT: &str = "blapose-proportion-reader/1";

/// Features per stream: each bone fraction's mean, then its spread.
pub const FEATURES: usize = 2 * NUM_BONES;

/// Inputs of each bone's linear model: the stature, then the stature times
/// each feature.
pub const INPUTS: usize = 1 + FEATURES;

/// Pseudo-frames at the fitting set's mean statistics that every stream's
/// statistics start with (chosen on a validation split of the training
/// bodies: 10 gives the lowest error after 10-100 frames and the same
/// after 500).
pub const SHRINK_FRAMES: f64 = 10.0;

/// Smallest summed bone length (keypoint units) a frame must show to count:
/// below it the fractions are noise.
const MIN_TOTAL: f64 = 1e-6;

/// Bytes of [`ProportionStats::to_bytes`].
pub const STATS_BYTES: usize = 8 + 2 * NUM_BONES * 8;

/// A stream's running bone-fraction statistics: frames counted and, per
/// bone, the sums of its fraction and of its square.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ProportionStats {
    frames: u64,
    sum: [f64; NUM_BONES],
    sum_sq: [f64; NUM_BONES],
}

/// Each bone's length in one frame over the frame's summed bone length;
/// `None` when the frame shows no measurable body (or a non-finite value).
pub fn bone_fractions(kp: &Keypoints2d) -> Option<[f64; NUM_BONES]> {
    let lengths: [f64; NUM_BONES] = std::array::from_fn(|b| {
        let (p, c) = (kp[bone_parent(b)], kp[bone_child(b)]);
        f64::from(c[0] - p[0]).hypot(f64::from(c[1] - p[1]))
    });
    let total: f64 = lengths.iter().sum();
    (total.is_finite() && total > MIN_TOTAL).then(|| lengths.map(|l| l / total))
}

impl ProportionStats {
    /// Count one frame whose every joint was detected; `false` (nothing
    /// counted) when it shows no measurable body.
    pub fn push(&mut self, kp: &Keypoints2d) -> bool {
        let Some(fractions) = bone_fractions(kp) else {
            return false;
        };
        self.frames += 1;
        for (b, r) in fractions.into_iter().enumerate() {
            self.sum[b] += r;
            self.sum_sq[b] += r * r;
        }
        true
    }

    /// Frames counted.
    pub fn frames(&self) -> u64 {
        self.frames
    }

    /// The statistics of a whole clip (frames `17 * 2` values each, every
    /// joint detected).
    pub fn of_frames(frames: &[f32]) -> Self {
        let mut stats = Self::default();
        for f in frames.chunks_exact(2 * blapose_core::NUM_JOINTS) {
            let kp: Keypoints2d = std::array::from_fn(|j| [f[2 * j], f[2 * j + 1]]);
            stats.push(&kp);
        }
        stats
    }

    /// The features: each fraction's mean, then its standard deviation,
    /// both over the counted frames plus [`SHRINK_FRAMES`] frames at
    /// `prior`'s moments.
    pub fn features(&self, prior: &FeaturePrior) -> [f64; FEATURES] {
        let n = self.frames as f64 + SHRINK_FRAMES;
        let mut out = [0.0; FEATURES];
        for b in 0..NUM_BONES {
            let m1 = (self.sum[b] + SHRINK_FRAMES * prior.mean[b]) / n;
            let m2 = (self.sum_sq[b] + SHRINK_FRAMES * prior.mean_square[b]) / n;
            out[b] = m1;
            out[NUM_BONES + b] = (m2 - m1 * m1).max(0.0).sqrt();
        }
        out
    }

    /// The raw moments (no shrinkage): per bone, the mean fraction and the
    /// mean squared fraction; `None` before the first counted frame.
    pub fn moments(&self) -> Option<([f64; NUM_BONES], [f64; NUM_BONES])> {
        (self.frames > 0).then(|| {
            let n = self.frames as f64;
            (self.sum.map(|s| s / n), self.sum_sq.map(|s| s / n))
        })
    }

    /// Little-endian bytes ([`STATS_BYTES`]): frames, sums, sums of squares.
    pub fn to_bytes(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(STATS_BYTES);
        out.extend_from_slice(&self.frames.to_le_bytes());
        for v in self.sum.iter().chain(&self.sum_sq) {
            out.extend_from_slice(&v.to_le_bytes());
        }
        out
    }

    /// Read [`Self::to_bytes`]; `None` when the length is wrong or a value
    /// could not come from counted frames (non-finite or negative sums, or
    /// sums without frames).
    pub fn from_bytes(bytes: &[u8]) -> Option<Self> {
        if bytes.len() != STATS_BYTES {
            return None;
        }
        let frames = u64::from_le_bytes(bytes[..8].try_into().ok()?);
        let value = |i: usize| -> Option<f64> {
            let start = 8 + 8 * i;
            let v = f64::from_le_bytes(bytes[start..start + 8].try_into().ok()?);
            (v.is_finite() && v >= 0.0).then_some(v)
        };
        let mut stats = Self {
            frames,
            ..Self::default()
        };
        for b in 0..NUM_BONES {
            stats.sum[b] = value(b)?;
            stats.sum_sq[b] = value(NUM_BONES + b)?;
        }
        let empty = stats.sum.iter().chain(&stats.sum_sq).all(|&v| v == 0.0);
        (frames > 0 || empty).then_some(stats)
    }
}

/// The fitting set's mean moments, what [`ProportionStats::features`]
/// shrinks towards.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FeaturePrior {
    /// Per bone, the mean fraction.
    pub mean: Vec<f64>,
    /// Per bone, the mean squared fraction.
    pub mean_square: Vec<f64>,
}

/// One linear model per bone: `length = intercept + weights . inputs`,
/// inputs `[stature, stature * feature_1, ...]` (metres).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ReaderLines {
    /// Per bone, metres.
    pub intercept: Vec<f64>,
    /// Per bone, [`INPUTS`] weights.
    pub weights: Vec<Vec<f64>>,
    /// Bodies fitted on.
    pub people: usize,
}

/// The reader for everyone, and for each sex.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ProportionModel {
    /// [`PROPORTIONS_FORMAT`].
    pub format: String,
    /// Where it comes from (data, split, command).
    pub source: String,
    /// What streams start at.
    pub prior: FeaturePrior,
    /// Everyone (used when the sex is not given).
    pub pooled: ReaderLines,
    /// Women.
    pub female: ReaderLines,
    /// Men.
    pub male: ReaderLines,
}

/// Why a proportion-reader file was refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ProportionModelError {
    /// Not JSON of the expected shape.
    #[error("the proportion reader does not parse: {0}")]
    Parse(String),
    /// Another format.
    #[error("the proportion reader has format {0:?}; expected {PROPORTIONS_FORMAT:?}")]
    Format(String),
    /// A model without 16 finite intercepts and 16 x 33 finite weights.
    #[error("the proportion reader's {0} model needs 16 finite intercepts and 16 x {INPUTS} finite weights")]
    Lines(&'static str),
    /// A prior without 16 finite non-negative moments per kind.
    #[error("the proportion reader's prior needs 16 finite non-negative moments of each kind")]
    Prior,
}

impl ReaderLines {
    fn check(&self, name: &'static str) -> Result<(), ProportionModelError> {
        let finite = |v: &[f64]| v.iter().all(|x| x.is_finite());
        let ok = self.intercept.len() == NUM_BONES
            && finite(&self.intercept)
            && self.weights.len() == NUM_BONES
            && self.weights.iter().all(|w| w.len() == INPUTS && finite(w));
        if ok {
            Ok(())
        } else {
            Err(ProportionModelError::Lines(name))
        }
    }

    fn predict(&self, inputs: &[f64; INPUTS]) -> BoneLengths {
        std::array::from_fn(|b| {
            let dot: f64 = self.weights[b].iter().zip(inputs).map(|(w, x)| w * x).sum();
            (self.intercept[b] + dot) as f32
        })
    }
}

/// A bone model's inputs: the stature, then the stature times each feature.
pub fn inputs(stature_m: f64, features: &[f64; FEATURES]) -> [f64; INPUTS] {
    std::array::from_fn(|i| {
        if i == 0 {
            stature_m
        } else {
            stature_m * features[i - 1]
        }
    })
}

impl ProportionModel {
    /// Read and check a model file's text.
    pub fn from_json(text: &str) -> Result<Self, ProportionModelError> {
        let model: Self =
            serde_json::from_str(text).map_err(|e| ProportionModelError::Parse(e.to_string()))?;
        if model.format != PROPORTIONS_FORMAT {
            return Err(ProportionModelError::Format(model.format));
        }
        let moments_ok =
            |v: &[f64]| v.len() == NUM_BONES && v.iter().all(|x| x.is_finite() && *x >= 0.0);
        if !(moments_ok(&model.prior.mean) && moments_ok(&model.prior.mean_square)) {
            return Err(ProportionModelError::Prior);
        }
        model.pooled.check("pooled")?;
        model.female.check("female")?;
        model.male.check("male")?;
        Ok(model)
    }

    /// The file's text.
    pub fn to_json(&self) -> String {
        // Plain data: serializing cannot fail.
        serde_json::to_string_pretty(self).unwrap_or_default() + "\n"
    }

    /// The lengths of someone `stature_m` tall (the caller checks the range,
    /// [`crate::stature::MIN_STATURE_M`]..=[`crate::stature::MAX_STATURE_M`]),
    /// of `sex` when given, whose stream so far shows `stats`.
    pub fn predict(
        &self,
        stature_m: f32,
        sex: Option<Sex>,
        stats: &ProportionStats,
    ) -> BoneLengths {
        let x = inputs(f64::from(stature_m), &stats.features(&self.prior));
        match sex {
            None => self.pooled.predict(&x),
            Some(Sex::Female) => self.female.predict(&x),
            Some(Sex::Male) => self.male.predict(&x),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A standing figure whose legs are `leg` long (keypoint units).
    fn figure(leg: f32) -> Keypoints2d {
        let mut kp = [[0.0f32; 2]; blapose_core::NUM_JOINTS];
        let set = |kp: &mut Keypoints2d, j: usize, x: f32, y: f32| kp[j] = [x, y];
        set(&mut kp, 1, -0.1, 0.0);
        set(&mut kp, 2, -0.1, leg);
        set(&mut kp, 3, -0.1, 2.0 * leg);
        set(&mut kp, 4, 0.1, 0.0);
        set(&mut kp, 5, 0.1, leg);
        set(&mut kp, 6, 0.1, 2.0 * leg);
        set(&mut kp, 7, 0.0, -0.2);
        set(&mut kp, 8, 0.0, -0.4);
        set(&mut kp, 9, 0.0, -0.5);
        set(&mut kp, 10, 0.0, -0.6);
        set(&mut kp, 11, 0.15, -0.4);
        set(&mut kp, 12, 0.15, -0.2);
        set(&mut kp, 13, 0.15, 0.0);
        set(&mut kp, 14, -0.15, -0.4);
        set(&mut kp, 15, -0.15, -0.2);
        set(&mut kp, 16, -0.15, 0.0);
        kp
    }

    fn lines(weight_on_thigh_mean: f64) -> ReaderLines {
        let mut weights = vec![vec![0.0; INPUTS]; NUM_BONES];
        for w in &mut weights {
            w[0] = 0.2;
        }
        // The right thigh reads its own mean fraction.
        weights[1][1 + 1] = weight_on_thigh_mean;
        ReaderLines {
            intercept: vec![0.01; NUM_BONES],
            weights,
            people: 10,
        }
    }

    fn model() -> ProportionModel {
        let f = bone_fractions(&figure(0.4)).unwrap();
        ProportionModel {
            format: PROPORTIONS_FORMAT.into(),
            source: "test".into(),
            prior: FeaturePrior {
                mean: f.to_vec(),
                mean_square: f.map(|r| r * r).to_vec(),
            },
            pooled: lines(1.0),
            female: lines(2.0),
            male: lines(3.0),
        }
    }

    #[test]
    fn fractions_ignore_scale_and_refuse_an_empty_frame() {
        let a = bone_fractions(&figure(0.4)).unwrap();
        let b = bone_fractions(&figure(0.4).map(|p| p.map(|v| v * 7.0))).unwrap();
        for (x, y) in a.iter().zip(&b) {
            assert!((x - y).abs() < 1e-6);
        }
        assert!((a.iter().sum::<f64>() - 1.0).abs() < 1e-9);
        assert!(bone_fractions(&[[0.3, 0.3]; blapose_core::NUM_JOINTS]).is_none());
        let mut nan = figure(0.4);
        nan[3][0] = f32::NAN;
        assert!(bone_fractions(&nan).is_none());
        let mut stats = ProportionStats::default();
        assert!(!stats.push(&nan));
        assert_eq!(stats, ProportionStats::default(), "nothing counted");
    }

    #[test]
    fn a_new_stream_starts_at_the_prior_and_moves_towards_its_frames() {
        let m = model();
        let empty = ProportionStats::default();
        let f0 = empty.features(&m.prior);
        for b in 0..NUM_BONES {
            assert!((f0[b] - m.prior.mean[b]).abs() < 1e-12);
            assert!(f0[NUM_BONES + b].abs() < 1e-6, "the prior has no spread");
        }
        let mut long_legs = ProportionStats::default();
        for _ in 0..90 {
            assert!(long_legs.push(&figure(0.6)));
        }
        let f = long_legs.features(&m.prior);
        let target = bone_fractions(&figure(0.6)).unwrap()[1];
        // 90 frames against 10 pseudo-frames: 90 % of the way.
        let expected = 0.9 * target + 0.1 * m.prior.mean[1];
        assert!((f[1] - expected).abs() < 1e-9, "{} vs {expected}", f[1]);
        assert!(f[1] > f0[1]);
    }

    #[test]
    fn predictions_follow_the_stature_the_sex_and_the_video() {
        let m = model();
        let empty = ProportionStats::default();
        let short = m.predict(1.6, None, &empty);
        let tall = m.predict(1.9, None, &empty);
        assert!(tall[0] > short[0]);
        let mut legs = ProportionStats::default();
        for _ in 0..50 {
            legs.push(&figure(0.7));
        }
        let read = m.predict(1.75, None, &legs);
        let prior = m.predict(1.75, None, &empty);
        assert!(
            read[1] > prior[1],
            "a long-legged stream reads longer thighs"
        );
        assert_eq!(read[0], prior[0], "bones without a feature weight stay");
        let female = m.predict(1.75, Some(Sex::Female), &legs);
        let male = m.predict(1.75, Some(Sex::Male), &legs);
        assert!(male[1] > female[1] && female[1] > read[1]);
    }

    #[test]
    fn files_and_statistics_round_trip_and_bad_ones_are_refused() {
        let m = model();
        assert_eq!(ProportionModel::from_json(&m.to_json()).unwrap(), m);
        let mut other = m.clone();
        other.format = "x/1".into();
        assert!(matches!(
            ProportionModel::from_json(&other.to_json()),
            Err(ProportionModelError::Format(_))
        ));
        let mut short = m.clone();
        short.male.weights[3].pop();
        assert_eq!(
            ProportionModel::from_json(&short.to_json()),
            Err(ProportionModelError::Lines("male"))
        );
        let mut prior = m.clone();
        prior.prior.mean[0] = -1.0;
        assert_eq!(
            ProportionModel::from_json(&prior.to_json()),
            Err(ProportionModelError::Prior)
        );
        assert!(matches!(
            ProportionModel::from_json("{"),
            Err(ProportionModelError::Parse(_))
        ));

        let mut stats = ProportionStats::default();
        for leg in [0.3, 0.5, 0.45] {
            stats.push(&figure(leg));
        }
        let bytes = stats.to_bytes();
        assert_eq!(bytes.len(), STATS_BYTES);
        assert_eq!(ProportionStats::from_bytes(&bytes), Some(stats));
        assert_eq!(
            ProportionStats::from_bytes(&ProportionStats::default().to_bytes()),
            Some(ProportionStats::default())
        );
        assert!(ProportionStats::from_bytes(&bytes[1..]).is_none());
        let mut negative = bytes.clone();
        negative[8..16].copy_from_slice(&(-1.0f64).to_le_bytes());
        assert!(ProportionStats::from_bytes(&negative).is_none());
        let mut no_frames = bytes;
        no_frames[..8].copy_from_slice(&0u64.to_le_bytes());
        assert!(ProportionStats::from_bytes(&no_frames).is_none());
    }
}

//! A licence-clean synthetic body-shape population: ANSUR II people mapped
//! to Human3.6M-convention bone lengths.
//!
//! The paper samples bone lengths from SMPL bodies; SMPL is licence
//! restricted, ANSUR II (US Army 2012, 6,068 people) is public domain. ANSUR
//! measures *surface landmarks* (heights of bony points above the floor,
//! breadths, segment lengths), not joint centres, so each bone gets a raw
//! estimate from the landmarks that bracket it ([`BONE_MAPPING`]) and then one
//! scale factor per bone that makes the population mean equal to the training
//! subjects' mean ([`AnsurPopulation::calibrate`]). A per-bone *scale* (not an
//! offset) keeps every person's proportions and the correlations between
//! bones (tall people have long thighs *and* long forearms) exactly as
//! measured; only the units are matched to Human3.6M's joint definitions.
//!
//! Symmetry is by construction: ANSUR measures one side, and the left and
//! right bone of each pair get the same raw value and the same factor.
//!
//! Bones whose length is identical for every training subject (Human3.6M's
//! head bone, 0.115 m) are held at that value: the dataset's skeleton fixes
//! them, so a person-to-person variation would only be label noise.
//!
//! **Spread.** The survey varies some bones far more than Human3.6M's
//! skeletons do (thorax 24.6 mm std in ANSUR vs 3.0 mm over the training
//! subjects, forearm 19.1 vs 4.7, calf 28.2 vs 9.3): the dataset's joint
//! centres come from a fitted skeleton, not from surface landmarks. A prior
//! that wide teaches the model that those bones vary, and it then errs by
//! centimetres where the dataset barely moves.
//! [`AnsurPopulation::match_spread`] rescales each bone's deviations from
//! the mean so its std becomes `factor x` the training subjects' std: a
//! per-bone affine map, so the survey's correlations between bones are kept
//! exactly. A factor above 1 (e.g. 1.25, about the small-sample correction
//! of a std taken over 5 subjects) keeps the prior wider than the five
//! training skeletons. The CLI default (0) keeps the survey's spread, the
//! recipe of the shipped weights; short runs with 1.25 did not learn faster
//! (see models/README.md).
//!
//! **Only training subjects calibrate.** [`AnsurPopulation::calibrate`] takes
//! the [`TrainingLengthStats`] built from the training subjects' lengths and
//! nothing else; a test (`tests/ansur_calibration.rs`) checks that changing a
//! training subject's lengths changes the population and that test subjects
//! cannot reach it.

use blapose_core::skeleton::NUM_BONES;
use blapose_core::BoneLengths;

use crate::error::TrainError;
use crate::training_lengths::TrainingLengthStats;

/// How a bone's raw length is computed from ANSUR columns (millimetres).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Landmarks {
    /// `a - b` (a vertical distance between two landmark heights).
    Difference(&'static str, &'static str),
    /// `a - b - c`.
    Difference3(&'static str, &'static str, &'static str),
    /// `a * k` (a breadth halved, or a segment length taken as is).
    Scaled(&'static str, f64),
}

/// The documented per-bone mapping, indexed like
/// [`blapose_core::skeleton::BONE_NAMES`]. Left and right bones use the same
/// landmarks. Raw means (mixed male + female survey) against the training
/// subjects' means give the calibration factors printed by
/// `blapose ansur-report` (all within 0.6-1.6).
pub const BONE_MAPPING: [Landmarks; NUM_BONES] = [
    // r_hip: pelvis centre to hip joint ~ half the iliac-crest breadth.
    Landmarks::Scaled("bicristalbreadth", 0.5),
    // r_thigh: hip joint (greater trochanter level) to knee (femoral epicondyle).
    Landmarks::Difference("trochanterionheight", "lateralfemoralepicondyleheight"),
    // r_calf: knee to ankle (lateral malleolus).
    Landmarks::Difference("lateralfemoralepicondyleheight", "lateralmalleolusheight"),
    Landmarks::Scaled("bicristalbreadth", 0.5),
    Landmarks::Difference("trochanterionheight", "lateralfemoralepicondyleheight"),
    Landmarks::Difference("lateralfemoralepicondyleheight", "lateralmalleolusheight"),
    // spine: pelvis (hip-joint level) to mid-spine (tenth rib level).
    Landmarks::Difference("tenthribheight", "trochanterionheight"),
    // thorax: mid-spine to the top of the sternum.
    Landmarks::Difference("suprasternaleheight", "tenthribheight"),
    // neck: sternum top to nose level (ear canal: stature - tragion-to-top).
    Landmarks::Difference3("stature", "tragiontopofhead", "suprasternaleheight"),
    // head: nose level to the top of the head (fixed in Human3.6M).
    Landmarks::Scaled("tragiontopofhead", 1.0),
    // l_shoulder: thorax to shoulder joint ~ half the biacromial breadth.
    Landmarks::Scaled("biacromialbreadth", 0.5),
    // l_upper_arm: acromion to radiale (elbow).
    Landmarks::Scaled("acromionradialelength", 1.0),
    // l_forearm: radiale to stylion (wrist).
    Landmarks::Scaled("radialestylionlength", 1.0),
    Landmarks::Scaled("biacromialbreadth", 0.5),
    Landmarks::Scaled("acromionradialelength", 1.0),
    Landmarks::Scaled("radialestylionlength", 1.0),
];

/// Every ANSUR column the mapping reads.
pub fn required_columns() -> Vec<&'static str> {
    let mut cols: Vec<&'static str> = Vec::new();
    for m in BONE_MAPPING {
        let names: &[&'static str] = match &m {
            Landmarks::Difference(a, b) => &[a, b],
            Landmarks::Difference3(a, b, c) => &[a, b, c],
            Landmarks::Scaled(a, _) => &[a],
        };
        for n in names {
            if !cols.contains(n) {
                cols.push(n);
            }
        }
    }
    cols
}

/// Raw (uncalibrated) bone lengths in metres of one person, reading columns
/// through `get` (millimetres). Errors name the missing column or the bone
/// whose landmarks give a non-positive length.
pub fn raw_lengths(get: impl Fn(&str) -> Option<f64>) -> Result<BoneLengths, TrainError> {
    let col = |name: &str| {
        get(name)
            .ok_or_else(|| TrainError::Ansur(format!("missing or non-numeric column {name:?}")))
    };
    let mut out = [0.0f32; NUM_BONES];
    for (b, m) in BONE_MAPPING.iter().enumerate() {
        let mm = match *m {
            Landmarks::Difference(a, c) => col(a)? - col(c)?,
            Landmarks::Difference3(a, c, d) => col(a)? - col(c)? - col(d)?,
            Landmarks::Scaled(a, k) => col(a)? * k,
        };
        if !mm.is_finite() || mm <= 0.0 {
            return Err(TrainError::Ansur(format!(
                "bone {} has non-positive raw length {mm} mm",
                blapose_core::skeleton::BONE_NAMES[b]
            )));
        }
        out[b] = (mm / 1000.0) as f32;
    }
    Ok(out)
}

/// The calibrated population: one row of 16 lengths (metres) per person.
#[derive(Debug, Clone, PartialEq)]
pub struct AnsurPopulation {
    people: Vec<BoneLengths>,
    /// Per-bone factor applied to the raw lengths.
    pub scale: BoneLengths,
}

impl AnsurPopulation {
    /// Calibrate raw people ([`raw_lengths`]) to the training subjects:
    /// `scale[b] = train_mean[b] / raw_mean[b]`; bones fixed across the
    /// training subjects are set to their training value.
    pub fn calibrate(
        raw: &[BoneLengths],
        training: &TrainingLengthStats,
    ) -> Result<Self, TrainError> {
        if raw.is_empty() {
            return Err(TrainError::Ansur("no ANSUR people".into()));
        }
        let n = raw.len() as f64;
        let mut scale = [0.0f32; NUM_BONES];
        for b in 0..NUM_BONES {
            let raw_mean = raw.iter().map(|p| f64::from(p[b])).sum::<f64>() / n;
            scale[b] = (f64::from(training.mean[b]) / raw_mean) as f32;
        }
        let people = raw
            .iter()
            .map(|p| {
                std::array::from_fn(|b| {
                    if training.is_fixed(b) {
                        training.mean[b]
                    } else {
                        p[b] * scale[b]
                    }
                })
            })
            .collect();
        Ok(Self { people, scale })
    }

    /// Rescale every non-fixed bone's deviations from the population mean
    /// so that its std becomes `factor * training.std[b]` (see the module
    /// docs). The mean and the correlations between bones are unchanged;
    /// symmetric pairs stay equal (same raw value, same map). `factor` must
    /// be positive and finite.
    pub fn match_spread(
        &mut self,
        training: &TrainingLengthStats,
        factor: f32,
    ) -> Result<(), TrainError> {
        if !(factor.is_finite() && factor > 0.0) {
            return Err(TrainError::InvalidArgument(format!(
                "ANSUR spread factor must be positive, got {factor}"
            )));
        }
        let (mean, std) = self.moments();
        for b in 0..NUM_BONES {
            if training.is_fixed(b) || std[b] <= 0.0 {
                continue;
            }
            let k = factor * training.std[b] / std[b];
            for p in &mut self.people {
                p[b] = mean[b] + (p[b] - mean[b]) * k;
            }
        }
        Ok(())
    }

    /// The people `i` with `keep[i]`, same calibration (`keep` has one
    /// entry per person; at least one must be kept).
    pub fn retained(&self, keep: &[bool]) -> Result<Self, TrainError> {
        if keep.len() != self.people.len() {
            return Err(TrainError::InvalidArgument(format!(
                "{} keep flags for {} people",
                keep.len(),
                self.people.len()
            )));
        }
        let people: Vec<BoneLengths> = self
            .people
            .iter()
            .zip(keep)
            .filter(|(_, &k)| k)
            .map(|(p, _)| *p)
            .collect();
        if people.is_empty() {
            return Err(TrainError::Ansur("no ANSUR people left".into()));
        }
        Ok(Self {
            people,
            scale: self.scale,
        })
    }

    /// Number of people.
    pub fn len(&self) -> usize {
        self.people.len()
    }

    /// True when there is nobody.
    pub fn is_empty(&self) -> bool {
        self.people.is_empty()
    }

    /// Person `i`'s calibrated lengths.
    pub fn person(&self, i: usize) -> BoneLengths {
        self.people[i % self.people.len().max(1)]
    }

    /// All people.
    pub fn people(&self) -> &[BoneLengths] {
        &self.people
    }

    /// Per-bone mean and standard deviation of the calibrated population.
    pub fn moments(&self) -> (BoneLengths, BoneLengths) {
        let n = self.people.len().max(1) as f64;
        let mut mean = [0.0f32; NUM_BONES];
        let mut std = [0.0f32; NUM_BONES];
        for b in 0..NUM_BONES {
            let m = self.people.iter().map(|p| f64::from(p[b])).sum::<f64>() / n;
            let v = self
                .people
                .iter()
                .map(|p| (f64::from(p[b]) - m).powi(2))
                .sum::<f64>()
                / n;
            mean[b] = m as f32;
            std[b] = v.sqrt() as f32;
        }
        (mean, std)
    }
}

/// Raw lengths of every person of a loaded ANSUR table; people whose
/// landmarks give a non-positive bone are skipped (returned count).
pub fn raw_population(
    table: &blapose_data::ansur::AnsurTable,
) -> Result<(Vec<BoneLengths>, usize), TrainError> {
    for c in required_columns() {
        if table.column_index(c).is_none() {
            return Err(TrainError::Ansur(format!("the survey has no column {c:?}")));
        }
    }
    let mut out = Vec::with_capacity(table.records.len());
    let mut skipped = 0;
    for r in &table.records {
        match raw_lengths(|c| table.value(r, c).map(f64::from)) {
            Ok(l) => out.push(l),
            Err(_) => skipped += 1,
        }
    }
    Ok((out, skipped))
}

/// Load both ANSUR II CSVs under `root` and calibrate them to the training
/// subjects' statistics.
pub fn load_population(
    root: &std::path::Path,
    training: &TrainingLengthStats,
) -> Result<AnsurPopulation, TrainError> {
    let table = blapose_data::ansur::load_ansur(root)?;
    let (raw, _) = raw_population(&table)?;
    AnsurPopulation::calibrate(&raw, training)
}

#[cfg(test)]
mod tests {
    use super::*;
    use blapose_core::skeleton::SYMMETRIC_BONE_PAIRS;
    use std::collections::HashMap;

    fn person(scale: f64) -> HashMap<&'static str, f64> {
        let base = [
            ("bicristalbreadth", 275.0),
            ("trochanterionheight", 880.0),
            ("lateralfemoralepicondyleheight", 480.0),
            ("lateralmalleolusheight", 70.0),
            ("tenthribheight", 1100.0),
            ("suprasternaleheight", 1400.0),
            ("stature", 1710.0),
            ("tragiontopofhead", 130.0),
            ("biacromialbreadth", 400.0),
            ("acromionradialelength", 327.0),
            ("radialestylionlength", 259.0),
        ];
        base.into_iter().map(|(k, v)| (k, v * scale)).collect()
    }

    fn training(mean: f32) -> TrainingLengthStats {
        let a = [mean; NUM_BONES];
        let mut b = [mean * 1.1; NUM_BONES];
        b[9] = mean; // a fixed bone, as Human3.6M's head
        TrainingLengthStats::from_training(&[a, b]).unwrap()
    }

    #[test]
    fn mapping_reads_every_column_and_is_symmetric() {
        assert_eq!(required_columns().len(), 11);
        let p = person(1.0);
        let raw = raw_lengths(|c| p.get(c).copied()).unwrap();
        assert!((raw[1] - 0.400).abs() < 1e-6);
        assert!((raw[8] - (1.710 - 0.130 - 1.400)).abs() < 1e-6);
        for &(r, l) in &SYMMETRIC_BONE_PAIRS {
            assert_eq!(raw[r], raw[l]);
        }
        let missing = raw_lengths(|c| {
            if c == "stature" {
                None
            } else {
                p.get(c).copied()
            }
        });
        assert!(matches!(missing, Err(TrainError::Ansur(m)) if m.contains("stature")));
    }

    #[test]
    fn calibration_matches_training_mean_and_keeps_ratios() {
        let raw: Vec<BoneLengths> = [0.9, 1.0, 1.1]
            .iter()
            .map(|&s| raw_lengths(|c| person(s).get(c).copied()).unwrap())
            .collect();
        let t = training(0.2);
        let pop = AnsurPopulation::calibrate(&raw, &t).unwrap();
        let (mean, _) = pop.moments();
        for b in 0..NUM_BONES {
            assert!((mean[b] - t.mean[b]).abs() < 1e-5, "bone {b}");
        }
        // Proportions between people survive the per-bone scale.
        assert!((pop.person(2)[1] / pop.person(0)[1] - 1.1 / 0.9).abs() < 1e-4);
        // The fixed bone is held.
        assert!(pop.people().iter().all(|p| p[9] == 0.2));
        // Changing the training statistics changes the population.
        let other = AnsurPopulation::calibrate(&raw, &training(0.25)).unwrap();
        assert_ne!(other, pop);
    }

    #[test]
    fn matched_spread_keeps_mean_symmetry_and_correlation() {
        let raw: Vec<BoneLengths> = [0.85, 0.95, 1.0, 1.02, 1.1, 1.2]
            .iter()
            .map(|&s| raw_lengths(|c| person(s).get(c).copied()).unwrap())
            .collect();
        let t = training(0.2);
        let mut pop = AnsurPopulation::calibrate(&raw, &t).unwrap();
        let before = pop.clone();
        pop.match_spread(&t, 1.5).unwrap();
        let (mean, std) = pop.moments();
        for b in 0..NUM_BONES {
            assert!((mean[b] - t.mean[b]).abs() < 1e-5, "bone {b} mean");
            if t.is_fixed(b) {
                assert!(pop.people().iter().all(|p| p[b] == t.mean[b]));
            } else {
                assert!(
                    (std[b] - 1.5 * t.std[b]).abs() < 1e-5,
                    "bone {b}: {} vs {}",
                    std[b],
                    1.5 * t.std[b]
                );
            }
        }
        for p in pop.people() {
            for &(r, l) in &SYMMETRIC_BONE_PAIRS {
                assert_eq!(p[r], p[l]);
            }
        }
        // Order of people along every bone is kept (affine, positive slope).
        for b in [1, 7, 12] {
            for i in 1..pop.len() {
                let up_before = before.person(i)[b] > before.person(i - 1)[b];
                let up_after = pop.person(i)[b] > pop.person(i - 1)[b];
                assert_eq!(up_before, up_after, "bone {b} person {i}");
            }
        }
        assert!(pop.match_spread(&t, 0.0).is_err());
        assert!(pop.match_spread(&t, f32::NAN).is_err());
    }
}

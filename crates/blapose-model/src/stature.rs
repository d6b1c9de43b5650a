//! The stature model: a person's 16 bone lengths from their height (and
//! sex), as the server answers a session or request that gives them.
//!
//! Why this and not a network: on the many-bodies benchmark (held-out
//! ANSUR II people through wide cameras) one least-squares line per bone
//! on stature scores 9.90 mm (9.35 with sex) against 15.0 for the
//! population prior, and combining it with any shipped model's reading
//! adds nothing measurable (models/README.md). So given the height, the
//! best answer served today is the regression itself.
//!
//! The file (`models/stature_regression.json`) is written by `blapose
//! fit-stature` (`blapose_train::stature`, fitted on the ANSUR training
//! split only) and embedded in the server; this module reads and applies
//! it, so trainer and server share one definition.

use blapose_core::skeleton::NUM_BONES;
use blapose_core::BoneLengths;
use serde::{Deserialize, Serialize};

/// The file's `format`.
pub const STATURE_FORMAT: &str = "blapose-stature-regression/1";

/// Shortest stature accepted, metres.
pub const MIN_STATURE_M: f32 = 1.0;
/// Tallest stature accepted, metres.
pub const MAX_STATURE_M: f32 = 2.3;

pub use blapose_core::Sex;

/// One line per bone: `length = intercept + slope * stature` (metres).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StatureLines {
    /// Per bone, metres.
    pub intercept: Vec<f64>,
    /// Per bone, metres of bone per metre of stature.
    pub slope: Vec<f64>,
    /// People fitted on.
    pub people: usize,
}

/// The regression for everyone, and for each sex.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StatureModel {
    /// [`STATURE_FORMAT`].
    pub format: String,
    /// Where it comes from (data, split, command).
    pub source: String,
    /// Everyone (used when the sex is not given).
    pub pooled: StatureLines,
    /// Women.
    pub female: StatureLines,
    /// Men.
    pub male: StatureLines,
}

/// Why a stature model file was refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum StatureModelError {
    /// Not JSON of the expected shape.
    #[error("the stature model does not parse: {0}")]
    Parse(String),
    /// Another format.
    #[error("the stature model has format {0:?}; expected {STATURE_FORMAT:?}")]
    Format(String),
    /// A line without 16 finite values.
    #[error("the stature model's {0} line needs 16 finite intercepts and slopes")]
    Line(&'static str),
}

impl StatureLines {
    fn check(&self, name: &'static str) -> Result<(), StatureModelError> {
        let ok = |v: &[f64]| v.len() == NUM_BONES && v.iter().all(|x| x.is_finite());
        if ok(&self.intercept) && ok(&self.slope) {
            Ok(())
        } else {
            Err(StatureModelError::Line(name))
        }
    }

    /// The stature whose lengths on these lines sum to `truth`'s summed
    /// length: a stature that reads the truth, so the lines get the overall
    /// size exactly and only proportions are left to them (the stand-in for
    /// a measured stature where nobody measured one). `None` when the
    /// summed slope is not positive.
    pub fn matched_stature(&self, truth: &BoneLengths) -> Option<f32> {
        let intercept: f64 = self.intercept.iter().sum();
        let slope: f64 = self.slope.iter().sum();
        let total = blapose_core::bones::summed_length(truth);
        (slope > 0.0).then(|| ((total - intercept) / slope) as f32)
    }

    /// The lengths of someone `stature_m` tall.
    pub fn predict(&self, stature_m: f32) -> BoneLengths {
        std::array::from_fn(|b| (self.intercept[b] + self.slope[b] * f64::from(stature_m)) as f32)
    }
}

impl StatureModel {
    /// Read and check a model file's text.
    pub fn from_json(text: &str) -> Result<Self, StatureModelError> {
        let model: Self =
            serde_json::from_str(text).map_err(|e| StatureModelError::Parse(e.to_string()))?;
        if model.format != STATURE_FORMAT {
            return Err(StatureModelError::Format(model.format));
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
    /// [`MIN_STATURE_M`]..=[`MAX_STATURE_M`]), of `sex` when given.
    pub fn predict(&self, stature_m: f32, sex: Option<Sex>) -> BoneLengths {
        match sex {
            None => self.pooled.predict(stature_m),
            Some(Sex::Female) => self.female.predict(stature_m),
            Some(Sex::Male) => self.male.predict(stature_m),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn lines(a: f64, s: f64) -> StatureLines {
        StatureLines {
            intercept: vec![a; NUM_BONES],
            slope: vec![s; NUM_BONES],
            people: 10,
        }
    }

    #[test]
    fn a_model_round_trips_and_predicts_by_sex() {
        let model = StatureModel {
            format: STATURE_FORMAT.into(),
            source: "test".into(),
            pooled: lines(0.0, 0.2),
            female: lines(0.01, 0.2),
            male: lines(-0.01, 0.2),
        };
        let back = StatureModel::from_json(&model.to_json()).unwrap();
        assert_eq!(back, model);
        assert!((back.predict(1.5, None)[0] - 0.3).abs() < 1e-6);
        assert!((back.predict(1.5, Some(Sex::Female))[0] - 0.31).abs() < 1e-6);
        assert!((back.predict(1.5, Some(Sex::Male))[0] - 0.29).abs() < 1e-6);
    }

    #[test]
    fn bad_files_are_typed_errors() {
        assert!(matches!(
            StatureModel::from_json("{"),
            Err(StatureModelError::Parse(_))
        ));
        let mut model = StatureModel {
            format: "other".into(),
            source: String::new(),
            pooled: lines(0.0, 0.2),
            female: lines(0.0, 0.2),
            male: lines(0.0, 0.2),
        };
        assert!(matches!(
            StatureModel::from_json(&model.to_json()),
            Err(StatureModelError::Format(_))
        ));
        model.format = STATURE_FORMAT.into();
        model.male.slope.pop();
        assert_eq!(
            StatureModel::from_json(&model.to_json()),
            Err(StatureModelError::Line("male"))
        );
    }
}

//! How the many-bodies benchmark scores one set of answers: the mean
//! error over individuals, the size slope, the error at the prior's size,
//! all beside the prior; and the typed rows and baselines the report
//! holds.
//!
//! Why apart from the benchmark's run: every answer (a network, the
//! stature regression, an oracle, a constant) is scored by these same few
//! functions, so their rows compare.

use blapose_core::bones::summed_length;
use blapose_core::skeleton::NUM_BONES;
use blapose_core::BoneLengths;
use blapose_model::ModelKind;
use blapose_train::eval::trial_error_mm;
use blapose_train::stature::StatureInput;
use blapose_train::TrainError;
use serde::Serialize;

use super::BenchInput;

/// The scores of one set of predictions.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Score {
    /// Mean over individuals of the mean |pred - true| over 16 bones, mm.
    pub mean_bone_error_mm: f64,
    /// Per bone, mean over individuals, mm.
    pub per_bone_mm: Vec<f64>,
    /// Least-squares slope of predicted against true total length.
    pub size_slope: f64,
}

/// Least-squares slope of `y` against `x` (`None` with fewer than two
/// points or no spread in `x`).
pub fn slope(x: &[f64], y: &[f64]) -> Option<f64> {
    if x.len() != y.len() || x.len() < 2 {
        return None;
    }
    let n = x.len() as f64;
    let mx = x.iter().sum::<f64>() / n;
    let my = y.iter().sum::<f64>() / n;
    let sxx: f64 = x.iter().map(|v| (v - mx).powi(2)).sum();
    let sxy: f64 = x.iter().zip(y).map(|(a, b)| (a - mx) * (b - my)).sum();
    (sxx > 0.0 && sxx.is_finite()).then(|| sxy / sxx)
}

/// Per bone, the mean over individuals of `|pred - true|`, mm.
fn per_bone_mm(pred: &dyn Fn(usize) -> BoneLengths, truth: &[BoneLengths]) -> Vec<f64> {
    let n = truth.len() as f64;
    (0..NUM_BONES)
        .map(|b| {
            truth
                .iter()
                .enumerate()
                .map(|(i, t)| f64::from((pred(i)[b] - t[b]).abs()) * 1000.0)
                .sum::<f64>()
                / n
        })
        .collect()
}

/// Score predictions against the truth (same order, at least two
/// individuals of different total length).
pub fn score(pred: &[BoneLengths], truth: &[BoneLengths]) -> Result<Score, TrainError> {
    if pred.len() != truth.len() || pred.is_empty() {
        return Err(TrainError::InvalidArgument(format!(
            "{} predictions for {} individuals",
            pred.len(),
            truth.len()
        )));
    }
    let n = pred.len() as f64;
    let size_slope = slope(
        &truth.iter().map(summed_length).collect::<Vec<_>>(),
        &pred.iter().map(summed_length).collect::<Vec<_>>(),
    )
    .ok_or_else(|| {
        TrainError::InvalidArgument("size slope needs individuals of different sizes".into())
    })?;
    Ok(Score {
        mean_bone_error_mm: pred
            .iter()
            .zip(truth)
            .map(|(p, t)| trial_error_mm(p, t))
            .sum::<f64>()
            / n,
        per_bone_mm: per_bone_mm(&|i| pred[i], truth),
        size_slope,
    })
}

/// A closed set of values spelled one way in the JSON, the markdown and
/// the code: the enum with its serde renames, `name()` and `Display`, all
/// from one table.
macro_rules! spelled {
    (
        $(#[$meta:meta])*
        pub enum $name:ident {
            $($(#[$vmeta:meta])* $variant:ident => $spelling:literal,)+
        }
    ) => {
        $(#[$meta])*
        #[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
        pub enum $name {
            $($(#[$vmeta])* #[serde(rename = $spelling)] $variant,)+
        }

        impl $name {
            /// The JSON spelling.
            pub const fn name(self) -> &'static str {
                match self {
                    $(Self::$variant => $spelling,)+
                }
            }
        }

        impl std::fmt::Display for $name {
            fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
                f.write_str(self.name())
            }
        }
    };
}

spelled! {
    /// Who answers in a row (`model` in the JSON).
    pub enum RowModel {
        /// The online GRU (its running mean at the last frame).
        Gru => "gru",
        /// The offline Bi-GRU.
        BiGru => "bigru",
        /// The stature regression ([`blapose_train::stature`]).
        StatureRegression => "stature-regression",
        /// Size oracle: the prior's proportions at the true summed length.
        OraclePriorProportions => "oracle: prior proportions",
        /// Size oracle: the stature regression's proportions at the
        /// matched stature.
        OracleRegressionProportions => "oracle: stature-regression proportions",
    }
}

impl From<ModelKind> for RowModel {
    fn from(kind: ModelKind) -> Self {
        match kind {
            ModelKind::Gru => Self::Gru,
            ModelKind::BiGru => Self::BiGru,
        }
    }
}

spelled! {
    /// What a row's answer is given besides the picture (`input` in the
    /// JSON).
    pub enum RowInput {
        /// Normalized keypoints, no calibration (the default pair).
        None => "none",
        /// Keypoints with the camera's calibration (the camera-aware pair).
        Calibration => "calibration",
        /// The person's measured stature (with a network: the keypoints
        /// too).
        Height => "height",
        /// The calibration and the person's stature.
        CalibrationHeight => "calibration+height",
        /// The person's stature and sex.
        HeightSex => "height+sex",
        /// The person's true summed length (the size oracles: reads the
        /// truth).
        TrueSize => "true size",
    }
}

impl RowInput {
    /// A network's input given the person's stature too.
    pub const fn with_height(input: BenchInput) -> Self {
        match input {
            BenchInput::None => Self::Height,
            BenchInput::Calibration => Self::CalibrationHeight,
        }
    }
}

impl From<BenchInput> for RowInput {
    fn from(input: BenchInput) -> Self {
        match input {
            BenchInput::None => Self::None,
            BenchInput::Calibration => Self::Calibration,
        }
    }
}

impl From<StatureInput> for RowInput {
    fn from(input: StatureInput) -> Self {
        match input {
            StatureInput::Height => Self::Height,
            StatureInput::HeightSex => Self::HeightSex,
        }
    }
}

/// One row of the benchmark (the JSON schema the model card reads, plus where the
/// weights came from and how long the model took).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Row {
    /// Who answers.
    pub model: RowModel,
    /// What it is given.
    pub input: RowInput,
    /// The model's error, mm.
    pub mean_bone_error_mm: f64,
    /// The prior's error on the same individuals, mm.
    pub prior_mean_bone_error_mm: f64,
    /// `mean_bone_error_mm / prior_mean_bone_error_mm`.
    pub ratio_to_prior: f64,
    /// Predicted against true total length (1 reads sizes, 0 one body).
    pub size_slope: f64,
    /// The error of every estimate rescaled to the prior's summed length,
    /// mm: its proportions alone, to read beside the prior's error (the
    /// prior's own proportions score exactly that).
    pub at_prior_size_mm: f64,
    /// Per bone, mm ([`blapose_core::skeleton::BONE_NAMES`] order).
    pub per_bone_mm: Vec<f64>,
    /// Weights file, or what the answer was fitted on.
    pub weights: String,
    /// Seconds of the model pass.
    pub seconds: f64,
    /// The same answer's error on the training subjects' own real
    /// detections, mm ([`crate::real_check`]; absent where not measured).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub real_check_mm: Option<f64>,
}

spelled! {
    /// Which constant answer a baseline is (`name` in the JSON).
    pub enum BaselineName {
        /// The population-mean body of the population training draws from.
        Prior => "prior (training population mean)",
        /// The Human3.6M training subjects' mean lengths.
        TrainingMean => "training subjects' mean lengths",
    }
}

/// A constant answer scored like a model.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Baseline {
    /// What it is.
    pub name: BaselineName,
    /// Its lengths (metres).
    pub lengths_m: Vec<f32>,
    /// Its error, mm.
    pub mean_bone_error_mm: f64,
    /// Against the prior.
    pub ratio_to_prior: f64,
    /// Per bone, mm.
    pub per_bone_mm: Vec<f64>,
    /// Its error on the training subjects' own real detections, mm
    /// ([`crate::real_check`]; absent where not measured).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub real_check_mm: Option<f64>,
}

/// The mean body of a population (the prior).
pub fn mean_body(people: &[BoneLengths]) -> Option<BoneLengths> {
    if people.is_empty() {
        return None;
    }
    let n = people.len() as f64;
    Some(std::array::from_fn(|b| {
        (people.iter().map(|p| f64::from(p[b])).sum::<f64>() / n) as f32
    }))
}

/// A row: the answer's score beside the prior's on the same individuals
/// (its `weights` and `seconds` for the caller to fill).
pub fn row(
    model: RowModel,
    input: RowInput,
    pred: &[BoneLengths],
    truth: &[BoneLengths],
    prior: &BoneLengths,
) -> Result<Row, TrainError> {
    let s = score(pred, truth)?;
    let prior_mm = prior_error(truth, prior)?;
    let prior_total = summed_length(prior);
    let at_prior_size = pred
        .iter()
        .map(|p| scaled_to(p, prior_total))
        .collect::<Result<Vec<_>, _>>()?;
    Ok(Row {
        model,
        input,
        mean_bone_error_mm: s.mean_bone_error_mm,
        prior_mean_bone_error_mm: prior_mm,
        ratio_to_prior: s.mean_bone_error_mm / prior_mm,
        size_slope: s.size_slope,
        at_prior_size_mm: score(&at_prior_size, truth)?.mean_bone_error_mm,
        per_bone_mm: s.per_bone_mm,
        weights: String::new(),
        seconds: 0.0,
        real_check_mm: None,
    })
}

fn prior_error(truth: &[BoneLengths], prior: &BoneLengths) -> Result<f64, TrainError> {
    if truth.is_empty() {
        return Err(TrainError::InvalidArgument("no individuals".into()));
    }
    let e = truth.iter().map(|t| trial_error_mm(prior, t)).sum::<f64>() / truth.len() as f64;
    if e > 0.0 {
        Ok(e)
    } else {
        Err(TrainError::InvalidArgument(
            "every individual is the prior body: no ratio".into(),
        ))
    }
}

/// A constant baseline's entry.
pub fn baseline(
    name: BaselineName,
    lengths: &BoneLengths,
    truth: &[BoneLengths],
    prior: &BoneLengths,
) -> Result<Baseline, TrainError> {
    let prior_mm = prior_error(truth, prior)?;
    let e = truth
        .iter()
        .map(|t| trial_error_mm(lengths, t))
        .sum::<f64>()
        / truth.len() as f64;
    Ok(Baseline {
        name,
        lengths_m: lengths.to_vec(),
        mean_bone_error_mm: e,
        ratio_to_prior: e / prior_mm,
        per_bone_mm: per_bone_mm(&|_| *lengths, truth),
        real_check_mm: None,
    })
}

/// `l` with its proportions kept and its summed length set to `total`.
pub fn scaled_to(l: &BoneLengths, total: f64) -> Result<BoneLengths, TrainError> {
    let own = summed_length(l);
    if !(own > 0.0 && own.is_finite()) {
        return Err(TrainError::InvalidArgument(format!(
            "lengths summing to {own} m have no proportions"
        )));
    }
    let k = total / own;
    Ok(std::array::from_fn(|b| (f64::from(l[b]) * k) as f32))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn slope_and_ratio_on_a_hand_made_case() {
        // Three individuals, bones all equal: totals 16*0.2, 16*0.25, 16*0.3.
        let truth: Vec<BoneLengths> = [0.20f32, 0.25, 0.30].map(|v| [v; NUM_BONES]).to_vec();
        // A model that reads half the size difference around 0.25.
        let pred: Vec<BoneLengths> = [0.225f32, 0.25, 0.275].map(|v| [v; NUM_BONES]).to_vec();
        let prior = [0.25f32; NUM_BONES];
        let r = row(RowModel::BiGru, RowInput::None, &pred, &truth, &prior).unwrap();
        assert!((r.size_slope - 0.5).abs() < 1e-4, "{}", r.size_slope);
        // Errors: 25, 0, 25 mm -> 16.67; prior 50, 0, 50 -> 33.33; ratio 0.5.
        assert!((r.mean_bone_error_mm - 50.0 / 3.0).abs() < 1e-3);
        assert!((r.prior_mean_bone_error_mm - 100.0 / 3.0).abs() < 1e-3);
        assert!((r.ratio_to_prior - 0.5).abs() < 1e-4);
        assert_eq!(r.per_bone_mm.len(), NUM_BONES);
        assert!((r.per_bone_mm[3] - 50.0 / 3.0).abs() < 1e-3);
        // A constant has slope 0 and is the prior's ratio when it is the prior.
        let c = row(
            RowModel::Gru,
            RowInput::Calibration,
            &[prior; 3],
            &truth,
            &prior,
        )
        .unwrap();
        assert!(c.size_slope.abs() < 1e-12);
        assert!((c.ratio_to_prior - 1.0).abs() < 1e-12);
        let b = baseline(BaselineName::Prior, &prior, &truth, &prior).unwrap();
        assert!((b.ratio_to_prior - 1.0).abs() < 1e-12);
        assert_eq!(b.per_bone_mm, c.per_bone_mm);
        // The truth itself: slope 1, no error.
        let t = score(&truth, &truth).unwrap();
        assert!((t.size_slope - 1.0).abs() < 1e-9 && t.mean_bone_error_mm == 0.0);
    }

    #[test]
    fn degenerate_inputs_are_errors_not_panics() {
        let one = vec![[0.2f32; NUM_BONES]];
        assert!(score(&one, &one).is_err(), "one individual has no slope");
        assert!(score(&one, &[]).is_err());
        let same = vec![[0.2f32; NUM_BONES]; 3];
        assert!(row(
            RowModel::Gru,
            RowInput::None,
            &same,
            &same,
            &[0.2; NUM_BONES]
        )
        .is_err());
        assert_eq!(slope(&[1.0, 1.0], &[0.0, 2.0]), None);
        assert_eq!(mean_body(&[]), None);
    }

    fn json(value: impl Serialize) -> String {
        serde_json::to_value(value)
            .unwrap()
            .as_str()
            .unwrap()
            .to_string()
    }

    #[test]
    fn rows_keep_the_json_spellings() {
        for m in [
            RowModel::Gru,
            RowModel::BiGru,
            RowModel::StatureRegression,
            RowModel::OraclePriorProportions,
            RowModel::OracleRegressionProportions,
        ] {
            assert_eq!(json(m), m.name());
        }
        for i in [
            RowInput::None,
            RowInput::Calibration,
            RowInput::Height,
            RowInput::CalibrationHeight,
            RowInput::HeightSex,
            RowInput::TrueSize,
        ] {
            assert_eq!(json(i), i.name());
        }
        for b in [BaselineName::Prior, BaselineName::TrainingMean] {
            assert_eq!(json(b), b.name());
        }
        assert_eq!(RowModel::from(ModelKind::BiGru), RowModel::BiGru);
        assert_eq!(RowInput::from(StatureInput::HeightSex).name(), "height+sex");
        assert_eq!(
            RowInput::with_height(BenchInput::Calibration).name(),
            "calibration+height"
        );
    }
}

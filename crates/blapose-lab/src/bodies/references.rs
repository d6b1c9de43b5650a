//! The rows the many-bodies benchmark prints beside the networks, each a
//! bar a network has to clear: the stature regression given each
//! individual's measured stature (and sex), the two size oracles given
//! each individual's true summed length, and each network's estimate
//! fused with the stature ([`crate::height_fusion`]).
//!
//! Why apart from the run: these rows answer without reading the 2D (or,
//! fused, beside it); what they are given, and what they are fitted on,
//! is the point of each, and is written here once.

use std::time::Instant;

use blapose_core::bones::summed_length;
use blapose_core::BoneLengths;
use blapose_model::stature::StatureLines;
use blapose_train::ansur_split::Person;
use blapose_train::stature::{StatureInput, StatureRegression};
use blapose_train::TrainError;

use super::score::{row, scaled_to, Row, RowInput, RowModel};
use super::trials::{estimate, trial_people, Trial};
use super::BenchModel;
use crate::height_fusion::HeightFusion;
use crate::stature_proxy::matched_lengths;

/// The stature regression's rows: each individual's lengths predicted
/// from its measured stature (and sex), scored like a model. `people` and
/// `trials` are in the same order (the trials of `people[..trials.len()]`).
pub fn stature_rows(
    regression: &StatureRegression,
    people: &[&Person],
    trials: &[Trial],
    prior: &BoneLengths,
) -> Result<Vec<Row>, TrainError> {
    let people = trial_people(people, trials)?;
    let truth: Vec<BoneLengths> = trials.iter().map(|t| t.lengths).collect();
    let mut rows = Vec::with_capacity(StatureInput::ALL.len());
    for input in StatureInput::ALL {
        let t = Instant::now();
        let pred = people
            .iter()
            .map(|p| regression.predict(input, f64::from(p.stature_m), p.sex))
            .collect::<Result<Vec<_>, _>>()?;
        let mut r = row(
            RowModel::StatureRegression,
            input.into(),
            &pred,
            &truth,
            prior,
        )?;
        r.weights = format!(
            "least squares on {} ANSUR II training-split people",
            regression.fitted_on.len()
        );
        r.seconds = t.elapsed().as_secs_f64();
        rows.push(r);
    }
    Ok(rows)
}

/// The size oracles' rows: each individual's lengths given its true
/// summed length for free, with the prior's proportions
/// ([`RowModel::OraclePriorProportions`]) or the stature regression's at
/// the matched stature ([`RowModel::OracleRegressionProportions`],
/// [`matched_lengths`]). They read the truth: they bound what a model
/// that reads size perfectly and proportion not at all can score, so a
/// target below them needs proportions read from the 2D.
pub fn size_oracle_rows(
    lines: &StatureLines,
    truth: &[BoneLengths],
    prior: &BoneLengths,
) -> Result<Vec<Row>, TrainError> {
    let scaled_prior = truth
        .iter()
        .map(|t| scaled_to(prior, summed_length(t)))
        .collect::<Result<Vec<_>, _>>()?;
    let regression = truth
        .iter()
        .map(|t| {
            matched_lengths(lines, t).ok_or_else(|| {
                TrainError::InvalidArgument("stature lines with no positive summed slope".into())
            })
        })
        .collect::<Result<Vec<_>, _>>()?;
    [
        (RowModel::OraclePriorProportions, scaled_prior),
        (RowModel::OracleRegressionProportions, regression),
    ]
    .into_iter()
    .map(|(model, pred)| {
        let mut r = row(model, RowInput::TrueSize, &pred, truth, prior)?;
        r.weights = "reads the truth: each individual's summed length".into();
        Ok(r)
    })
    .collect()
}

/// What the height-fused rows are fitted on and applied to: the fit
/// trials with their people's statures, and the benchmark individuals'
/// statures.
pub struct FusionData {
    /// Trials built like the benchmark's from training data only.
    pub fit_trials: Vec<Trial>,
    /// Their people's statures, in trial order.
    pub fit_statures: Vec<f64>,
    /// The benchmark individuals' statures, in trial order.
    pub test_statures: Vec<f64>,
}

/// `model`'s row given the person's stature too: its estimate on the fit
/// trials fitted against the truth ([`HeightFusion`]), then applied to
/// its estimates `pred` of the benchmark individuals (`truth`).
pub fn fused_row(
    model: &BenchModel<'_>,
    data: &FusionData,
    pred: &[BoneLengths],
    truth: &[BoneLengths],
    prior: &BoneLengths,
) -> Result<Row, TrainError> {
    let t = Instant::now();
    let fit_pred = estimate(model, &data.fit_trials)?;
    let samples: Vec<_> = data
        .fit_statures
        .iter()
        .zip(&fit_pred)
        .zip(&data.fit_trials)
        .map(|((&h, &e), tr)| (h, e, tr.lengths))
        .collect();
    let fusion = HeightFusion::fit(&samples)?;
    let fused: Vec<BoneLengths> = data
        .test_statures
        .iter()
        .zip(pred)
        .map(|(&h, e)| fusion.predict(h, e))
        .collect();
    let mut r = row(
        model.kind.into(),
        RowInput::with_height(model.input),
        &fused,
        truth,
        prior,
    )?;
    r.weights = format!(
        "{} + per-bone least squares on stature and the estimate over {} training-split \
         people on training-subject motion (mean estimate weight {:.2})",
        model.path,
        fusion.people,
        fusion.mean_estimate_weight()
    );
    r.seconds = t.elapsed().as_secs_f64();
    Ok(r)
}

#[cfg(test)]
mod tests {
    use super::*;
    use blapose_core::skeleton::NUM_BONES;

    #[test]
    fn the_size_oracles_get_the_size_exactly_and_only_the_size() {
        let prior: BoneLengths = std::array::from_fn(|b| 0.1 + 0.02 * b as f32);
        // Two individuals with the prior's proportions, one without.
        let mut odd = prior;
        odd[0] += 0.05;
        odd[1] -= 0.05;
        let truth = vec![prior.map(|v| v * 0.9), prior.map(|v| v * 1.1), odd];
        let lines = StatureLines {
            intercept: vec![0.01; NUM_BONES],
            slope: (0..NUM_BONES).map(|b| 0.05 + 0.002 * b as f64).collect(),
            people: 3,
        };
        let rows = size_oracle_rows(&lines, &truth, &prior).unwrap();
        assert_eq!(rows.len(), 2);
        let scaled = &rows[0];
        assert_eq!(scaled.model, RowModel::OraclePriorProportions);
        assert_eq!(scaled.input, RowInput::TrueSize);
        // Exact on the first two; on the third only the two changed bones
        // (the sum is unchanged) miss, by 50 mm each.
        assert!((scaled.mean_bone_error_mm - 100.0 / 16.0 / 3.0).abs() < 1e-3);
        assert!((scaled.size_slope - 1.0).abs() < 1e-6);
        // At the prior's size, the prior's proportions are the prior.
        assert!((scaled.at_prior_size_mm - scaled.prior_mean_bone_error_mm).abs() < 1e-3);
        assert!(
            (rows[1].size_slope - 1.0).abs() < 1e-6,
            "matched stature reads the size"
        );
        assert!(rows[1].mean_bone_error_mm > 0.0);
    }
}

//! Statures where nobody measured one, for the served stature regression
//! ([`blapose_train::stature`], `models/stature_regression.json`):
//!
//! - the *stature proxy* of a motion-capture subject (Human3.6M publishes
//!   no statures), raw or calibrated on the training subjects, with which
//!   `blapose-lab diagnose --stature-proxy` scores the regression on
//!   S9/S11 by the evaluation protocol ([`stature_answers`]);
//! - the *matched stature*, a diagnostic that reads the truth: the stature
//!   whose regression lengths sum to the person's true summed length, so
//!   what is left of the regression's error is proportion (the
//!   many-bodies benchmark's regression oracle, the real-detection
//!   check, `--stature-source matched`).
//!
//! Why in the lab: the regression itself is product (`blapose
//! fit-stature`); these statures only measure it.

use std::collections::BTreeMap;

use blapose_core::{BoneLengths, Pose};
use blapose_data::h36m::TRAIN_SUBJECTS;
use blapose_model::stature::{StatureLines, StatureModel};
use blapose_train::dataset::EvalSequence;
use blapose_train::eval::run::EvalData;
use blapose_train::eval::{Estimate, LengthEstimator};
use blapose_train::TrainError;

/// Ankle to floor, metres: the ANSUR II mean lateral malleolus height
/// (69.6 mm over its 6,068 people), added by [`stature_proxy`].
pub const ANKLE_HEIGHT_M: f32 = 0.0696;

/// The stature whose lengths on `lines` (a regression's pooled lines) sum
/// to `truth`'s summed length: a diagnostic stature that reads the truth,
/// so the regression gets the overall size exactly and what is left of its
/// error is proportion. `None` when the lines' summed slope is not
/// positive.
pub fn matched_stature(lines: &StatureLines, truth: &BoneLengths) -> Option<f32> {
    lines.matched_stature(truth)
}

/// The lengths `lines` give at `truth`'s matched stature
/// ([`matched_stature`]): the truth's overall size with the lines'
/// proportions. `None` when the lines' summed slope is not positive.
pub fn matched_lengths(lines: &StatureLines, truth: &BoneLengths) -> Option<BoneLengths> {
    matched_stature(lines, truth).map(|stature| lines.predict(stature))
}

/// The mean over `subjects` (each one's stature proxy and true lengths:
/// training subjects only) of its matched stature ([`matched_stature`])
/// minus its proxy: what [`stature_proxy`] reads short by, on average,
/// through `lines`. Added to a test subject's proxy it gives the
/// calibrated proxy. `None` without subjects.
pub fn proxy_offset(lines: &StatureLines, subjects: &[(f32, BoneLengths)]) -> Option<f32> {
    let diffs: Vec<f32> = subjects
        .iter()
        .map(|(proxy, truth)| matched_stature(lines, truth).map(|m| m - proxy))
        .collect::<Option<_>>()?;
    (!diffs.is_empty()).then(|| diffs.iter().sum::<f32>() / diffs.len() as f32)
}

/// A stature proxy for a motion-capture subject, whose stature is not
/// published (Human3.6M): the 99th percentile over `poses` (world
/// coordinates, metres, z up) of the vertical span from the lower ankle to
/// the head joint, plus [`ANKLE_HEIGHT_M`]. Taking the head joint for the
/// crown and the 99th percentile for standing upright, it reads short by
/// however far the crown is above the head joint. `None` without poses.
pub fn stature_proxy(poses: &[Pose]) -> Option<f32> {
    const HEAD: usize = 10;
    const ANKLES: [usize; 2] = [3, 6];
    let mut spans: Vec<f32> = poses
        .iter()
        .map(|p| p[HEAD][2] - p[ANKLES[0]][2].min(p[ANKLES[1]][2]))
        .filter(|v| v.is_finite())
        .collect();
    if spans.is_empty() {
        return None;
    }
    spans.sort_by(f32::total_cmp);
    let k = ((spans.len() - 1) as f64 * 0.99).round() as usize;
    Some(spans[k] + ANKLE_HEIGHT_M)
}

/// Where `--stature-proxy` takes each subject's stature from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum StatureSource {
    /// The documented proxy ([`stature_proxy`]).
    Proxy,
    /// The proxy plus its mean shortfall on the training subjects
    /// ([`proxy_offset`]).
    CalibratedProxy,
    /// Matched to the subject's true summed length ([`matched_stature`]:
    /// reads the truth).
    Matched,
}

impl StatureSource {
    /// The report's model label.
    pub const fn label(self) -> &'static str {
        match self {
            Self::Proxy => "stature-regression+proxy",
            Self::CalibratedProxy => "stature-regression+calibrated-proxy",
            Self::Matched => "stature-regression+matched-stature",
        }
    }
}

/// One fixed answer per subject (the stature model given each subject's
/// stature), as an estimator the protocol scores.
pub struct PerSubject(pub BTreeMap<String, BoneLengths>);

impl LengthEstimator for PerSubject {
    fn estimate(&self, trials: &[EvalSequence]) -> Result<Vec<Estimate>, TrainError> {
        trials
            .iter()
            .map(|t| {
                let lengths = *self.0.get(&t.subject).ok_or_else(|| {
                    TrainError::Data(format!("no answer for subject {}", t.subject))
                })?;
                Ok(Estimate {
                    lengths,
                    curve: Vec::new(),
                })
            })
            .collect()
    }
}

/// One evaluated subject's stature and what the regression made of it.
#[derive(Debug, Clone, PartialEq)]
pub struct SubjectStature {
    /// Subject.
    pub subject: String,
    /// The stature given, metres.
    pub stature_m: f32,
    /// The regression's summed length at that stature, metres.
    pub predicted_total_m: f32,
    /// The subject's true summed length, metres.
    pub true_total_m: f32,
}

/// The stature regression's answers for the evaluated subjects.
pub struct StatureAnswers {
    /// With [`StatureSource::CalibratedProxy`]: what the proxy reads short
    /// by on the training subjects, metres (added to every proxy).
    pub offset_m: Option<f32>,
    /// Per evaluated subject, in the run's order.
    pub subjects: Vec<SubjectStature>,
    /// The answers, for the protocol.
    pub answers: PerSubject,
}

/// The stature `model`'s answer for each subject of the run `data`, from
/// the statures `source` says (each subject's proxy from all of its
/// recordings).
pub fn stature_answers(
    data: &EvalData,
    source: StatureSource,
    model: &StatureModel,
) -> Result<StatureAnswers, TrainError> {
    let proxy_of = |s: &str| -> Result<f32, TrainError> {
        let poses: Vec<Pose> = data
            .all
            .sequences()
            .filter(|(subject, _, _)| *subject == s)
            .flat_map(|(_, _, p)| p.iter().copied())
            .collect();
        stature_proxy(&poses)
            .ok_or_else(|| TrainError::Data(format!("no poses of {s} for its stature proxy")))
    };
    let truth_of = |s: &str| -> Result<BoneLengths, TrainError> {
        data.lengths
            .get(s)
            .copied()
            .ok_or_else(|| TrainError::Data(format!("no true lengths for {s}")))
    };
    let no_slope =
        || TrainError::Data("the stature regression's summed slope is not positive".into());
    let offset_m = match source {
        StatureSource::CalibratedProxy => {
            let training = TRAIN_SUBJECTS
                .iter()
                .map(|s| Ok((proxy_of(s)?, truth_of(s)?)))
                .collect::<Result<Vec<_>, TrainError>>()?;
            Some(proxy_offset(&model.pooled, &training).ok_or_else(|| {
                TrainError::Data("no training subject to calibrate the proxy on".into())
            })?)
        }
        StatureSource::Proxy | StatureSource::Matched => None,
    };
    let mut subjects = Vec::with_capacity(data.args.subjects.len());
    let mut answers = BTreeMap::new();
    for s in &data.args.subjects {
        let truth = truth_of(s)?;
        let stature_m = match source {
            StatureSource::Matched => {
                matched_stature(&model.pooled, &truth).ok_or_else(no_slope)?
            }
            StatureSource::Proxy | StatureSource::CalibratedProxy => {
                proxy_of(s)? + offset_m.unwrap_or(0.0)
            }
        };
        let predicted = model.predict(stature_m, None);
        subjects.push(SubjectStature {
            subject: s.clone(),
            stature_m,
            predicted_total_m: predicted.iter().sum(),
            true_total_m: truth.iter().sum(),
        });
        answers.insert(s.clone(), predicted);
    }
    Ok(StatureAnswers {
        offset_m,
        subjects,
        answers: PerSubject(answers),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use blapose_core::skeleton::NUM_BONES;
    use blapose_model::stature::STATURE_FORMAT;

    #[test]
    fn matched_statures_reproduce_the_true_total_and_offsets_average_them() {
        let model = StatureModel {
            format: STATURE_FORMAT.into(),
            source: "test".into(),
            pooled: StatureLines {
                intercept: vec![0.01; NUM_BONES],
                slope: vec![0.15; NUM_BONES],
                people: 3,
            },
            female: StatureLines {
                intercept: vec![0.0; NUM_BONES],
                slope: vec![0.1; NUM_BONES],
                people: 1,
            },
            male: StatureLines {
                intercept: vec![0.0; NUM_BONES],
                slope: vec![0.1; NUM_BONES],
                people: 1,
            },
        };
        let truth = model.predict(1.8, None);
        let m = matched_stature(&model.pooled, &truth).unwrap();
        assert!((m - 1.8).abs() < 1e-5, "{m}");
        let other = model.predict(1.6, None);
        let offset = proxy_offset(&model.pooled, &[(1.7, truth), (1.5, other)]).unwrap();
        assert!((offset - 0.1).abs() < 1e-5, "{offset}");
        assert_eq!(proxy_offset(&model.pooled, &[]), None);
        let mut flat = model.clone();
        flat.pooled.slope = vec![0.0; NUM_BONES];
        assert_eq!(matched_stature(&flat.pooled, &truth), None);
    }

    #[test]
    fn the_stature_proxy_is_the_upright_span_plus_the_ankle() {
        let pose = |span: f32| {
            let mut p = [[0.0f32; 3]; 17];
            p[3][2] = 0.1;
            p[6][2] = 0.05;
            p[10][2] = 0.05 + span;
            p
        };
        // 200 frames crouching at 1.2 m, one standing at 1.7 m among 100.
        let mut poses: Vec<_> = (0..99).map(|_| pose(1.2)).collect();
        poses.extend((0..101).map(|_| pose(1.7)));
        let proxy = stature_proxy(&poses).unwrap();
        assert!((proxy - (1.7 + ANKLE_HEIGHT_M)).abs() < 1e-5, "{proxy}");
        assert_eq!(stature_proxy(&[]), None);
    }
}

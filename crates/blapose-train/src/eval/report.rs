//! The evaluation report and its aggregation: per trial the mean absolute
//! error over the 16 bones, then per action, per subject, per bone and per
//! view, beside the baselines; the markdown table a run prints.
//!
//! Why apart from the protocol ([`super::evaluate`]): what a report holds
//! and how it is aggregated is read by every consumer of `--json` (the
//! model card, the shipped-weights test, the lab's diagnostics), while the
//! protocol only fills it.

use std::collections::BTreeMap;

use blapose_core::metrics::ActionAggregator;
use blapose_core::skeleton::{BONE_NAMES, NUM_BONES};
use blapose_core::BoneLengths;
use serde::Serialize;

use crate::dataset::EvalSequence;
use crate::error::TrainError;

/// Errors of one set of estimates, aggregated (mm).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Summary {
    /// Mean over actions of the per-action mean trial error (headline).
    pub mean_bone_error_mm: f64,
    /// Plain mean over trials.
    pub mean_over_trials_mm: f64,
    /// Per subject (mean over its trials).
    pub per_subject_mm: BTreeMap<String, f64>,
    /// Per bone, mean over trials, in [`BONE_NAMES`] order.
    pub per_bone_mm: Vec<f64>,
    /// Per action.
    pub per_action_mm: BTreeMap<String, f64>,
}

/// Mean absolute error over the 16 bones, mm.
pub fn trial_error_mm(pred: &BoneLengths, gt: &BoneLengths) -> f64 {
    pred.iter()
        .zip(gt)
        .map(|(p, g)| f64::from((p - g).abs()))
        .sum::<f64>()
        * 1000.0
        / NUM_BONES as f64
}

/// Aggregate predictions `pred[i]` for `trials[i]` (see the module docs).
pub fn summarize(trials: &[EvalSequence], pred: &[BoneLengths]) -> Result<Summary, TrainError> {
    if trials.len() != pred.len() || trials.is_empty() {
        return Err(TrainError::InvalidArgument(format!(
            "{} trials but {} predictions",
            trials.len(),
            pred.len()
        )));
    }
    let mut actions = ActionAggregator::new();
    let mut subj: BTreeMap<String, (f64, usize)> = BTreeMap::new();
    let mut per_bone = [0.0f64; NUM_BONES];
    let mut total = 0.0;
    for (t, p) in trials.iter().zip(pred) {
        let e = trial_error_mm(p, &t.gt);
        actions.add_mean(&t.sequence, e, 1);
        let s = subj.entry(t.subject.clone()).or_insert((0.0, 0));
        s.0 += e;
        s.1 += 1;
        for b in 0..NUM_BONES {
            per_bone[b] += f64::from((p[b] - t.gt[b]).abs()) * 1000.0;
        }
        total += e;
    }
    let n = trials.len() as f64;
    Ok(Summary {
        mean_bone_error_mm: actions.mean_over_actions().unwrap_or(f64::NAN),
        mean_over_trials_mm: total / n,
        per_subject_mm: subj
            .into_iter()
            .map(|(k, (s, c))| (k, s / c as f64))
            .collect(),
        per_bone_mm: per_bone.iter().map(|v| v / n).collect(),
        per_action_mm: actions.per_action().into_iter().collect(),
    })
}

/// One point of the online error curve.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct CurvePoint {
    /// Frames seen.
    pub frames: usize,
    /// Headline error after that many frames (mm).
    pub mean_bone_error_mm: f64,
    /// Plain mean over trials (mm).
    pub mean_over_trials_mm: f64,
}

/// The full evaluation report (`--json`).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct EvalReport {
    /// `gru` or `bigru`.
    pub model: String,
    /// `sh` or `gt`.
    pub input: String,
    /// Weights file.
    pub weights: String,
    /// Evaluated subjects.
    pub subjects: Vec<String>,
    /// How the headline is averaged.
    pub aggregation: String,
    /// Trials (sequence x camera).
    pub trials: usize,
    /// Frames read.
    pub frames: usize,
    /// Headline (mean over actions), mm.
    pub mean_bone_error_mm: f64,
    /// The model's full summary.
    pub summary: Summary,
    /// Per bone (mm), [`BONE_NAMES`] order (duplicated at top level for tools).
    pub per_bone_mm: Vec<f64>,
    /// Bone names of `per_bone_mm`.
    pub bone_names: Vec<String>,
    /// Per action (mm).
    pub per_action_mm: BTreeMap<String, f64>,
    /// Per bone: mean signed error `pred - true` over trials (mm). A bias
    /// close to the absolute error means the model is off in one
    /// direction for everyone, not noisy.
    pub per_bone_bias_mm: Vec<f64>,
    /// Per subject: the mean of its trials' estimates beside its true
    /// lengths. A model that reads people from their keypoints predicts
    /// different people differently; one that has only learned a prior
    /// predicts everyone alike ([`SubjectSpread`]).
    pub per_subject_mean_prediction: BTreeMap<String, SubjectMean>,
    /// How far apart the subjects' mean estimates are, against how far
    /// apart they really are.
    pub subject_spread: SubjectSpread,
    /// Per view (`"subject camera"`): the mean estimate of its trials.
    pub per_view_mean_prediction: BTreeMap<String, SubjectMean>,
    /// Every trial's estimate beside the truth (for calibration and
    /// error analysis).
    pub trial_predictions: Vec<TrialPrediction>,
    /// Naive baselines, same aggregation.
    pub baselines: BTreeMap<String, Summary>,
    /// Online only: error against frames seen.
    pub curve: Vec<CurvePoint>,
    /// Wall-clock seconds of the model pass.
    pub seconds: f64,
}

/// One trial's estimate in the JSON report.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct TrialPrediction {
    /// Subject.
    pub subject: String,
    /// Sequence.
    pub sequence: String,
    /// Camera id.
    pub camera: String,
    /// Frames read.
    pub frames: usize,
    /// Predicted lengths (metres).
    pub predicted_m: Vec<f32>,
    /// True lengths (metres).
    pub true_m: Vec<f32>,
}

/// One subject's mean estimate.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SubjectMean {
    /// Trials averaged.
    pub trials: usize,
    /// Mean of the trials' predicted lengths (metres).
    pub predicted_m: Vec<f32>,
    /// The subject's true lengths (metres).
    pub true_m: Vec<f32>,
}

/// Between-subject spread per bone (standard deviation over subjects of
/// their mean estimate, and of their true lengths), averaged over bones,
/// mm. `predicted_mm` near 0 against a clearly positive `true_mm` means
/// the model tells the subjects apart no better than a constant.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize)]
pub struct SubjectSpread {
    /// Spread of the subjects' mean estimates.
    pub predicted_mm: f64,
    /// Spread of their true lengths.
    pub true_mm: f64,
}

/// Trials grouped by `key`: the mean estimate of each group and its true
/// lengths (the first trial's; every trial of one subject has the same).
fn grouped_mean(
    trials: &[EvalSequence],
    pred: &[BoneLengths],
    key: impl Fn(&EvalSequence) -> String,
) -> BTreeMap<String, SubjectMean> {
    let mut sums: BTreeMap<String, (usize, [f64; NUM_BONES], BoneLengths)> = BTreeMap::new();
    for (t, p) in trials.iter().zip(pred) {
        let e = sums.entry(key(t)).or_insert((0, [0.0; NUM_BONES], t.gt));
        e.0 += 1;
        for b in 0..NUM_BONES {
            e.1[b] += f64::from(p[b]);
        }
    }
    sums.into_iter()
        .map(|(s, (n, sum, gt))| {
            let mean = sum.iter().map(|v| (v / n as f64) as f32).collect();
            (
                s,
                SubjectMean {
                    trials: n,
                    predicted_m: mean,
                    true_m: gt.to_vec(),
                },
            )
        })
        .collect()
}

/// Per subject: the mean estimate over its trials and its true lengths.
pub(super) fn per_subject_mean(
    trials: &[EvalSequence],
    pred: &[BoneLengths],
) -> BTreeMap<String, SubjectMean> {
    grouped_mean(trials, pred, |t| t.subject.clone())
}

/// Per view (subject and camera, key `"S9 54138969"`): the same means.
/// Human3.6M's cameras were calibrated again for every subject, and a
/// model that reads size from where the feet meet the floor carries the
/// camera's placement into its estimate; this shows it per camera.
pub(super) fn per_view_mean(
    trials: &[EvalSequence],
    pred: &[BoneLengths],
) -> BTreeMap<String, SubjectMean> {
    grouped_mean(trials, pred, |t| format!("{} {}", t.subject, t.camera))
}

impl SubjectMean {
    /// Predicted over true total length (all 16 bones): 1 is right on
    /// average, 0.98 a body 2 % too small.
    pub fn size_ratio(&self) -> f64 {
        let total = |v: &[f32]| v.iter().map(|&x| f64::from(x)).sum::<f64>();
        total(&self.predicted_m) / total(&self.true_m)
    }
}

/// The [`SubjectSpread`] of per-subject means (zero for fewer than two
/// subjects).
pub fn subject_spread(means: &BTreeMap<String, SubjectMean>) -> SubjectSpread {
    let n = means.len();
    if n < 2 {
        return SubjectSpread::default();
    }
    let spread = |get: &dyn Fn(&SubjectMean) -> &[f32]| {
        (0..NUM_BONES)
            .map(|b| {
                let v: Vec<f64> = means.values().map(|m| f64::from(get(m)[b])).collect();
                let mean = v.iter().sum::<f64>() / n as f64;
                (v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n as f64).sqrt()
            })
            .sum::<f64>()
            * 1000.0
            / NUM_BONES as f64
    };
    SubjectSpread {
        predicted_mm: spread(&|m| &m.predicted_m),
        true_mm: spread(&|m| &m.true_m),
    }
}

/// Mean of `pred - true` per bone over trials, mm.
pub(super) fn per_bone_bias_mm(trials: &[EvalSequence], pred: &[BoneLengths]) -> Vec<f64> {
    let n = trials.len().max(1) as f64;
    (0..NUM_BONES)
        .map(|b| {
            trials
                .iter()
                .zip(pred)
                .map(|(t, p)| f64::from(p[b] - t.gt[b]))
                .sum::<f64>()
                * 1000.0
                / n
        })
        .collect()
}

/// The report as a markdown table (model beside the baselines).
pub fn markdown(r: &EvalReport) -> String {
    let mut s = String::new();
    let names: Vec<&String> = r.baselines.keys().collect();
    s.push_str(&format!(
        "## Bone-length error (mm), {} on {} input, subjects {} ({} trials, {} frames)\n\n",
        r.model,
        r.input,
        r.subjects.join(" "),
        r.trials,
        r.frames
    ));
    s.push_str("| | model |");
    for n in &names {
        s.push_str(&format!(" baseline: {n} |"));
    }
    s.push_str("\n|---|---|");
    for _ in &names {
        s.push_str("---|");
    }
    s.push('\n');
    let row = |s: &mut String, label: &str, f: &dyn Fn(&Summary) -> Option<f64>| {
        s.push_str(&format!(
            "| {label} | {} |",
            f(&r.summary).map_or("-".into(), |v| format!("{v:.2}"))
        ));
        for n in &names {
            s.push_str(&format!(
                " {} |",
                f(&r.baselines[*n]).map_or("-".into(), |v| format!("{v:.2}"))
            ));
        }
        s.push('\n');
    };
    row(&mut s, "**mean over actions (headline)**", &|x| {
        Some(x.mean_bone_error_mm)
    });
    row(&mut s, "mean over trials", &|x| Some(x.mean_over_trials_mm));
    for subj in r.summary.per_subject_mm.keys() {
        row(&mut s, subj, &|x| x.per_subject_mm.get(subj).copied());
    }
    for (b, name) in BONE_NAMES.iter().enumerate() {
        row(&mut s, name, &|x| x.per_bone_mm.get(b).copied());
    }
    for a in r.summary.per_action_mm.keys() {
        row(&mut s, a, &|x| x.per_action_mm.get(a).copied());
    }
    s.push_str("\nModel bias per bone (mean of pred - true, mm):");
    for (name, b) in BONE_NAMES.iter().zip(&r.per_bone_bias_mm) {
        s.push_str(&format!(" {name} {b:+.1};"));
    }
    s.push('\n');
    s.push_str("\nMean estimate per subject (mm; predicted / true):\n\n| subject |");
    for name in BONE_NAMES {
        s.push_str(&format!(" {name} |"));
    }
    s.push_str("\n|---|");
    s.push_str(&"---|".repeat(NUM_BONES));
    for (subj, m) in &r.per_subject_mean_prediction {
        s.push_str(&format!("\n| {subj} ({} trials) |", m.trials));
        for (p, t) in m.predicted_m.iter().zip(&m.true_m) {
            s.push_str(&format!(" {:.0} / {:.0} |", p * 1000.0, t * 1000.0));
        }
    }
    s.push_str(&format!(
        "\n\nSpread between subjects (std over subjects, mean over bones): predicted {:.2} mm, true {:.2} mm\n",
        r.subject_spread.predicted_mm, r.subject_spread.true_mm
    ));
    s.push_str("\nSize ratio per view (predicted / true total length over the 16 bones):\n\n| view | trials | size ratio |\n|---|---|---|");
    for (view, m) in &r.per_view_mean_prediction {
        s.push_str(&format!(
            "\n| {view} | {} | {:.4} |",
            m.trials,
            m.size_ratio()
        ));
    }
    s.push('\n');
    if !r.curve.is_empty() {
        s.push_str("\n| frames seen |");
        for c in &r.curve {
            s.push_str(&format!(" {} |", c.frames));
        }
        s.push_str("\n|---|");
        for _ in &r.curve {
            s.push_str("---|");
        }
        s.push_str("\n| error (mm) |");
        for c in &r.curve {
            s.push_str(&format!(" {:.2} |", c.mean_bone_error_mm));
        }
        s.push('\n');
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synth::FRAME_DIM;

    #[test]
    fn a_constant_has_no_spread_between_subjects() {
        let trial = |subject: &str, gt: f32| EvalSequence {
            subject: subject.into(),
            sequence: "Walking".into(),
            camera: "54138969".into(),
            input: vec![0.0; FRAME_DIM],
            gt: [gt; NUM_BONES],
        };
        let trials = [trial("S9", 0.30), trial("S9", 0.30), trial("S11", 0.26)];
        let constant = vec![[0.28; NUM_BONES]; 3];
        let means = per_subject_mean(&trials, &constant);
        assert_eq!(means["S9"].trials, 2);
        let s = subject_spread(&means);
        assert!(s.predicted_mm.abs() < 1e-6);
        assert!((s.true_mm - 20.0).abs() < 1e-3, "{s:?}");
        // Two trials of S9 at 0.30 and 0.32 average to 0.31.
        let pred = vec![[0.30; NUM_BONES], [0.32; NUM_BONES], [0.26; NUM_BONES]];
        let means = per_subject_mean(&trials, &pred);
        assert!((means["S9"].predicted_m[0] - 0.31).abs() < 1e-6);
        assert!((subject_spread(&means).predicted_mm - 25.0).abs() < 1e-3);
        assert!((means["S11"].size_ratio() - 1.0).abs() < 1e-6);
        assert!((means["S9"].size_ratio() - 0.31 / 0.30).abs() < 1e-6);
    }

    #[test]
    fn views_group_by_subject_and_camera() {
        let trial = |camera: &str| EvalSequence {
            subject: "S9".into(),
            sequence: "Walking".into(),
            camera: camera.into(),
            input: vec![0.0; FRAME_DIM],
            gt: [0.30; NUM_BONES],
        };
        let trials = [trial("54138969"), trial("54138969"), trial("55011271")];
        let pred = vec![[0.27; NUM_BONES], [0.29; NUM_BONES], [0.33; NUM_BONES]];
        let views = per_view_mean(&trials, &pred);
        assert_eq!(views.len(), 2);
        assert_eq!(views["S9 54138969"].trials, 2);
        assert!((views["S9 54138969"].size_ratio() - 0.28 / 0.30).abs() < 1e-6);
        assert!((views["S9 55011271"].size_ratio() - 1.1).abs() < 1e-6);
    }
}

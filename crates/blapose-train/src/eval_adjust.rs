//! How much the bone-length adjustment helps a lifter: the paper's Table 2
//! (MPJPE, P-MPJPE, MPJVE and bone-length error, before and after
//! adjustment) and Table 3 (MPJPE per action), the measure of what the
//! served adjustment is for.
//!
//! For every trial (sequence x camera of the test subjects) the lifter's
//! root-relative camera-space poses are scored against the ground truth as
//! they are (`before`), and after [`adjust_sequence_with`] /
//! [`adjust_sequence_per_frame`] rebuilt them from their own bone
//! directions and
//!
//! * `gru`: the online GRU's *running* estimate — frame `t` uses the mean of
//!   the per-frame predictions over frames `0..=t`, so the adjustment is
//!   causal, exactly what a streaming session serves;
//! * `bigru`: the offline Bi-GRU's one estimate from the whole sequence;
//!
//! and, so that those gains are read against something, two baselines that
//! need no model:
//!
//! * `training_mean`: the training subjects' mean lengths, the same for
//!   everyone (the constant every bone-length estimate must beat);
//! * `lifter_median`: the lifter's own lengths, made consistent: frame `t`
//!   uses the per-bone median of the lifter's lengths over frames `0..=t`
//!   (causal, like the GRU), which removes the wobble but keeps the
//!   lifter's idea of the person's size.
//!
//! The root is kept (it is the origin here). A frame with a zero-length
//! bone keeps that bone's input offset ([`ZeroBonePolicy::KeepInput`])
//! rather than aborting a whole evaluation.
//!
//! **Aggregation** as in the bone-length evaluation ([`ActionAggregator`]):
//! each metric is frame-weighted within an action (take number dropped; all
//! subjects and cameras), then averaged over actions. MPJVE has `T - 1`
//! velocity frames per trial (a one-frame trial contributes none); it is in
//! mm per 50 Hz frame. The bone-length error of a pose is the mean over the
//! 16 bones of `|length - true length|`, true lengths from the ground-truth
//! pose of the same frame.

use std::collections::BTreeMap;

use std::cmp::{Ordering, Reverse};
use std::collections::BinaryHeap;

use blapose_core::bones::{
    adjust_sequence_per_frame, adjust_sequence_with, bone_lengths, ZeroBonePolicy,
};
use blapose_core::metrics::{
    mpjpe, mpjve, p_mpjpe, pose_bone_length_error, ActionAggregator, MetricError, MM_PER_M,
};
use blapose_core::skeleton::NUM_BONES;
use blapose_core::{BoneLengths, Pose};
use rayon::prelude::*;
use serde::Serialize;

use crate::error::TrainError;
use crate::lifter::data::LifterSequence;

/// The four pose metrics (mm; MPJVE in mm per frame, always computed
/// here): blapose-core's one definition, shared with the client.
pub use blapose_core::metrics::PoseMetrics;

/// One method's aggregated metrics.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct MethodReport {
    /// Mean over actions (the tables' "Avg").
    #[serde(flatten)]
    pub avg: PoseMetrics,
    /// Per action.
    pub per_action: BTreeMap<String, PoseMetrics>,
}

/// One lifter before and after adjustment (the `--json` value per lifter).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct LifterReport {
    /// The lifter as it is.
    pub before: MethodReport,
    /// Adjusted with the online GRU's running estimate.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub gru: Option<MethodReport>,
    /// Adjusted with the offline Bi-GRU's whole-sequence estimate.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub bigru: Option<MethodReport>,
    /// Baseline: adjusted with the training subjects' constant mean lengths.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub training_mean: Option<MethodReport>,
    /// Baseline: adjusted with the running median of the lifter's own
    /// lengths.
    pub lifter_median: MethodReport,
    /// Trials scored.
    pub trials: usize,
    /// Frames scored.
    pub frames: usize,
    /// The lifter's weights file, as given to eval-adjust.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub weights: Option<String>,
    /// How the averages are formed.
    pub aggregation: String,
}

/// Per-trial means and their frame counts.
#[derive(Debug, Clone, Copy)]
struct TrialMetrics {
    m: PoseMetrics,
    frames: usize,
}

fn metric(e: MetricError) -> TrainError {
    TrainError::Data(e.to_string())
}

fn trial_metrics(pred: &[Pose], gt: &[Pose]) -> Result<TrialMetrics, TrainError> {
    Ok(TrialMetrics {
        m: PoseMetrics {
            mpjpe_mm: mpjpe(pred, gt).map_err(metric)? * MM_PER_M,
            p_mpjpe_mm: p_mpjpe(pred, gt).map_err(metric)? * MM_PER_M,
            mpjve_mm: Some(if pred.len() >= 2 {
                mpjve(pred, gt).map_err(metric)? * MM_PER_M
            } else {
                0.0
            }),
            bone_error_mm: pose_bone_length_error(pred, gt).map_err(metric)?.mean * MM_PER_M,
        },
        frames: pred.len(),
    })
}

/// Four [`ActionAggregator`]s, one per metric.
#[derive(Default)]
struct Accumulator {
    mpjpe: ActionAggregator,
    p_mpjpe: ActionAggregator,
    mpjve: ActionAggregator,
    bone: ActionAggregator,
}

impl Accumulator {
    fn add(&mut self, sequence: &str, t: TrialMetrics) {
        self.mpjpe.add_mean(sequence, t.m.mpjpe_mm, t.frames);
        self.p_mpjpe.add_mean(sequence, t.m.p_mpjpe_mm, t.frames);
        self.mpjve.add_mean(
            sequence,
            t.m.mpjve_mm.unwrap_or(f64::NAN),
            t.frames.saturating_sub(1),
        );
        self.bone.add_mean(sequence, t.m.bone_error_mm, t.frames);
    }

    fn report(&self) -> MethodReport {
        let avg = |a: &ActionAggregator| a.mean_over_actions().unwrap_or(f64::NAN);
        let per = |a: &ActionAggregator| -> BTreeMap<String, f64> {
            a.per_action().into_iter().collect()
        };
        let (m, p, v, b) = (
            per(&self.mpjpe),
            per(&self.p_mpjpe),
            per(&self.mpjve),
            per(&self.bone),
        );
        MethodReport {
            avg: PoseMetrics {
                mpjpe_mm: avg(&self.mpjpe),
                p_mpjpe_mm: avg(&self.p_mpjpe),
                mpjve_mm: Some(avg(&self.mpjve)),
                bone_error_mm: avg(&self.bone),
            },
            per_action: m
                .iter()
                .map(|(a, &mv)| {
                    let get = |x: &BTreeMap<String, f64>| x.get(a).copied().unwrap_or(f64::NAN);
                    (
                        a.clone(),
                        PoseMetrics {
                            mpjpe_mm: mv,
                            p_mpjpe_mm: get(&p),
                            mpjve_mm: Some(get(&v)),
                            bone_error_mm: get(&b),
                        },
                    )
                })
                .collect(),
        }
    }
}

/// Length estimates to adjust with, per trial (same order as the trials).
#[derive(Debug, Clone, Copy, Default)]
pub struct Adjusters<'a> {
    /// Online GRU: one running estimate per frame of each trial.
    pub gru: Option<&'a [Vec<BoneLengths>]>,
    /// Offline Bi-GRU: one estimate per trial.
    pub bigru: Option<&'a [BoneLengths]>,
    /// The training subjects' mean lengths, for every trial.
    pub training_mean: Option<&'a BoneLengths>,
}

/// Total order on lengths for the median heaps (lengths are finite).
#[derive(Debug, Clone, Copy, PartialEq)]
struct Length(f32);

impl Eq for Length {}

impl PartialOrd for Length {
    fn partial_cmp(&self, other: &Self) -> Option<Ordering> {
        Some(self.cmp(other))
    }
}

impl Ord for Length {
    fn cmp(&self, other: &Self) -> Ordering {
        self.0.total_cmp(&other.0)
    }
}

/// Median of the values pushed so far, in O(log n) per value: the lower
/// half in a max-heap, the upper half in a min-heap, the lower one at most
/// one larger. An even count gives the mean of the two middle values.
#[derive(Debug, Default)]
struct RunningMedian {
    lower: BinaryHeap<Length>,
    upper: BinaryHeap<Reverse<Length>>,
}

impl RunningMedian {
    fn push(&mut self, v: f32) -> f32 {
        match self.lower.peek() {
            Some(top) if v > top.0 => self.upper.push(Reverse(Length(v))),
            _ => self.lower.push(Length(v)),
        }
        if self.lower.len() > self.upper.len() + 1 {
            let moved = self.lower.pop().map(Reverse);
            self.upper.extend(moved);
        } else if self.upper.len() > self.lower.len() {
            let moved = self.upper.pop().map(|Reverse(l)| l);
            self.lower.extend(moved);
        }
        let low = self.lower.peek().map_or(v, |l| l.0);
        if self.lower.len() == self.upper.len() {
            let high = self.upper.peek().map_or(low, |Reverse(l)| l.0);
            (low + high) / 2.0
        } else {
            low
        }
    }
}

/// The running per-bone median of `poses`' own bone lengths: entry `t` is
/// the median over frames `0..=t` (the `lifter_median` baseline).
pub fn running_median_lengths(poses: &[Pose]) -> Vec<BoneLengths> {
    let mut medians: [RunningMedian; NUM_BONES] = std::array::from_fn(|_| RunningMedian::default());
    poses
        .iter()
        .map(|p| {
            let l = bone_lengths(p);
            std::array::from_fn(|b| medians[b].push(l[b]))
        })
        .collect()
}

/// The bone-length estimates an evaluation adjusts with, computed once for
/// all lifters.
#[derive(Debug, Clone, Default)]
pub struct LengthEstimates {
    /// Online GRU running estimates (one per frame of each trial).
    pub gru: Option<Vec<Vec<BoneLengths>>>,
    /// Offline Bi-GRU estimates (one per trial).
    pub bigru: Option<Vec<BoneLengths>>,
    /// The training subjects' mean lengths (the constant baseline).
    pub training_mean: Option<BoneLengths>,
}

impl LengthEstimates {
    /// Run the given models on `trials`' 2D inputs.
    pub fn compute(
        trials: &[LifterSequence],
        gru: Option<&blapose_model::weights::LoadedWeights>,
        bigru: Option<&blapose_model::weights::LoadedWeights>,
    ) -> Result<Self, TrainError> {
        use crate::eval::{BiGruEstimator, GruEstimator, LengthEstimator};
        let inputs: Vec<_> = trials.iter().map(|t| t.trial.clone()).collect();
        let gru = match gru {
            Some(w) => Some(GruEstimator::new(w)?.running_estimates(&inputs)?),
            None => None,
        };
        let bigru = match bigru {
            Some(w) => Some(
                BiGruEstimator::new(w)?
                    .estimate(&inputs)?
                    .into_iter()
                    .map(|e| e.lengths)
                    .collect(),
            ),
            None => None,
        };
        Ok(Self {
            gru,
            bigru,
            training_mean: None,
        })
    }

    /// The adjusters over these estimates.
    pub fn adjusters(&self) -> Adjusters<'_> {
        Adjusters {
            gru: self.gru.as_deref(),
            bigru: self.bigru.as_deref(),
            training_mean: self.training_mean.as_ref(),
        }
    }
}

/// Score one lifter on `trials`; `lift` gives the lifter's poses for a
/// trial (one per target frame).
pub fn evaluate_lifter(
    trials: &[LifterSequence],
    lift: &(dyn Fn(&LifterSequence) -> Result<Vec<Pose>, TrainError> + Sync),
    adjusters: Adjusters,
) -> Result<LifterReport, TrainError> {
    if trials.is_empty() {
        return Err(TrainError::InvalidArgument("no trials to evaluate".into()));
    }
    for (name, n) in [
        ("gru", adjusters.gru.map(<[_]>::len)),
        ("bigru", adjusters.bigru.map(<[_]>::len)),
    ] {
        if n.is_some_and(|n| n != trials.len()) {
            return Err(TrainError::InvalidArgument(format!(
                "{name}: {} estimates for {} trials",
                n.unwrap_or(0),
                trials.len()
            )));
        }
    }
    /// before, gru, bigru, training mean, lifter median
    type PerTrial = (
        TrialMetrics,
        Option<TrialMetrics>,
        Option<TrialMetrics>,
        Option<TrialMetrics>,
        TrialMetrics,
    );
    let scored: Vec<PerTrial> = trials
        .par_iter()
        .enumerate()
        .map(|(i, tr)| -> Result<PerTrial, TrainError> {
            let pred = lift(tr)?;
            let gt = &tr.target;
            let before = trial_metrics(&pred, gt)?;
            let gru = match adjusters.gru {
                Some(g) => {
                    let adj = adjust_sequence_per_frame(&pred, &g[i], ZeroBonePolicy::KeepInput)?;
                    Some(trial_metrics(&adj, gt)?)
                }
                None => None,
            };
            let bigru = match adjusters.bigru {
                Some(b) => {
                    let adj = adjust_sequence_with(&pred, &b[i], ZeroBonePolicy::KeepInput)?;
                    Some(trial_metrics(&adj, gt)?)
                }
                None => None,
            };
            let training_mean = match adjusters.training_mean {
                Some(m) => {
                    let adj = adjust_sequence_with(&pred, m, ZeroBonePolicy::KeepInput)?;
                    Some(trial_metrics(&adj, gt)?)
                }
                None => None,
            };
            let medians = running_median_lengths(&pred);
            let adj = adjust_sequence_per_frame(&pred, &medians, ZeroBonePolicy::KeepInput)?;
            let lifter_median = trial_metrics(&adj, gt)?;
            Ok((before, gru, bigru, training_mean, lifter_median))
        })
        .collect::<Result<_, _>>()?;
    let mut acc: [Accumulator; 5] = Default::default();
    for (tr, (b, g, bi, tm, lm)) in trials.iter().zip(&scored) {
        let seq = tr.trial.sequence.as_str();
        for (a, m) in acc
            .iter_mut()
            .zip([Some(b), g.as_ref(), bi.as_ref(), tm.as_ref(), Some(lm)])
        {
            if let Some(m) = m {
                a.add(seq, *m);
            }
        }
    }
    Ok(LifterReport {
        before: acc[0].report(),
        gru: adjusters.gru.map(|_| acc[1].report()),
        bigru: adjusters.bigru.map(|_| acc[2].report()),
        training_mean: adjusters.training_mean.map(|_| acc[3].report()),
        lifter_median: acc[4].report(),
        trials: trials.len(),
        frames: trials.iter().map(LifterSequence::frames).sum(),
        weights: None,
        aggregation:
            "per metric: frame-weighted mean within each action (takes, subjects, cameras \
                      pooled), then the mean over actions"
                .into(),
    })
}

fn methods(r: &LifterReport) -> Vec<(&'static str, &MethodReport)> {
    let mut v = vec![("none", &r.before)];
    if let Some(m) = &r.training_mean {
        v.push(("baseline: constant training mean", m));
    }
    v.push(("baseline: lifter's own running median", &r.lifter_median));
    if let Some(g) = &r.gru {
        v.push(("online GRU (running estimate)", g));
    }
    if let Some(b) = &r.bigru {
        v.push(("offline Bi-GRU", b));
    }
    v
}

/// Table 2 (summary) and Table 3 (MPJPE per action) as markdown.
pub fn markdown(reports: &BTreeMap<String, LifterReport>) -> String {
    let mut s = String::from(
        "## Adjustment on S9/S11 (Table 2)\n\n\
         | lifter | adjustment | MPJPE (mm) | P-MPJPE (mm) | MPJVE (mm/frame) | bone error (mm) |\n\
         |---|---|---|---|---|---|\n",
    );
    for (name, r) in reports {
        for (method, m) in methods(r) {
            s.push_str(&format!(
                "| {name} | {method} | {:.2} | {:.2} | {:.2} | {:.2} |\n",
                m.avg.mpjpe_mm,
                m.avg.p_mpjpe_mm,
                m.avg.mpjve_mm.unwrap_or(f64::NAN),
                m.avg.bone_error_mm
            ));
        }
    }
    let actions: Vec<&String> = reports
        .values()
        .next()
        .map(|r| r.before.per_action.keys().collect())
        .unwrap_or_default();
    s.push_str("\n## MPJPE per action (mm, Table 3)\n\n| lifter | adjustment |");
    for a in &actions {
        s.push_str(&format!(" {a} |"));
    }
    s.push_str(" Avg |\n|---|---|");
    for _ in &actions {
        s.push_str("---|");
    }
    s.push_str("---|\n");
    for (name, r) in reports {
        for (method, m) in methods(r) {
            s.push_str(&format!("| {name} | {method} |"));
            for a in &actions {
                match m.per_action.get(*a) {
                    Some(v) => s.push_str(&format!(" {:.1} |", v.mpjpe_mm)),
                    None => s.push_str(" - |"),
                }
            }
            s.push_str(&format!(" {:.1} |\n", m.avg.mpjpe_mm));
        }
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A pose whose 16 bones all have non-zero length.
    fn pose(scale: f32) -> Pose {
        std::array::from_fn(|j| {
            let j = j as f32;
            [
                0.1 * j * scale,
                0.05 * (j % 3.0) * scale,
                0.02 * j * j * scale,
            ]
        })
    }

    #[test]
    fn running_median_is_causal_and_averages_the_middle_pair() {
        let scales = [1.0, 3.0, 2.0, 0.5, 10.0];
        let poses: Vec<Pose> = scales.iter().map(|&s| pose(s)).collect();
        let medians = running_median_lengths(&poses);
        let base = bone_lengths(&pose(1.0));
        // Medians of the scales so far: 1; (1+3)/2; 2; (1+2)/2; 2.
        for (t, want) in [1.0f32, 2.0, 2.0, 1.5, 2.0].into_iter().enumerate() {
            for b in 0..NUM_BONES {
                let got = medians[t][b];
                let expected = base[b] * want;
                assert!(
                    (got - expected).abs() <= 1e-5 * expected,
                    "frame {t} bone {b}: {got} vs {expected}"
                );
            }
        }
    }

    #[test]
    fn one_outlier_frame_does_not_move_the_median() {
        let mut m = RunningMedian::default();
        for v in [0.30, 0.31, 0.29, 0.30] {
            m.push(v);
        }
        let with_outlier = m.push(5.0);
        assert!((with_outlier - 0.30).abs() < 1e-6, "{with_outlier}");
    }
}

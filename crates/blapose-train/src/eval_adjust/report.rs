//! The eval-adjust report: per method, the pose metrics and the motion
//! metrics aggregated over actions, and the markdown tables printed from
//! them.

use std::collections::BTreeMap;

use blapose_core::metrics::{
    mpjpe, mpjve, p_mpjpe, pose_bone_length_error, ActionAggregator, MetricError, MM_PER_M,
};
use blapose_core::Pose;
use serde::Serialize;

use crate::error::TrainError;
use crate::motion_eval::MotionScore;

/// The four pose metrics (mm; MPJVE in mm per frame, always computed
/// here): blapose-core's one definition, shared with the client.
pub use blapose_core::metrics::PoseMetrics;

/// How a method moves (present when the evaluation had the scenes: the
/// data's cameras and world poses).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Default)]
pub struct MotionMetrics {
    /// Mean |acceleration difference| (mm/frame²).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub accel_error_mm: Option<f64>,
    /// Mean root position error of the root placed with the method's poses
    /// (mm).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub mrpe_mm: Option<f64>,
    /// Mean horizontal slide of an ankle per ground-truth contact frame
    /// (mm).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub foot_skate_mm: Option<f64>,
}

/// One method's aggregated metrics.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct MethodReport {
    /// Mean over actions (the tables' "Avg").
    #[serde(flatten)]
    pub avg: PoseMetrics,
    /// Motion metrics, mean over actions.
    #[serde(flatten)]
    pub motion: MotionMetrics,
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
    /// Oracle: the lifter's directions with the subject's true lengths
    /// (what placement can reach with right lengths).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub ground_truth_lengths: Option<MethodReport>,
    /// The online GRU streamed through the served causal motion stage.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub gru_motion: Option<MethodReport>,
    /// The Bi-GRU through the served offline motion stage.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub bigru_motion: Option<MethodReport>,
    /// A known stature's regression lengths through the causal stage.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub gru_motion_height: Option<MethodReport>,
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
pub(crate) struct TrialMetrics {
    pub m: PoseMetrics,
    pub frames: usize,
    pub motion: Option<MotionScore>,
}

fn metric(e: MetricError) -> TrainError {
    TrainError::Data(e.to_string())
}

/// The pose metrics of one trial.
pub(crate) fn trial_metrics(
    pred: &[Pose],
    gt: &[Pose],
    motion: Option<MotionScore>,
) -> Result<TrialMetrics, TrainError> {
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
        motion,
    })
}

/// One [`ActionAggregator`] per metric.
#[derive(Default)]
pub(crate) struct Accumulator {
    mpjpe: ActionAggregator,
    p_mpjpe: ActionAggregator,
    mpjve: ActionAggregator,
    bone: ActionAggregator,
    accel: ActionAggregator,
    mrpe: ActionAggregator,
    skate: ActionAggregator,
}

impl Accumulator {
    pub fn add(&mut self, sequence: &str, t: &TrialMetrics) {
        self.mpjpe.add_mean(sequence, t.m.mpjpe_mm, t.frames);
        self.p_mpjpe.add_mean(sequence, t.m.p_mpjpe_mm, t.frames);
        self.mpjve.add_mean(
            sequence,
            t.m.mpjve_mm.unwrap_or(f64::NAN),
            t.frames.saturating_sub(1),
        );
        self.bone.add_mean(sequence, t.m.bone_error_mm, t.frames);
        if let Some(m) = t.motion {
            if let Some(a) = m.accel_error_mm {
                self.accel.add_mean(sequence, a, t.frames.saturating_sub(2));
            }
            self.mrpe.add_mean(sequence, m.mrpe_mm, t.frames);
            if let Some((s, n)) = m.foot_skate {
                self.skate.add_mean(sequence, s, n);
            }
        }
    }

    pub fn report(&self) -> MethodReport {
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
            motion: MotionMetrics {
                accel_error_mm: self.accel.mean_over_actions(),
                mrpe_mm: self.mrpe.mean_over_actions(),
                foot_skate_mm: self.skate.mean_over_actions(),
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

fn methods(r: &LifterReport) -> Vec<(&'static str, &MethodReport)> {
    let mut v = vec![("none", &r.before)];
    if let Some(m) = &r.training_mean {
        v.push(("baseline: constant training mean", m));
    }
    v.push(("baseline: lifter's own running median", &r.lifter_median));
    if let Some(m) = &r.ground_truth_lengths {
        v.push(("oracle: true lengths", m));
    }
    if let Some(g) = &r.gru {
        v.push(("online GRU (running estimate)", g));
    }
    if let Some(g) = &r.gru_motion {
        v.push(("online GRU + causal motion", g));
    }
    if let Some(g) = &r.gru_motion_height {
        v.push(("known stature + causal motion", g));
    }
    if let Some(b) = &r.bigru {
        v.push(("offline Bi-GRU", b));
    }
    if let Some(b) = &r.bigru_motion {
        v.push(("offline Bi-GRU + offline motion", b));
    }
    v
}

fn cell(v: Option<f64>) -> String {
    v.map_or("-".into(), |v| format!("{v:.2}"))
}

/// Table 2 (summary with the motion metrics) and Table 3 (MPJPE per
/// action) as markdown.
pub fn markdown(reports: &BTreeMap<String, LifterReport>) -> String {
    let mut s = String::from(
        "## Adjustment on S9/S11 (Table 2)\n\n\
         | lifter | adjustment | MPJPE (mm) | P-MPJPE (mm) | MPJVE (mm/frame) | bone error (mm) \
         | accel error (mm/frame²) | MRPE (mm) | foot skate (mm/frame) |\n\
         |---|---|---|---|---|---|---|---|---|\n",
    );
    for (name, r) in reports {
        for (method, m) in methods(r) {
            s.push_str(&format!(
                "| {name} | {method} | {:.2} | {:.2} | {:.2} | {:.2} | {} | {} | {} |\n",
                m.avg.mpjpe_mm,
                m.avg.p_mpjpe_mm,
                m.avg.mpjve_mm.unwrap_or(f64::NAN),
                m.avg.bone_error_mm,
                cell(m.motion.accel_error_mm),
                cell(m.motion.mrpe_mm),
                cell(m.motion.foot_skate_mm),
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

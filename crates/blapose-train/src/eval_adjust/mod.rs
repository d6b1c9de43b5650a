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
//! With the trials' scenes ([`crate::motion_eval::Scene`]) every method is
//! also scored for motion (acceleration error, the root it places, foot
//! skating), and three more methods are scored:
//!
//! * `ground_truth_lengths`: the lifter's directions with the subject's
//!   true lengths, the oracle of root placement;
//! * `gru_motion`: `gru` streamed through the served causal motion stage
//!   (`blapose_core::motion::served_causal`), as a session with the
//!   camera's calibration is answered;
//! * `bigru_motion`: `bigru` through the served offline stage;
//! * `gru_motion_height`: a session that knows the person's stature (its
//!   stature-regression lengths, as the server answers a subject) through
//!   the causal stage. Human3.6M publishes no statures: the stature used is
//!   the one whose regression lengths sum to the subject's true total
//!   ([`blapose_model::stature::StatureLines::matched_stature`]), so it
//!   knows the size exactly and leaves the proportions to the regression.
//!
//! The pose's own root is kept (it is the origin here). A frame with a zero-length
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

mod median;
mod report;

use blapose_core::bones::{adjust_sequence_per_frame, adjust_sequence_with, ZeroBonePolicy};
use blapose_core::motion::{offline_motion, CausalMotionConfig, OfflineMotionConfig};
use blapose_core::{BoneLengths, Pose};
use rayon::prelude::*;

use crate::error::TrainError;
use crate::lifter::data::LifterSequence;
use crate::motion_eval::{place_roots, score, stream_causal, Scene};
pub use median::running_median_lengths;
pub use report::{markdown, LifterReport, MethodReport, MotionMetrics, PoseMetrics};
use report::{trial_metrics, Accumulator, TrialMetrics};

/// The motion stages scored, and the scenes they place the trials in.
#[derive(Debug, Clone, Copy)]
pub struct MotionSetup<'a> {
    /// One scene per trial (same order).
    pub scenes: &'a [Scene],
    /// The causal stage `gru_motion` streams through.
    pub causal: CausalMotionConfig,
    /// The offline stage `bigru_motion` goes through.
    pub offline: OfflineMotionConfig,
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
    /// Score motion too (and the motion methods).
    pub motion: Option<MotionSetup<'a>>,
    /// A known stature's lengths per trial (what a session opened with its
    /// subject's height answers with): scored through the causal motion
    /// stage as `gru_motion_height`.
    pub height: Option<&'a [BoneLengths]>,
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
            motion: None,
            height: None,
        }
    }
}

/// One method's poses on one trial, scored.
fn scored(
    pred: &[Pose],
    gt: &[Pose],
    scene: Option<&Scene>,
    roots: Option<Vec<[f64; 3]>>,
) -> Result<TrialMetrics, TrainError> {
    let motion = match scene {
        Some(sc) => {
            let roots = roots.unwrap_or_else(|| place_roots(pred, sc));
            Some(score(pred, &roots, gt, sc)?)
        }
        None => None,
    };
    trial_metrics(pred, gt, motion)
}

/// The methods of a report, in the order [`evaluate_lifter`] scores them.
const METHODS: usize = 9;
const BEFORE: usize = 0;
const GRU: usize = 1;
const BIGRU: usize = 2;
const TRAINING_MEAN: usize = 3;
const LIFTER_MEDIAN: usize = 4;
const TRUE_LENGTHS: usize = 5;
const GRU_MOTION: usize = 6;
const BIGRU_MOTION: usize = 7;
const GRU_MOTION_HEIGHT: usize = 8;

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
        ("scenes", adjusters.motion.map(|m| m.scenes.len())),
        ("height lengths", adjusters.height.map(<[_]>::len)),
    ] {
        if n.is_some_and(|n| n != trials.len()) {
            return Err(TrainError::InvalidArgument(format!(
                "{name}: {} for {} trials",
                n.unwrap_or(0),
                trials.len()
            )));
        }
    }
    let motion = adjusters.motion;
    let scored_trials: Vec<[Option<TrialMetrics>; METHODS]> = trials
        .par_iter()
        .enumerate()
        .map(|(i, tr)| -> Result<_, TrainError> {
            let pred = lift(tr)?;
            let gt = &tr.target;
            let scene = motion.map(|m| &m.scenes[i]);
            let mut out: [Option<TrialMetrics>; METHODS] = [None; METHODS];
            out[BEFORE] = Some(scored(&pred, gt, scene, None)?);
            if let Some(g) = adjusters.gru {
                let adj = adjust_sequence_per_frame(&pred, &g[i], ZeroBonePolicy::KeepInput)?;
                out[GRU] = Some(scored(&adj, gt, scene, None)?);
                if let (Some(m), Some(sc)) = (motion, scene) {
                    let (poses, roots) = stream_causal(&adj, &g[i], m.causal, sc)?;
                    out[GRU_MOTION] = Some(scored(&poses, gt, scene, Some(roots))?);
                }
            }
            if let Some(b) = adjusters.bigru {
                let adj = adjust_sequence_with(&pred, &b[i], ZeroBonePolicy::KeepInput)?;
                out[BIGRU] = Some(scored(&adj, gt, scene, None)?);
                if let (Some(m), Some(sc)) = (motion, scene) {
                    let lengths = vec![b[i]; adj.len()];
                    let (poses, roots) =
                        offline_motion(&adj, &lengths, &m.offline, Some(sc.viewing()))?;
                    out[BIGRU_MOTION] = Some(scored(&poses, gt, scene, roots)?);
                }
            }
            if let Some(m) = adjusters.training_mean {
                let adj = adjust_sequence_with(&pred, m, ZeroBonePolicy::KeepInput)?;
                out[TRAINING_MEAN] = Some(scored(&adj, gt, scene, None)?);
            }
            let medians = running_median_lengths(&pred);
            let adj = adjust_sequence_per_frame(&pred, &medians, ZeroBonePolicy::KeepInput)?;
            out[LIFTER_MEDIAN] = Some(scored(&adj, gt, scene, None)?);
            if scene.is_some() {
                let adj = adjust_sequence_with(&pred, &tr.trial.gt, ZeroBonePolicy::KeepInput)?;
                out[TRUE_LENGTHS] = Some(scored(&adj, gt, scene, None)?);
            }
            if let (Some(h), Some(m), Some(sc)) = (adjusters.height, motion, scene) {
                let adj = adjust_sequence_with(&pred, &h[i], ZeroBonePolicy::KeepInput)?;
                let lengths = vec![h[i]; adj.len()];
                let (poses, roots) = stream_causal(&adj, &lengths, m.causal, sc)?;
                out[GRU_MOTION_HEIGHT] = Some(scored(&poses, gt, scene, Some(roots))?);
            }
            Ok(out)
        })
        .collect::<Result<_, _>>()?;
    let mut acc: [Accumulator; METHODS] = Default::default();
    let mut seen = [false; METHODS];
    for (tr, methods) in trials.iter().zip(&scored_trials) {
        let seq = tr.trial.sequence.as_str();
        for (k, m) in methods.iter().enumerate() {
            if let Some(m) = m {
                acc[k].add(seq, m);
                seen[k] = true;
            }
        }
    }
    let report = |k: usize| seen[k].then(|| acc[k].report());
    Ok(LifterReport {
        before: acc[BEFORE].report(),
        gru: report(GRU),
        bigru: report(BIGRU),
        training_mean: report(TRAINING_MEAN),
        lifter_median: acc[LIFTER_MEDIAN].report(),
        ground_truth_lengths: report(TRUE_LENGTHS),
        gru_motion: report(GRU_MOTION),
        bigru_motion: report(BIGRU_MOTION),
        gru_motion_height: report(GRU_MOTION_HEIGHT),
        trials: trials.len(),
        frames: trials.iter().map(LifterSequence::frames).sum(),
        weights: None,
        aggregation:
            "per metric: frame-weighted mean within each action (takes, subjects, cameras \
                      pooled), then the mean over actions"
                .into(),
    })
}

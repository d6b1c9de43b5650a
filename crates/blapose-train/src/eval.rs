//! Bone-length evaluation on the standard protocol: one implementation of
//! it, so every number in the model card, the shipped-weights test and a
//! new run's report is computed the same way.
//!
//! Every (sequence, camera) of the evaluated subjects is one *trial*: the
//! model reads the whole 2D stream and gives one estimate of the subject's
//! 16 lengths; the trial's error is the mean absolute error over the 16
//! bones (mm).
//!
//! * **Offline Bi-GRU**: one pass over the whole sequence
//!   ([`OfflineBiGruEngine`]).
//! * **Online GRU**: the serving estimate, i.e. the running mean of the
//!   per-frame predictions over all frames seen ([`OnlineGruEngine`],
//!   trials stepped in lockstep batches; the mean is the server's own
//!   [`RunningMean`], so the two cannot drift apart); its error after the whole
//!   sequence is the headline, and the error after `n` frames for `n` in
//!   [`CURVE_FRAMES`] is the curve (a trial shorter than `n` contributes its
//!   final estimate).
//!
//! **Aggregation** (the headline `mean_bone_error_mm`): trials are averaged
//! within each action (take number dropped, e.g. "Walking 1" and "Walking"
//! are both "Walking"; both subjects, all cameras, each trial weighted
//! equally), then the per-action means are averaged over actions — the
//! Human3.6M tables' "Avg" ([`ActionAggregator`]). The plain mean over
//! trials, per subject and per bone are reported too. The naive baselines
//! (predict the training subjects' mean for everyone; the mean of all seven
//! subjects, test subjects included) are aggregated the same way.

use std::collections::BTreeMap;

use blapose_core::camera::Camera;
use blapose_core::metrics::ActionAggregator;
use blapose_core::pose::flip_bone_lengths;
use blapose_core::skeleton::{BONE_NAMES, NUM_BONES};
use blapose_core::BoneLengths;
use blapose_model::{
    EngineOptions, LoadedWeights, OfflineBiGruEngine, OnlineGruEngine, Precision, RunningMean,
    STATE_DIM,
};
use rayon::prelude::*;
use serde::Serialize;

use crate::dataset::EvalSequence;
use crate::error::TrainError;
use crate::synth::FRAME_DIM;

/// Frames-seen points of the online error curve.
pub const CURVE_FRAMES: [usize; 9] = [1, 2, 5, 10, 20, 50, 100, 200, 500];

/// Streams stepped together by the online evaluation.
const ONLINE_GROUP: usize = 32;

/// One trial's estimate.
#[derive(Debug, Clone, PartialEq)]
pub struct Estimate {
    /// After the whole sequence.
    pub lengths: BoneLengths,
    /// Online only: the running estimate after `CURVE_FRAMES[i]` frames.
    pub curve: Vec<BoneLengths>,
}

/// Anything that estimates lengths for a batch of trials.
pub trait LengthEstimator: Sync {
    /// One estimate per trial, in order.
    fn estimate(&self, trials: &[EvalSequence]) -> Result<Vec<Estimate>, TrainError>;
}

/// One fixed answer per subject (e.g. the stature model given each
/// subject's stature proxy).
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

impl<E: LengthEstimator + ?Sized> LengthEstimator for Box<E> {
    fn estimate(&self, trials: &[EvalSequence]) -> Result<Vec<Estimate>, TrainError> {
        (**self).estimate(trials)
    }
}

/// The offline Bi-GRU over whole sequences.
pub struct BiGruEstimator {
    engine: OfflineBiGruEngine,
}

impl BiGruEstimator {
    /// From Bi-GRU weights.
    pub fn new(weights: &LoadedWeights) -> Result<Self, TrainError> {
        Self::with_precision(weights, Precision::F32)
    }

    /// From Bi-GRU weights stored at `precision` in the engine.
    pub fn with_precision(
        weights: &LoadedWeights,
        precision: Precision,
    ) -> Result<Self, TrainError> {
        Ok(Self {
            engine: OfflineBiGruEngine::with_options(
                weights,
                EngineOptions {
                    precision,
                    ..EngineOptions::threads(1)
                },
            )?,
        })
    }
}

impl LengthEstimator for BiGruEstimator {
    fn estimate(&self, trials: &[EvalSequence]) -> Result<Vec<Estimate>, TrainError> {
        trials
            .par_iter()
            .map(|t| {
                Ok(Estimate {
                    lengths: self.engine.predict(&t.input)?,
                    curve: Vec::new(),
                })
            })
            .collect()
    }
}

/// Test-time flip augmentation: the mean of an estimator's estimates for
/// each trial and for its mirror image ([`EvalSequence::mirrored`], lengths
/// swapped back). Training flips half of its samples, so both views are in
/// the training distribution and their errors are partly independent; the
/// cost is a second pass.
pub struct FlipAveraged<E> {
    inner: E,
}

impl<E: LengthEstimator> FlipAveraged<E> {
    /// Wrap `inner`.
    pub fn new(inner: E) -> Self {
        Self { inner }
    }
}

fn mean_of_views(a: &BoneLengths, mirrored: &BoneLengths) -> BoneLengths {
    let b = flip_bone_lengths(mirrored);
    std::array::from_fn(|i| 0.5 * (a[i] + b[i]))
}

impl<E: LengthEstimator> LengthEstimator for FlipAveraged<E> {
    fn estimate(&self, trials: &[EvalSequence]) -> Result<Vec<Estimate>, TrainError> {
        let direct = self.inner.estimate(trials)?;
        let mirrored: Vec<EvalSequence> = trials.iter().map(EvalSequence::mirrored).collect();
        let seen_mirrored = self.inner.estimate(&mirrored)?;
        Ok(direct
            .into_iter()
            .zip(seen_mirrored)
            .map(|(a, b)| Estimate {
                lengths: mean_of_views(&a.lengths, &b.lengths),
                curve: a
                    .curve
                    .iter()
                    .zip(&b.curve)
                    .map(|(x, y)| mean_of_views(x, y))
                    .collect(),
            })
            .collect())
    }
}

/// Camera-height correction for models trained on rectified keypoints
/// ([`blapose_core::level`]): a scene seen from a camera `k` times higher
/// looks exactly like the scene `1/k` times the size seen from the
/// training cameras' height, so the estimate is scaled by the view's camera
/// height over that reference. `scales` maps `(subject, camera)` to that
/// ratio.
pub struct HeightCorrected<E> {
    inner: E,
    scales: BTreeMap<(String, String), f32>,
}

impl<E: LengthEstimator> HeightCorrected<E> {
    /// Wrap `inner` with one scale per view.
    pub fn new(inner: E, scales: BTreeMap<(String, String), f32>) -> Self {
        Self { inner, scales }
    }
}

impl<E: LengthEstimator> LengthEstimator for HeightCorrected<E> {
    fn estimate(&self, trials: &[EvalSequence]) -> Result<Vec<Estimate>, TrainError> {
        let est = self.inner.estimate(trials)?;
        trials
            .iter()
            .zip(est)
            .map(|(t, e)| {
                let k = *self
                    .scales
                    .get(&(t.subject.clone(), t.camera.clone()))
                    .ok_or_else(|| {
                        TrainError::Data(format!("no camera height for {} {}", t.subject, t.camera))
                    })?;
                let scale = |l: &BoneLengths| l.map(|v| v * k);
                Ok(Estimate {
                    lengths: scale(&e.lengths),
                    curve: e.curve.iter().map(scale).collect(),
                })
            })
            .collect()
    }
}

/// Evaluate camera-aware weights as the server serves a calibrated
/// session: every trial's keypoints undistorted with its camera's lens
/// model (the detections are pixels of the distorted video, and the
/// served protocol takes undistorted pixels:
/// [`crate::dataset::undistort_streams`]), then rectified with its camera
/// (scaled to the floor when the weights were trained so), and
/// `estimator` scaled by each view's camera height when the weights are
/// height-normalized.
/// `camera(subject, id)` finds each trial's calibration.
pub fn calibrated<'a>(
    estimator: Box<dyn LengthEstimator>,
    weights: &LoadedWeights,
    trials: &mut [EvalSequence],
    camera: impl Fn(&str, &str) -> Option<&'a Camera>,
) -> Result<Box<dyn LengthEstimator>, TrainError> {
    let config = crate::train::trained_config(weights);
    let (floor_scaled, height_normalized) = config
        .as_ref()
        .map_or((false, false), |c| (c.floor_scaled, c.height_normalized));
    crate::dataset::undistort_streams(trials, &camera)?;
    crate::dataset::rectify_streams(trials, &camera, floor_scaled)?;
    if height_normalized {
        height_corrected(estimator, trials, camera)
    } else {
        Ok(estimator)
    }
}

/// `estimator` scaled by each trial's camera height over the reference
/// height ([`HeightCorrected`]); `camera(subject, id)` finds each trial's
/// calibration.
pub fn height_corrected<'a>(
    estimator: Box<dyn LengthEstimator>,
    trials: &[EvalSequence],
    camera: impl Fn(&str, &str) -> Option<&'a Camera>,
) -> Result<Box<dyn LengthEstimator>, TrainError> {
    let mut scales = BTreeMap::new();
    for t in trials {
        let cam = camera(&t.subject, &t.camera)
            .ok_or_else(|| TrainError::Data(format!("no camera {} for {}", t.camera, t.subject)))?;
        scales.insert(
            (t.subject.clone(), t.camera.clone()),
            blapose_core::level::height_scale(cam.center[2]) as f32,
        );
    }
    Ok(Box::new(HeightCorrected::new(estimator, scales)))
}

/// The online GRU's running mean of per-frame predictions.
pub struct GruEstimator {
    engine: OnlineGruEngine,
    /// Restart the hidden state every this many frames (the running mean
    /// of predictions carries on); `None`: never.
    state_frames: Option<usize>,
}

impl GruEstimator {
    /// From GRU weights.
    pub fn new(weights: &LoadedWeights) -> Result<Self, TrainError> {
        Self::with_precision(weights, Precision::F32)
    }

    /// From GRU weights stored at `precision` in the engine.
    pub fn with_precision(
        weights: &LoadedWeights,
        precision: Precision,
    ) -> Result<Self, TrainError> {
        Ok(Self {
            engine: OnlineGruEngine::with_options(
                weights,
                EngineOptions {
                    precision,
                    ..EngineOptions::threads(1)
                },
            )?,
            state_frames: None,
        })
    }

    /// The same estimator restarting its hidden state every `frames`
    /// frames (`None` or 0: never).
    pub fn with_state_frames(mut self, frames: Option<usize>) -> Self {
        self.state_frames = frames.filter(|&f| f > 0);
        self
    }

    /// Step a group of trials in lockstep; finished trials are fed their
    /// last frame again but stop accumulating. With `per_frame`, the second
    /// element holds every frame's running estimate (the estimate after
    /// frames `0..=t`, what a causal adjustment of frame `t` uses);
    /// otherwise it is empty.
    fn run_group(
        &self,
        group: &[&EvalSequence],
        per_frame: bool,
    ) -> Result<Vec<(Estimate, Vec<BoneLengths>)>, TrainError> {
        let b = group.len();
        let longest = group.iter().map(|t| t.frames()).max().unwrap_or(0);
        let mut hidden = vec![0.0f32; b * STATE_DIM];
        let mut out = vec![0.0f32; b * NUM_BONES];
        let mut input = vec![0.0f32; b * FRAME_DIM];
        let mut means = vec![RunningMean::new(); b];
        let mut curves = vec![Vec::with_capacity(CURVE_FRAMES.len()); b];
        let mut running: Vec<Vec<BoneLengths>> = group
            .iter()
            .map(|t| Vec::with_capacity(if per_frame { t.frames() } else { 0 }))
            .collect();
        let mut scratch = self.engine.scratch(b);
        for t in 0..longest {
            if self.state_frames.is_some_and(|k| t > 0 && t % k == 0) {
                hidden.fill(0.0);
            }
            for (i, tr) in group.iter().enumerate() {
                let f = t.min(tr.frames() - 1);
                input[i * FRAME_DIM..(i + 1) * FRAME_DIM]
                    .copy_from_slice(&tr.input[f * FRAME_DIM..(f + 1) * FRAME_DIM]);
            }
            self.engine
                .step(&input, &mut hidden, &mut out, &mut scratch)?;
            for (i, tr) in group.iter().enumerate() {
                if t >= tr.frames() {
                    continue;
                }
                let frame: &BoneLengths = out[i * NUM_BONES..(i + 1) * NUM_BONES]
                    .try_into()
                    .map_err(|_| TrainError::Data("model output is not 16 lengths".into()))?;
                let mean = means[i].push(frame);
                let seen = t + 1;
                for &n in &CURVE_FRAMES {
                    if seen == n || (seen == tr.frames() && n > seen) {
                        curves[i].push(mean);
                    }
                }
                if per_frame {
                    running[i].push(mean);
                }
            }
        }
        Ok(running
            .into_iter()
            .enumerate()
            .map(|(i, r)| {
                let e = Estimate {
                    lengths: means[i].mean().unwrap_or([0.0; NUM_BONES]),
                    curve: std::mem::take(&mut curves[i]),
                };
                (e, r)
            })
            .collect())
    }

    /// Run every trial (in groups of similar length, so lockstep wastes
    /// little; groups in parallel), results in trial order.
    fn run_all(
        &self,
        trials: &[EvalSequence],
        per_frame: bool,
    ) -> Result<Vec<(Estimate, Vec<BoneLengths>)>, TrainError> {
        let mut order: Vec<usize> = (0..trials.len())
            .filter(|&i| trials[i].frames() > 0)
            .collect();
        order.sort_by_key(|&i| trials[i].frames());
        let groups: Vec<Vec<usize>> = order.chunks(ONLINE_GROUP).map(|c| c.to_vec()).collect();
        type Indexed = Vec<(usize, (Estimate, Vec<BoneLengths>))>;
        let results: Vec<Indexed> = groups
            .par_iter()
            .map(|g| {
                let refs: Vec<&EvalSequence> = g.iter().map(|&i| &trials[i]).collect();
                Ok(g.iter()
                    .copied()
                    .zip(self.run_group(&refs, per_frame)?)
                    .collect())
            })
            .collect::<Result<_, TrainError>>()?;
        let mut out: Vec<Option<(Estimate, Vec<BoneLengths>)>> = vec![None; trials.len()];
        for (i, e) in results.into_iter().flatten() {
            out[i] = Some(e);
        }
        out.into_iter()
            .enumerate()
            .map(|(i, e)| e.ok_or_else(|| TrainError::Data(format!("trial {i} has no frames"))))
            .collect()
    }

    /// For every trial, the running estimate after each frame (`result[i][t]`
    /// is the mean of the per-frame predictions of frames `0..=t`).
    pub fn running_estimates(
        &self,
        trials: &[EvalSequence],
    ) -> Result<Vec<Vec<BoneLengths>>, TrainError> {
        Ok(self
            .run_all(trials, true)?
            .into_iter()
            .map(|(_, r)| r)
            .collect())
    }
}

impl LengthEstimator for GruEstimator {
    fn estimate(&self, trials: &[EvalSequence]) -> Result<Vec<Estimate>, TrainError> {
        Ok(self
            .run_all(trials, false)?
            .into_iter()
            .map(|(e, _)| e)
            .collect())
    }
}

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
    /// With `--drop-joints`: the headline is the model reading the trials
    /// with lost joints held (confidence honoured); this compares it with
    /// the clean trials and with the garbage fed as is.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub drop_joints: Option<crate::joint_dropout::DropJointsReport>,
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
fn per_subject_mean(
    trials: &[EvalSequence],
    pred: &[BoneLengths],
) -> BTreeMap<String, SubjectMean> {
    grouped_mean(trials, pred, |t| t.subject.clone())
}

/// Per view (subject and camera, key `"S9 54138969"`): the same means.
/// Human3.6M's cameras were calibrated again for every subject, and a
/// model that reads size from where the feet meet the floor carries the
/// camera's placement into its estimate; this shows it per camera.
fn per_view_mean(trials: &[EvalSequence], pred: &[BoneLengths]) -> BTreeMap<String, SubjectMean> {
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
fn per_bone_bias_mm(trials: &[EvalSequence], pred: &[BoneLengths]) -> Vec<f64> {
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

/// Evaluate `estimator` on `trials`; `baselines` are `(name, lengths)`
/// predicted for every trial.
#[allow(clippy::too_many_arguments)]
pub fn evaluate(
    estimator: &dyn LengthEstimator,
    trials: &[EvalSequence],
    baselines: &[(&str, BoneLengths)],
    model: &str,
    input: &str,
    weights: &str,
    subjects: &[String],
) -> Result<EvalReport, TrainError> {
    let t0 = std::time::Instant::now();
    let est = estimator.estimate(trials)?;
    let seconds = t0.elapsed().as_secs_f64();
    let pred: Vec<BoneLengths> = est.iter().map(|e| e.lengths).collect();
    let summary = summarize(trials, &pred)?;
    let per_subject_mean_prediction = per_subject_mean(trials, &pred);
    let mut base = BTreeMap::new();
    for (name, l) in baselines {
        base.insert(
            name.to_string(),
            summarize(trials, &vec![*l; trials.len()])?,
        );
    }
    let mut curve = Vec::new();
    if est.iter().all(|e| e.curve.len() == CURVE_FRAMES.len()) && !est.is_empty() {
        for (k, &n) in CURVE_FRAMES.iter().enumerate() {
            let p: Vec<BoneLengths> = est.iter().map(|e| e.curve[k]).collect();
            let s = summarize(trials, &p)?;
            curve.push(CurvePoint {
                frames: n,
                mean_bone_error_mm: s.mean_bone_error_mm,
                mean_over_trials_mm: s.mean_over_trials_mm,
            });
        }
    }
    Ok(EvalReport {
        model: model.into(),
        input: input.into(),
        weights: weights.into(),
        subjects: subjects.to_vec(),
        aggregation: "mean over actions of the mean error of each action's trials (sequence x camera, \
                      both subjects, each trial weighted equally); per trial: mean |pred - true| over 16 bones"
            .into(),
        trials: trials.len(),
        frames: trials.iter().map(|t| t.frames()).sum(),
        mean_bone_error_mm: summary.mean_bone_error_mm,
        per_bone_mm: summary.per_bone_mm.clone(),
        bone_names: BONE_NAMES.iter().map(|s| s.to_string()).collect(),
        per_action_mm: summary.per_action_mm.clone(),
        per_bone_bias_mm: per_bone_bias_mm(trials, &pred),
        subject_spread: subject_spread(&per_subject_mean_prediction),
        per_subject_mean_prediction,
        per_view_mean_prediction: per_view_mean(trials, &pred),
        trial_predictions: trials
            .iter()
            .zip(&pred)
            .map(|(t, p)| TrialPrediction {
                subject: t.subject.clone(),
                sequence: t.sequence.clone(),
                camera: t.camera.clone(),
                frames: t.frames(),
                predicted_m: p.to_vec(),
                true_m: t.gt.to_vec(),
            })
            .collect(),
        summary,
        baselines: base,
        curve,
        seconds,
        drop_joints: None,
    })
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

    /// Predicts the first frame's x coordinate of joint 1 (r_hip) as the
    /// r_hip length and 0 elsewhere: not mirror-invariant, so the average
    /// of the two views is visible.
    struct FirstX;

    impl LengthEstimator for FirstX {
        fn estimate(&self, trials: &[EvalSequence]) -> Result<Vec<Estimate>, TrainError> {
            Ok(trials
                .iter()
                .map(|t| {
                    let mut l = [0.0; NUM_BONES];
                    l[0] = t.input[2];
                    Estimate {
                        lengths: l,
                        curve: vec![l],
                    }
                })
                .collect())
        }
    }

    #[test]
    fn flip_averaging_means_the_direct_and_the_mirrored_view() {
        let mut input = vec![0.0; FRAME_DIM];
        input[2] = 0.3; // r_hip x
        input[8] = 0.1; // l_hip x: r_hip's x in the mirror is -0.1
        let trial = EvalSequence {
            subject: "S9".into(),
            sequence: "Walking".into(),
            camera: "54138969".into(),
            input,
            gt: [0.2; NUM_BONES],
        };
        let est = FlipAveraged::new(FirstX).estimate(&[trial]).unwrap();
        // Direct: r_hip 0.3. Mirrored: r_hip slot -0.1, swapped back to l_hip.
        assert!((est[0].lengths[0] - 0.15).abs() < 1e-6);
        assert!((est[0].lengths[3] + 0.05).abs() < 1e-6);
        assert_eq!(est[0].curve.len(), 1);
        assert_eq!(est[0].curve[0], est[0].lengths);
    }

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

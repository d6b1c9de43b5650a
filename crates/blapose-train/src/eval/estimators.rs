//! The estimators the protocol scores ([`super::LengthEstimator`]): the
//! offline Bi-GRU over whole sequences, the online GRU's running mean (the
//! serving estimate, stepped in lockstep batches), test-time flip
//! averaging; and [`calibrate`], the trials fed as the server feeds a
//! calibrated session.
//!
//! Why apart from the protocol: the protocol ([`super::evaluate`]) scores
//! any estimator (a constant, a stature answer, a lifter's lengths); these
//! are the ways the shipped networks are run.

use blapose_core::camera::Camera;
use blapose_core::pose::flip_bone_lengths;
use blapose_core::skeleton::NUM_BONES;
use blapose_core::BoneLengths;
use blapose_model::{
    EngineOptions, LoadedWeights, OfflineBiGruEngine, OnlineGruEngine, Precision, RunningMean,
    STATE_DIM,
};
use rayon::prelude::*;

use super::{Estimate, LengthEstimator, CURVE_FRAMES};
use crate::dataset::{prepare_streams, undistort_streams, EvalSequence};
use crate::error::TrainError;
use crate::synth::FRAME_DIM;

/// Streams stepped together by the online evaluation.
const ONLINE_GROUP: usize = 32;

/// One evaluation thread's engine options at `precision`.
fn engine_options(precision: Precision) -> EngineOptions {
    EngineOptions {
        precision,
        ..EngineOptions::threads(1)
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

    /// From Bi-GRU weights stored at `precision` in the engine (to score a
    /// serving precision against f32).
    pub fn with_precision(
        weights: &LoadedWeights,
        precision: Precision,
    ) -> Result<Self, TrainError> {
        Ok(Self {
            engine: OfflineBiGruEngine::with_options(weights, engine_options(precision))?,
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

/// Feed camera-aware weights the trials as the server feeds a calibrated
/// session: every trial's keypoints undistorted with its camera's lens
/// model (the detections are pixels of the distorted video, and the
/// served protocol takes undistorted pixels: [`undistort_streams`]), then
/// prepared as the weights' input contract says ([`prepare_streams`]:
/// rectified with the camera, scaled to the floor when they were trained
/// so). Weights that record no contract are taken to read plain
/// rectified keypoints
/// ([`blapose_model::WeightsMetadata::input_contract`]); calibration-free weights
/// read no calibration and are refused. `camera(subject, id)` finds each
/// trial's calibration.
pub fn calibrate<'a>(
    weights: &LoadedWeights,
    trials: &mut [EvalSequence],
    camera: impl Fn(&str, &str) -> Option<&'a Camera>,
) -> Result<(), TrainError> {
    let input = weights.meta.input_contract(true);
    if !input.framing.needs_calibration() {
        return Err(TrainError::InvalidArgument(
            "these weights read keypoints as the camera gave them (input contract: screen); \
             a calibration is for camera-aware weights"
                .into(),
        ));
    }
    undistort_streams(trials, &camera)?;
    prepare_streams(trials, &input, &camera)
}

/// Which frames the online GRU's hidden state restarts (from zeros)
/// before: `restart(t)` for frame `t` of a trial, the running mean of
/// predictions carrying on ([`GruEstimator::with_state_restarts`]).
pub type StateRestarts = std::sync::Arc<dyn Fn(usize) -> bool + Send + Sync>;

/// The online GRU's running mean of per-frame predictions.
pub struct GruEstimator {
    engine: OnlineGruEngine,
    /// Before which frames the hidden state restarts; `None`: never.
    restarts: Option<StateRestarts>,
}

impl GruEstimator {
    /// From GRU weights.
    pub fn new(weights: &LoadedWeights) -> Result<Self, TrainError> {
        Self::with_precision(weights, Precision::F32)
    }

    /// From GRU weights stored at `precision` in the engine (to score a
    /// serving precision against f32).
    pub fn with_precision(
        weights: &LoadedWeights,
        precision: Precision,
    ) -> Result<Self, TrainError> {
        Ok(Self {
            engine: OnlineGruEngine::with_options(weights, engine_options(precision))?,
            restarts: None,
        })
    }

    /// The same estimator restarting its hidden state before the frames
    /// `restarts` names. The lockstep loop is the one place a state lives
    /// through a trial, so this is where a caller can restart it; which
    /// frames (e.g. `blapose-lab diagnose --state-frames`) is the
    /// caller's.
    pub fn with_state_restarts(mut self, restarts: StateRestarts) -> Self {
        self.restarts = Some(restarts);
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
            if self.restarts.as_ref().is_some_and(|restart| restart(t)) {
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
}

//! The many-bodies benchmark's trials: each held-out individual retargeted
//! onto a clip of test-subject motion, seen by one drawn camera with real
//! detector noise; and each model's estimate of them, its keypoints
//! prepared as its weights' input contract says.
//!
//! Why apart from the run: the trials are the benchmark's data (seeded,
//! built once, read by every row); what the rows make of them is
//! [`super::run`]'s.

use blapose_core::{BoneLengths, Keypoints2d, Pose};
use blapose_model::input::{ModelInput, ViewCalibration};
use blapose_model::Precision;
use blapose_train::ansur_split::Person;
use blapose_train::camera_range::{draw_camera_seeing, DrawnCamera};
use blapose_train::dataset::EvalSequence;
use blapose_train::eval::run::network_estimator;
use blapose_train::eval::LengthEstimator;
use blapose_train::noise::{apply_residual, residual_at, ResidualBank};
use blapose_train::synth::{rebuild_on_floor, sample_rng, MotionSequence, FRAME_DIM};
use blapose_train::TrainError;
use rand::Rng;
use rayon::prelude::*;

use super::{BenchModel, BodiesConfig};

/// Camera draws per clip before another clip is drawn.
const CAMERA_TRIES: usize = 200;
/// Clips drawn per individual before giving up.
const CLIP_TRIES: usize = 20;

/// One individual's trial: truth, clip, camera and what the camera saw.
#[derive(Debug, Clone)]
pub struct Trial {
    /// The survey id.
    pub subject_id: u64,
    /// True lengths (metres).
    pub lengths: BoneLengths,
    /// Motion: `"S9/Walking 1"`.
    pub motion: String,
    /// First frame of the clip.
    pub start: usize,
    /// The camera.
    pub camera: DrawnCamera,
    /// Normalized keypoints (`frames * 34`) as the camera gave them.
    pub plain: Vec<f32>,
}

impl Trial {
    /// The trial as a model with input contract `input` reads it: the
    /// keypoints prepared with the drawn camera's calibration
    /// ([`ModelInput::camera`]; as they are for calibration-free weights).
    pub fn stream(&self, input: &ModelInput) -> Result<EvalSequence, TrainError> {
        let mut frames = self.plain.clone();
        let view = ViewCalibration::from_camera(&self.camera.camera);
        if let Some(camera) = input.camera(&view)? {
            camera.prepare_frames(&mut frames);
        }
        Ok(EvalSequence {
            subject: self.subject_id.to_string(),
            sequence: self.motion.clone(),
            camera: "benchmark".into(),
            input: frames,
            gt: self.lengths,
        })
    }
}

/// Build every individual's trial (see the module docs of
/// [`super`]). `motions` are the test subjects' decomposed sequences
/// (their own lengths in [`MotionSequence::lengths`]); `residuals` the
/// training subjects' noise.
pub fn build_trials(
    people: &[&Person],
    motions: &[MotionSequence],
    residuals: &ResidualBank,
    cfg: &BodiesConfig,
) -> Result<Vec<Trial>, TrainError> {
    cfg.cameras.validate()?;
    if cfg.frames == 0 {
        return Err(TrainError::InvalidArgument(
            "clip length must be positive".into(),
        ));
    }
    let usable: Vec<&MotionSequence> = motions.iter().filter(|m| m.len() >= cfg.frames).collect();
    if usable.is_empty() {
        return Err(TrainError::Data(format!(
            "no test sequence has {} frames",
            cfg.frames
        )));
    }
    if residuals.frames() == 0 {
        return Err(TrainError::Data("the residual bank is empty".into()));
    }
    let n = cfg.limit.map_or(people.len(), |l| l.min(people.len()));
    people[..n]
        .par_iter()
        .enumerate()
        .map(|(i, p)| trial(p, &usable, residuals, cfg, i as u64))
        .collect()
}

fn trial(
    person: &Person,
    motions: &[&MotionSequence],
    residuals: &ResidualBank,
    cfg: &BodiesConfig,
    index: u64,
) -> Result<Trial, TrainError> {
    let mut rng = sample_rng(cfg.seed, 0, index);
    for _ in 0..CLIP_TRIES {
        let m = motions[rng.random_range(0..motions.len())];
        let start = rng.random_range(0..=m.len() - cfg.frames);
        let world: Vec<Pose> = (start..start + cfg.frames)
            .map(|f| rebuild_on_floor(m.roots[f], &m.dirs[f], &person.lengths, &m.lengths))
            .collect();
        let Ok(camera) = draw_camera_seeing(&cfg.cameras, &world, CAMERA_TRIES, &mut rng) else {
            continue;
        };
        let cam = &camera.camera;
        let k = cam.normalized_intrinsics();
        let track = residuals
            .random_track(&mut rng)
            .ok_or_else(|| TrainError::Data("the residual bank is empty".into()))?;
        let offset = rng.random_range(0..=track.len().saturating_sub(cfg.frames));
        let mut plain = Vec::with_capacity(cfg.frames * FRAME_DIM);
        for (t, p) in world.iter().enumerate() {
            let c = cam.world_to_camera_pose(p);
            let mut kp: Keypoints2d = k.project_pose(&c);
            // Short tracks repeat their last frame (residual_at clamps).
            let r = residual_at(track, (offset + t) as f32);
            apply_residual(&mut kp, &r, c[0][2], k.focal);
            plain.extend(kp.iter().flatten());
        }
        return Ok(Trial {
            subject_id: person.subject_id,
            lengths: person.lengths,
            motion: format!("{}/{}", m.subject, m.action),
            start,
            camera,
            plain,
        });
    }
    Err(TrainError::Data(format!(
        "no clip of individual {} could be framed by the camera range",
        person.subject_id
    )))
}

/// One model's final estimate per trial (the online GRU's: its running
/// mean at the last frame), each trial read as the model's weights say
/// ([`BenchModel::contract`], [`Trial::stream`]).
pub fn estimate(model: &BenchModel<'_>, trials: &[Trial]) -> Result<Vec<BoneLengths>, TrainError> {
    let contract = model.contract()?;
    let streams = trials
        .iter()
        .map(|t| t.stream(&contract))
        .collect::<Result<Vec<_>, _>>()?;
    let est = network_estimator(model.kind, model.weights, Precision::F32)?.estimate(&streams)?;
    Ok(est.into_iter().map(|e| e.lengths).collect())
}

/// The person of each trial, in trial order: `people` and `trials` are in
/// the same order (the trials of `people[..trials.len()]`); a shorter or
/// misaligned `people` is an error.
pub fn trial_people<'a>(
    people: &[&'a Person],
    trials: &[Trial],
) -> Result<Vec<&'a Person>, TrainError> {
    if people.len() < trials.len() {
        return Err(TrainError::InvalidArgument(format!(
            "{} people for {} trials",
            people.len(),
            trials.len()
        )));
    }
    trials
        .iter()
        .zip(people)
        .map(|(t, &p)| {
            if p.subject_id == t.subject_id {
                Ok(p)
            } else {
                Err(TrainError::InvalidArgument(format!(
                    "person {} is not the individual of trial {}",
                    p.subject_id, t.subject_id
                )))
            }
        })
        .collect()
}

/// Each individual's stature, in trial order ([`trial_people`]).
pub fn statures(people: &[&Person], trials: &[Trial]) -> Result<Vec<f64>, TrainError> {
    Ok(trial_people(people, trials)?
        .iter()
        .map(|p| f64::from(p.stature_m))
        .collect())
}

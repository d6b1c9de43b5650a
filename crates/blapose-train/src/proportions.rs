//! Fitting the proportion reader ([`blapose_model::proportions`]): one
//! ridge regression per bone (and per sex) from the stature and the
//! stature times each bone-fraction statistic of a clip's 2D keypoints.
//!
//! Why a linear model on hand-made statistics: given the height, what is
//! left to read is proportion, and a bone's share of the summed bone length
//! in 2D is a direct, scale-free view of it. The recurrent models, trained
//! to output absolute lengths, added nothing measurable on top of the
//! height (`height` rows of the many-bodies benchmark); these statistics,
//! fitted on the same kind of data, do (models/README.md).
//!
//! What it is fitted on ([`fit_trials`]): ANSUR II *training-split* bodies
//! ([`crate::ansur_split`]) retargeted onto the *training* subjects'
//! motion, seen through cameras from the benchmark's wide distribution
//! with real-detector residual noise: the benchmark's generator
//! ([`crate::bodies::build_trials`]) with training data only, so the
//! held-out individuals and S9/S11 never enter the fit. The ridge strength
//! and the shrinkage ([`blapose_model::proportions::SHRINK_FRAMES`]) were
//! chosen on a validation quarter of those training bodies.

use blapose_core::skeleton::NUM_BONES;
use blapose_core::BoneLengths;
use blapose_data::ansur::Sex as AnsurSex;
use blapose_model::proportions::{
    inputs, FeaturePrior, ProportionModel, ProportionStats, ReaderLines, INPUTS, PROPORTIONS_FORMAT,
};
use blapose_model::stature::Sex;
use nalgebra::{DMatrix, DVector};

use crate::ansur_split::Person;
use crate::bodies::{build_trials, BodiesConfig, Trial};
use crate::dataset::EvalSequence;
use crate::error::TrainError;
use crate::eval::{Estimate, LengthEstimator};
use crate::noise::ResidualBank;
use crate::synth::MotionSequence;

/// Ridge strength on standardized inputs, per sample (chosen on a
/// validation quarter of the training bodies: 0.01 and 0.001 within
/// 0.01 mm, 0.1 worse).
pub const RIDGE: f64 = 0.01;

/// The reader's `model` in benchmark rows.
pub const MODEL_NAME: &str = "proportion-reader";

/// Default seed of the fitting trials (neither the benchmark's nor the
/// height-fusion fit's).
pub const FIT_SEED: u64 = 11;

/// The model's sex from the survey's.
pub fn model_sex(sex: AnsurSex) -> Sex {
    match sex {
        AnsurSex::Male => Sex::Male,
        AnsurSex::Female => Sex::Female,
    }
}

/// One body's clip, reduced to what the reader sees and what it must
/// answer.
#[derive(Debug, Clone, PartialEq)]
pub struct FitSample {
    /// Measured stature, metres.
    pub stature_m: f64,
    /// Sex.
    pub sex: Sex,
    /// The clip's bone-fraction statistics (every frame of the normalized
    /// keypoints, as a session would push them).
    pub stats: ProportionStats,
    /// True lengths.
    pub lengths: BoneLengths,
}

/// Each trial's sample; `people` and `trials` in the same order (the
/// trials of `people[..trials.len()]`).
pub fn samples(people: &[&Person], trials: &[Trial]) -> Result<Vec<FitSample>, TrainError> {
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
        .map(|(t, p)| {
            if p.subject_id != t.subject_id {
                return Err(TrainError::InvalidArgument(format!(
                    "person {} is not the individual of trial {}",
                    p.subject_id, t.subject_id
                )));
            }
            Ok(FitSample {
                stature_m: f64::from(p.stature_m),
                sex: model_sex(p.sex),
                stats: ProportionStats::of_frames(&t.plain),
                lengths: t.lengths,
            })
        })
        .collect()
}

/// The mean raw moments over the samples that counted a frame.
fn prior(samples: &[FitSample]) -> Result<FeaturePrior, TrainError> {
    let mut mean = [0.0; NUM_BONES];
    let mut mean_square = [0.0; NUM_BONES];
    let mut n = 0usize;
    for (m1, m2) in samples.iter().filter_map(|s| s.stats.moments()) {
        for b in 0..NUM_BONES {
            mean[b] += m1[b];
            mean_square[b] += m2[b];
        }
        n += 1;
    }
    if n == 0 {
        return Err(TrainError::Data(
            "no fitting clip showed a measurable body".into(),
        ));
    }
    Ok(FeaturePrior {
        mean: mean.map(|v| v / n as f64).to_vec(),
        mean_square: mean_square.map(|v| v / n as f64).to_vec(),
    })
}

/// Ridge regression of the lengths on the inputs, on standardized inputs
/// with an unpenalized intercept, folded back to raw inputs.
fn ridge(group: &str, rows: &[([f64; INPUTS], BoneLengths)]) -> Result<ReaderLines, TrainError> {
    let n = rows.len();
    if n <= INPUTS {
        return Err(TrainError::Data(format!(
            "{n} {group} bodies are too few to fit {INPUTS} inputs"
        )));
    }
    let nf = n as f64;
    let mu: [f64; INPUTS] =
        std::array::from_fn(|j| rows.iter().map(|(x, _)| x[j]).sum::<f64>() / nf);
    let sd: [f64; INPUTS] = std::array::from_fn(|j| {
        let var = rows
            .iter()
            .map(|(x, _)| (x[j] - mu[j]).powi(2))
            .sum::<f64>()
            / nf;
        var.sqrt().max(1e-12)
    });
    let y_mean: [f64; NUM_BONES] =
        std::array::from_fn(|b| rows.iter().map(|(_, l)| f64::from(l[b])).sum::<f64>() / nf);
    let z = DMatrix::from_fn(n, INPUTS, |i, j| (rows[i].0[j] - mu[j]) / sd[j]);
    let y = DMatrix::from_fn(n, NUM_BONES, |i, b| f64::from(rows[i].1[b]) - y_mean[b]);
    let gram = z.transpose() * &z + DMatrix::identity(INPUTS, INPUTS) * (RIDGE * nf);
    let chol = gram
        .cholesky()
        .ok_or_else(|| TrainError::Data(format!("the {group} fit is singular")))?;
    let w = chol.solve(&(z.transpose() * y));
    let mut intercept = Vec::with_capacity(NUM_BONES);
    let mut weights = Vec::with_capacity(NUM_BONES);
    for b in 0..NUM_BONES {
        let col: DVector<f64> = w.column(b).into_owned();
        let raw: Vec<f64> = (0..INPUTS).map(|j| col[j] / sd[j]).collect();
        let shift: f64 = raw.iter().zip(&mu).map(|(w, m)| w * m).sum();
        intercept.push(y_mean[b] - shift);
        weights.push(raw);
    }
    Ok(ReaderLines {
        intercept,
        weights,
        people: n,
    })
}

/// Fit the reader: pooled, and per sex. `source` says where the samples
/// come from (written into the file).
pub fn fit(samples: &[FitSample], source: String) -> Result<ProportionModel, TrainError> {
    let prior = prior(samples)?;
    let rows = |keep: &dyn Fn(&FitSample) -> bool| -> Vec<([f64; INPUTS], BoneLengths)> {
        samples
            .iter()
            .filter(|s| keep(s))
            .map(|s| (inputs(s.stature_m, &s.stats.features(&prior)), s.lengths))
            .collect()
    };
    Ok(ProportionModel {
        format: PROPORTIONS_FORMAT.into(),
        source,
        pooled: ridge("pooled", &rows(&|_| true))?,
        female: ridge("female", &rows(&|s| s.sex == Sex::Female))?,
        male: ridge("male", &rows(&|s| s.sex == Sex::Male))?,
        prior,
    })
}

/// The reader as an evaluation estimator: each trial's lengths from its
/// subject's stature and the statistics of the trial's keypoints (every
/// frame, as a session that sent the whole trial would have them).
pub struct ReaderEstimator {
    /// The reader.
    pub model: ProportionModel,
    /// Each subject's stature (metres).
    pub statures: std::collections::BTreeMap<String, f32>,
}

impl LengthEstimator for ReaderEstimator {
    fn estimate(&self, trials: &[EvalSequence]) -> Result<Vec<Estimate>, TrainError> {
        trials
            .iter()
            .map(|t| {
                let stature = *self.statures.get(&t.subject).ok_or_else(|| {
                    TrainError::Data(format!("no stature for subject {}", t.subject))
                })?;
                Ok(Estimate {
                    lengths: self.model.predict(
                        stature,
                        None,
                        &ProportionStats::of_frames(&t.input),
                    ),
                    curve: Vec::new(),
                })
            })
            .collect()
    }
}

/// What [`fit_training`] fits on: training data only.
pub struct TrainingBodies<'a> {
    /// ANSUR II training-split people ([`crate::bodies::fit_people`]).
    pub people: Vec<&'a Person>,
    /// The training subjects' decomposed motion.
    pub motions: &'a [MotionSequence],
    /// The training subjects' detector residuals.
    pub residuals: &'a ResidualBank,
    /// Seed of the clips, cameras and noise ([`FIT_SEED`] for the shipped
    /// file).
    pub seed: u64,
    /// Frames per clip.
    pub frames: usize,
}

/// Build one clip per body with the benchmark's generator and fit the
/// reader on them: what `blapose fit-proportions` writes.
pub fn fit_training(bodies: &TrainingBodies<'_>) -> Result<ProportionModel, TrainError> {
    if let Some(p) = bodies
        .people
        .iter()
        .find(|p| crate::ansur_split::is_held_out(p.subject_id, p.sex))
    {
        return Err(TrainError::InvalidArgument(format!(
            "person {} is in the held-out split",
            p.subject_id
        )));
    }
    let cfg = BodiesConfig {
        seed: bodies.seed,
        frames: bodies.frames,
        ..BodiesConfig::default()
    };
    let trials = build_trials(&bodies.people, bodies.motions, bodies.residuals, &cfg)?;
    let samples = samples(&bodies.people, &trials)?;
    drop(trials);
    fit(
        &samples,
        format!(
            "{} ANSUR II training-split bodies (blapose_train::ansur_split; lengths calibrated to \
             the Human3.6M training subjects), each retargeted onto {} frames of one training-subject \
             sequence (S1-S8, feet on the floor) and seen through one camera from the many-bodies \
             benchmark's wide distribution with real Stacked Hourglass residual noise (seed {}); \
             ridge {RIDGE} per bone on stature and stature x bone-fraction statistics, per sex and \
             pooled; written by `blapose fit-proportions`",
            samples.len(),
            bodies.frames,
            bodies.seed,
        ),
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use blapose_core::Keypoints2d;
    use rand::{Rng, SeedableRng};

    /// A figure whose thighs are `thigh` of its height in 2D, jittered.
    fn clip(thigh: f32, rng: &mut impl Rng) -> ProportionStats {
        let mut stats = ProportionStats::default();
        for _ in 0..50 {
            let mut kp: Keypoints2d = [[0.0; 2]; blapose_core::NUM_JOINTS];
            let j = |rng: &mut dyn rand::RngCore| rng.random_range(-0.005f32..0.005);
            for (i, p) in kp.iter_mut().enumerate() {
                *p = [0.05 * i as f32 + j(rng), -0.03 * i as f32 + j(rng)];
            }
            kp[2] = [kp[1][0], kp[1][1] + thigh];
            kp[5] = [kp[4][0], kp[4][1] + thigh];
            stats.push(&kp);
        }
        stats
    }

    #[test]
    fn the_fit_reads_a_planted_proportion_beyond_the_stature() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(5);
        let mut make = |n: usize| -> Vec<FitSample> {
            (0..n)
                .map(|i| {
                    let stature = rng.random_range(1.5..1.95);
                    let share = rng.random_range(0.2f32..0.4);
                    let stats = clip(share, &mut rng);
                    let mut lengths = [0.0f32; NUM_BONES];
                    for (b, l) in lengths.iter_mut().enumerate() {
                        *l = 0.1 + 0.01 * b as f32 + 0.1 * stature as f32;
                    }
                    // The thighs depend on the proportion the video shows.
                    lengths[1] = stature as f32 * share;
                    lengths[4] = lengths[1];
                    FitSample {
                        stature_m: stature,
                        sex: if i % 3 == 0 { Sex::Female } else { Sex::Male },
                        stats,
                        lengths,
                    }
                })
                .collect()
        };
        let train = make(400);
        let test = make(100);
        let model = fit(&train, "test".into()).unwrap();
        assert_eq!(model.pooled.people, 400);
        assert_eq!(model.female.people + model.male.people, 400);
        // The written file answers as the fitted model (JSON floats parse
        // back to within an ulp).
        let reparsed = ProportionModel::from_json(&model.to_json()).unwrap();
        let mut reader = 0.0;
        let mut stature_only = 0.0;
        let empty = ProportionStats::default();
        for s in &test {
            let p = model.predict(s.stature_m as f32, None, &s.stats);
            let q = model.predict(s.stature_m as f32, None, &empty);
            let r = reparsed.predict(s.stature_m as f32, Some(s.sex), &s.stats);
            let direct = model.predict(s.stature_m as f32, Some(s.sex), &s.stats);
            assert!(r.iter().zip(&direct).all(|(a, b)| (a - b).abs() < 1e-6));
            reader += f64::from((p[1] - s.lengths[1]).abs());
            stature_only += f64::from((q[1] - s.lengths[1]).abs());
            // Bones that depend on the stature alone come out exactly.
            assert!(
                (p[8] - s.lengths[8]).abs() < 2e-3,
                "{} vs {}",
                p[8],
                s.lengths[8]
            );
        }
        assert!(
            reader < 0.3 * stature_only,
            "thigh error {reader} with the video, {stature_only} without"
        );
    }

    #[test]
    fn the_estimator_reads_each_trial_with_its_subjects_stature() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(9);
        let train: Vec<FitSample> = (0..200)
            .map(|i| FitSample {
                stature_m: 1.5 + 0.002 * f64::from(i),
                sex: if i % 2 == 0 { Sex::Female } else { Sex::Male },
                stats: clip(rng.random_range(0.2f32..0.4), &mut rng),
                lengths: [0.1 + 0.001 * i as f32; NUM_BONES],
            })
            .collect();
        let model = fit(&train, "test".into()).unwrap();
        let frames: Vec<f32> = (0..3 * 34).map(|v| (v as f32 * 0.37).sin()).collect();
        let trial = |subject: &str| EvalSequence {
            subject: subject.into(),
            sequence: "Walking".into(),
            camera: "c".into(),
            input: frames.clone(),
            gt: [0.2; NUM_BONES],
        };
        let estimator = ReaderEstimator {
            model: model.clone(),
            statures: [("S9".to_string(), 1.8f32)].into_iter().collect(),
        };
        let out = estimator.estimate(&[trial("S9")]).unwrap();
        let expected = model.predict(1.8, None, &ProportionStats::of_frames(&frames));
        assert_eq!(out[0].lengths, expected);
        assert!(estimator.estimate(&[trial("S11")]).is_err());
    }

    #[test]
    fn too_few_bodies_are_an_error_not_a_fit() {
        let s = FitSample {
            stature_m: 1.7,
            sex: Sex::Male,
            stats: ProportionStats::default(),
            lengths: [0.2; NUM_BONES],
        };
        assert!(fit(&[s], "x".into()).is_err());
    }
}

//! Bone-length sampling strategies: what lengths the synthetic training
//! sequences are rebuilt with.
//!
//! The model learns to read a person's bone lengths from 2D motion, so the
//! distribution of lengths it is trained on is its prior. The paper compares
//! four strategies, all available here ([`LengthStrategy`]):
//!
//! - `true`: each sequence keeps its subject's own lengths (only 5 distinct
//!   skeletons: the model can memorise them);
//! - `uniform`: every bone independently `x U(0.7, 1.3)` of the training
//!   mean (Chen et al.), then each symmetric pair made equal (the pair shares
//!   one draw, so left and right stay equal as in a real body);
//! - `normal`: every bone `N(mean, std)` with the training subjects' per-bone
//!   std, one draw per symmetric pair, bones independent;
//! - `ansur`: a random person of the ANSUR II survey mapped to the 16 bones
//!   and mean-aligned to the training subjects ([`crate::ansur`]), which keeps
//!   the natural correlations between bones.
//!
//! **No test statistics.** Every statistic is computed by
//! [`TrainingLengthStats::from_training`] from the lengths of the training
//! subjects handed to it, and the data loader only ever hands it S1 S5 S6 S7
//! S8 ([`crate::dataset::TRAIN_SUBJECTS`]). Nothing in this module can see a
//! test subject.

use blapose_core::bones::average_symmetric_pairs;
use blapose_core::skeleton::{NUM_BONES, SYMMETRIC_BONE_PAIRS};
use blapose_core::BoneLengths;
use rand::Rng;
use rand_distr::{Distribution, Normal, StandardNormal};
use serde::{Deserialize, Serialize};

use crate::ansur::AnsurPopulation;
use crate::error::TrainError;
pub use crate::training_lengths::{TrainingLengthStats, FIXED_BONE_STD};

/// Which lengths the synthetic sequences are rebuilt with (`--lengths`;
/// the same spelling in a run's configuration).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum LengthStrategy {
    /// The subject's own lengths.
    True,
    /// `x U(0.7, 1.3)` of the training mean per bone, symmetric pairs shared.
    Uniform,
    /// `N(mean, std)` of the training subjects per bone, pairs shared.
    Normal,
    /// A random ANSUR II person, mapped and mean-aligned.
    Ansur,
}

impl LengthStrategy {
    /// All strategies, in the order of the paper's ablation.
    pub const ALL: [LengthStrategy; 4] = [Self::True, Self::Uniform, Self::Normal, Self::Ansur];

    /// The flag spelling (`true|uniform|normal|ansur`).
    pub fn name(self) -> &'static str {
        match self {
            Self::True => "true",
            Self::Uniform => "uniform",
            Self::Normal => "normal",
            Self::Ansur => "ansur",
        }
    }
}

impl std::fmt::Display for LengthStrategy {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// Draws bone lengths for synthetic sequences.
#[derive(Debug, Clone)]
pub struct LengthSampler {
    strategy: LengthStrategy,
    stats: TrainingLengthStats,
    ansur: Option<AnsurPopulation>,
}

/// For each bone, the bone whose draw it shares: the right bone of a
/// symmetric pair for its left partner, itself otherwise.
fn draw_owner(bone: usize) -> usize {
    SYMMETRIC_BONE_PAIRS
        .iter()
        .find(|&&(_, l)| l == bone)
        .map_or(bone, |&(r, _)| r)
}

impl LengthSampler {
    /// A sampler for `strategy`. `ansur` must be given for
    /// [`LengthStrategy::Ansur`] (it is already aligned to `stats`).
    pub fn new(
        strategy: LengthStrategy,
        stats: TrainingLengthStats,
        ansur: Option<AnsurPopulation>,
    ) -> Result<Self, TrainError> {
        if strategy == LengthStrategy::Ansur && ansur.as_ref().is_none_or(|a| a.is_empty()) {
            return Err(TrainError::InvalidArgument(
                "the ansur strategy needs a calibrated ANSUR population".into(),
            ));
        }
        Ok(Self {
            strategy,
            stats,
            ansur,
        })
    }

    /// The strategy.
    pub fn strategy(&self) -> LengthStrategy {
        self.strategy
    }

    /// The training statistics the sampler is centred on.
    pub fn stats(&self) -> &TrainingLengthStats {
        &self.stats
    }

    /// Draw the lengths for one sequence whose subject's own lengths are
    /// `subject`. Always symmetric; never non-positive.
    pub fn sample<R: Rng + ?Sized>(&self, subject: &BoneLengths, rng: &mut R) -> BoneLengths {
        let mean = &self.stats.mean;
        let out = match self.strategy {
            LengthStrategy::True => {
                let mut l = *subject;
                average_symmetric_pairs(&mut l);
                l
            }
            LengthStrategy::Uniform => {
                // One draw per bone, then each left bone takes its right
                // partner's draw (draws first: a left bone may precede its
                // partner in bone order).
                let draw: [f32; NUM_BONES] =
                    std::array::from_fn(|_| rng.random_range(0.7f32..1.3f32));
                std::array::from_fn(|b| mean[b] * draw[draw_owner(b)])
            }
            LengthStrategy::Normal => {
                let z: [f32; NUM_BONES] = std::array::from_fn(|_| StandardNormal.sample(rng));
                std::array::from_fn(|b| mean[b] + self.stats.std[b] * z[draw_owner(b)])
            }
            LengthStrategy::Ansur => match &self.ansur {
                Some(pop) => pop.person(rng.random_range(0..pop.len())),
                None => *mean,
            },
        };
        self.bounded(out)
    }

    /// A drawn body made valid: a bone the training subjects all share
    /// stays fixed whatever the strategy draws for it (except `uniform`,
    /// which is defined as independent +-30% on every bone), and no bone
    /// falls below 30% of its mean (normal tails).
    fn bounded(&self, mut out: BoneLengths) -> BoneLengths {
        let mean = &self.stats.mean;
        for (b, l) in out.iter_mut().enumerate() {
            if self.strategy != LengthStrategy::Uniform && self.stats.is_fixed(b) {
                *l = mean[b];
            }
            *l = l.max(0.3 * mean[b]);
        }
        out
    }
}

/// A standard normal draw for callers that need one without naming
/// rand_distr (used by the synthesizer for the 3D shift).
pub fn normal_f32<R: Rng + ?Sized>(rng: &mut R, std: f32) -> f32 {
    Normal::new(0.0f32, std.max(0.0))
        .map(|n| n.sample(rng))
        .unwrap_or(0.0)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    fn stats() -> TrainingLengthStats {
        let a: BoneLengths = [
            0.13, 0.44, 0.45, 0.13, 0.44, 0.45, 0.23, 0.25, 0.12, 0.115, 0.15, 0.28, 0.25, 0.15,
            0.28, 0.25,
        ];
        let mut b = a.map(|v| v * 1.05);
        b[9] = 0.115;
        TrainingLengthStats::from_training(&[a, b]).unwrap()
    }

    #[test]
    fn strategies_are_symmetric_and_bounded() {
        let s = stats();
        for strategy in [
            LengthStrategy::True,
            LengthStrategy::Uniform,
            LengthStrategy::Normal,
        ] {
            let sampler = LengthSampler::new(strategy, s.clone(), None).unwrap();
            let mut rng = rand::rngs::StdRng::seed_from_u64(7);
            for _ in 0..500 {
                let l = sampler.sample(&s.mean, &mut rng);
                for &(r, le) in &SYMMETRIC_BONE_PAIRS {
                    assert_eq!(l[r], l[le], "{strategy}");
                }
                for b in 0..NUM_BONES {
                    assert!(
                        l[b] >= 0.3 * s.mean[b] && l[b] <= 1.3 * s.mean[b] + 1e-6,
                        "{strategy} bone {b}: {}",
                        l[b]
                    );
                }
                if strategy != LengthStrategy::Uniform {
                    assert_eq!(l[9], 0.115, "fixed bone stays fixed");
                }
            }
        }
    }

    #[test]
    fn uniform_covers_its_range() {
        let s = stats();
        let sampler = LengthSampler::new(LengthStrategy::Uniform, s.clone(), None).unwrap();
        let mut rng = rand::rngs::StdRng::seed_from_u64(1);
        let ratios: Vec<f32> = (0..2000)
            .map(|_| sampler.sample(&s.mean, &mut rng)[1] / s.mean[1])
            .collect();
        let lo = ratios.iter().cloned().fold(f32::MAX, f32::min);
        let hi = ratios.iter().cloned().fold(f32::MIN, f32::max);
        assert!((0.7..0.72).contains(&lo), "{lo}");
        assert!(hi < 1.3 && hi > 1.28, "{hi}");
    }

    #[test]
    fn ansur_needs_a_population() {
        assert!(LengthSampler::new(LengthStrategy::Ansur, stats(), None).is_err());
    }

    #[test]
    fn flag_config_and_display_spellings_agree() {
        use clap::ValueEnum;
        for k in LengthStrategy::ALL {
            let flag = k.to_possible_value().unwrap();
            assert_eq!(flag.get_name(), k.name());
            assert_eq!(serde_json::to_value(k).unwrap(), k.name());
            assert_eq!(k.to_string(), k.name());
        }
        assert!(LengthStrategy::from_str("bogus", false).is_err());
    }
}

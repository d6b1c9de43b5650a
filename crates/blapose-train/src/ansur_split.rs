//! The fixed held-out split of ANSUR II people: the bodies of the
//! many-bodies benchmark (`blapose-lab bodies`), which training never draws.
//!
//! Why: a benchmark that asks "does the model read *this* person's size"
//! is only honest on people the model was never trained to output. The
//! split is a pure function of the survey's own subject id and sex
//! ([`is_held_out`]): a seeded splitmix64 hash, one person in
//! [`HELD_OUT_ONE_IN`] of each sex (about 10 %: ~410 men and ~200 women of
//! 4,082 and 1,986), so it does not depend on file order, on which people
//! the mapping skips, or on anything a training run chooses.
//!
//! `--ansur-people train` (the default, [`AnsurPeople::Train`]) removes the
//! held-out people from the population training draws from;
//! [`AnsurPeople::All`] keeps everyone, the behaviour every shipped weight
//! file was trained with (their `train_config` predates the option and
//! reads as `all`).
//!
//! **Calibration is unchanged.** The per-bone scale factors
//! ([`AnsurPopulation::calibrate`]) are still computed over the whole
//! survey, exactly as before, and held-out people are removed *after*
//! calibration: so `all` is bit-identical to the old code, the benchmark's
//! bodies are in the same units as the training population, and the only
//! thing the held-out people contribute to training is one mean per bone
//! of their raw landmark measurements (about 10 % of 6,068 people's
//! weight in a unit conversion), never a length target.

use blapose_core::BoneLengths;
use blapose_data::ansur::{AnsurTable, Sex};
use serde::{Deserialize, Serialize};

use crate::ansur::{raw_lengths, required_columns, AnsurPopulation};
use crate::error::TrainError;
use crate::lengths::TrainingLengthStats;

/// One person in this many (per sex, by hash) is held out.
pub const HELD_OUT_ONE_IN: u64 = 10;
/// Seed of the split's hash (fixed forever: changing it changes the
/// benchmark's people).
pub const SPLIT_SEED: u64 = 0x00B0_D1E5_2026;

/// Which ANSUR people training draws from (`--ansur-people`; the same
/// spelling in a run's configuration).
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, Hash, Default, Serialize, Deserialize, clap::ValueEnum,
)]
#[serde(rename_all = "lowercase")]
pub enum AnsurPeople {
    /// Everyone but the held-out split ([`is_held_out`]).
    #[default]
    Train,
    /// Everyone (the shipped weights' recipe, before the split existed).
    All,
}

impl AnsurPeople {
    /// The flag spelling.
    pub fn name(self) -> &'static str {
        match self {
            Self::Train => "train",
            Self::All => "all",
        }
    }

    /// The value a configuration written before the option reads as.
    pub fn before_the_split() -> Self {
        Self::All
    }
}

impl std::fmt::Display for AnsurPeople {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// splitmix64 of `x`.
fn splitmix(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// The split's hash of one survey person.
fn person_hash(subject_id: u64, sex: Sex) -> u64 {
    let sex_salt = match sex {
        Sex::Male => 1,
        Sex::Female => 2,
    };
    splitmix(SPLIT_SEED ^ splitmix(subject_id.wrapping_mul(4).wrapping_add(sex_salt)))
}

/// Whether the survey person `subject_id` of `sex` is in the held-out split.
pub fn is_held_out(subject_id: u64, sex: Sex) -> bool {
    person_hash(subject_id, sex).is_multiple_of(HELD_OUT_ONE_IN)
}

/// One surveyed person: id, sex, measured stature and calibrated lengths.
#[derive(Debug, Clone, PartialEq)]
pub struct Person {
    /// The survey's subject id.
    pub subject_id: u64,
    /// Sex.
    pub sex: Sex,
    /// Measured stature (the survey's `stature`, metres): the input of the
    /// stature regression ([`crate::stature`]).
    pub stature_m: f32,
    /// Calibrated bone lengths (metres).
    pub lengths: BoneLengths,
}

/// The calibrated survey, split.
#[derive(Debug, Clone)]
pub struct AnsurSplit {
    /// Everyone, calibrated, in file order (people whose landmarks give a
    /// non-positive bone are left out, as before).
    pub everyone: Vec<Person>,
    /// The calibration (per-bone factors over everyone, as before).
    pub calibrated: AnsurPopulation,
}

impl AnsurSplit {
    /// Map and calibrate every person of `table` to `training`.
    pub fn from_table(
        table: &AnsurTable,
        training: &TrainingLengthStats,
    ) -> Result<Self, TrainError> {
        for c in required_columns() {
            if table.column_index(c).is_none() {
                return Err(TrainError::Ansur(format!("the survey has no column {c:?}")));
            }
        }
        let mut ids = Vec::with_capacity(table.records.len());
        let mut raw = Vec::with_capacity(table.records.len());
        for r in &table.records {
            if let Ok(l) = raw_lengths(|c| table.value(r, c).map(f64::from)) {
                // The mapping reads `stature` (neck bone), so a person it
                // keeps has one.
                let stature_mm = table.value(r, "stature").unwrap_or(f32::NAN);
                ids.push((r.subject_id, r.sex, (f64::from(stature_mm) / 1000.0) as f32));
                raw.push(l);
            }
        }
        let calibrated = AnsurPopulation::calibrate(&raw, training)?;
        let everyone = ids
            .into_iter()
            .zip(calibrated.people())
            .map(|((subject_id, sex, stature_m), &lengths)| Person {
                subject_id,
                sex,
                stature_m,
                lengths,
            })
            .collect();
        Ok(Self {
            everyone,
            calibrated,
        })
    }

    /// Load both CSVs under `root` and calibrate.
    pub fn load(
        root: &std::path::Path,
        training: &TrainingLengthStats,
    ) -> Result<Self, TrainError> {
        Self::from_table(&blapose_data::ansur::load_ansur(root)?, training)
    }

    /// The held-out people, ordered by the split's hash (a fixed shuffle
    /// that mixes the sexes, so the first `n` of them are a fair subset).
    pub fn held_out(&self) -> Vec<&Person> {
        let mut out: Vec<&Person> = self
            .everyone
            .iter()
            .filter(|p| is_held_out(p.subject_id, p.sex))
            .collect();
        out.sort_by_key(|p| (person_hash(p.subject_id, p.sex), p.subject_id));
        out
    }

    /// The population training draws from: everyone for
    /// [`AnsurPeople::All`] (exactly [`crate::ansur::load_population`]),
    /// everyone but the held-out people for [`AnsurPeople::Train`]. Same
    /// calibration either way (see the module docs).
    pub fn training_population(&self, people: AnsurPeople) -> Result<AnsurPopulation, TrainError> {
        match people {
            AnsurPeople::All => Ok(self.calibrated.clone()),
            AnsurPeople::Train => {
                let keep: Vec<bool> = self
                    .everyone
                    .iter()
                    .map(|p| !is_held_out(p.subject_id, p.sex))
                    .collect();
                self.calibrated.retained(&keep)
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn about_one_in_ten_of_each_sex_deterministically() {
        for sex in [Sex::Male, Sex::Female] {
            let n = (0..20_000u64).filter(|&id| is_held_out(id, sex)).count();
            assert!((1_700..2_300).contains(&n), "{sex:?}: {n}");
            let again = (0..20_000u64).filter(|&id| is_held_out(id, sex)).count();
            assert_eq!(n, again);
        }
        // Sex is part of the key: the two sexes' splits differ.
        let differ = (0..1000u64)
            .filter(|&id| is_held_out(id, Sex::Male) != is_held_out(id, Sex::Female))
            .count();
        assert!(differ > 50, "{differ}");
    }

    #[test]
    fn flag_config_and_display_spellings_agree() {
        use clap::ValueEnum;
        for k in AnsurPeople::value_variants() {
            assert_eq!(k.to_possible_value().unwrap().get_name(), k.name());
            assert_eq!(serde_json::to_value(k).unwrap(), k.name());
            assert_eq!(k.to_string(), k.name());
        }
        assert_eq!(AnsurPeople::default(), AnsurPeople::Train);
    }
}

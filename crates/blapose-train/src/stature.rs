//! The stature regression: the pure anthropometric answer to "how long are
//! this person's bones, given their height (and sex)?".
//!
//! Why: a user who knows the person's stature already knows most of their
//! absolute size (a body of size L at distance Z through a lens of focal
//! f appears as f·L/Z, so uncalibrated 2D shows proportions, not size);
//! what the 2D stream can add is the *proportions* given that height. So a model that
//! takes the height as input is only worth shipping if it beats the answer
//! that ignores the video altogether: an ordinary least-squares line per
//! bone, `length_b = a_b + s_b * stature`, fitted over the survey. With sex
//! given, each sex gets its own line (its own intercept and slope per bone).
//! `blapose fit-stature` writes it as the file the server answers a known
//! stature with (`models/stature_regression.json`,
//! [`blapose_model::stature`]); the many-bodies benchmark (`blapose-lab
//! bodies`) scores it beside the networks.
//!
//! **Fitted on the training split only.** [`StatureRegression::fit_training`]
//! fits on the ANSUR people outside the held-out split
//! ([`crate::ansur_split::is_held_out`]), the same people training draws
//! from by default; the benchmark's individuals never enter the fit (their
//! ids are absent from [`StatureRegression::fitted_on`], and changing their
//! lengths leaves the fit bit for bit unchanged: tested). The targets are
//! the calibrated lengths ([`crate::ansur`], the survey's own spread), the
//! same units as the benchmark's truth; the input is the survey's measured
//! stature.
//!
//! Degenerate input (fewer than two people, no spread in stature, a
//! non-finite value, a non-positive stature to predict from, a sex with no
//! fit) is a [`StatureError`], never a panic.

use blapose_core::skeleton::NUM_BONES;
use blapose_core::BoneLengths;
use blapose_data::ansur::Sex;
use blapose_model::stature::{StatureLines, StatureModel, STATURE_FORMAT};

use crate::ansur_split::{is_held_out, Person};

pub use crate::error::StatureError;

/// Which inputs the regression reads.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StatureInput {
    /// Stature only: one line per bone over everyone.
    Height,
    /// Stature and sex: one line per bone and sex.
    HeightSex,
}

impl StatureInput {
    /// Both: stature alone first.
    pub const ALL: [Self; 2] = [Self::Height, Self::HeightSex];
}

fn sex_name(sex: Sex) -> &'static str {
    match sex {
        Sex::Male => "male",
        Sex::Female => "female",
    }
}

/// One least-squares line per bone: `length = intercept + slope * stature`
/// (metres).
#[derive(Debug, Clone, PartialEq)]
pub struct LinearFit {
    /// Per bone, metres.
    pub intercept: [f64; NUM_BONES],
    /// Per bone, metres of bone per metre of stature.
    pub slope: [f64; NUM_BONES],
    /// People the line was fitted on.
    pub people: usize,
}

impl LinearFit {
    /// Ordinary least squares of each bone on stature over `people`
    /// (`(stature_m, lengths)`); `group` names them in errors.
    pub fn fit(group: &'static str, people: &[(f64, BoneLengths)]) -> Result<Self, StatureError> {
        let n = people.len();
        if n < 2 {
            return Err(StatureError::TooFewPeople { group, people: n });
        }
        let nf = n as f64;
        let mx = people.iter().map(|(x, _)| x).sum::<f64>() / nf;
        let sxx: f64 = people.iter().map(|(x, _)| (x - mx).powi(2)).sum();
        if !(sxx > 0.0 && sxx.is_finite()) {
            return Err(StatureError::NoStatureSpread { group });
        }
        let mut intercept = [0.0; NUM_BONES];
        let mut slope = [0.0; NUM_BONES];
        for b in 0..NUM_BONES {
            let my = people.iter().map(|(_, l)| f64::from(l[b])).sum::<f64>() / nf;
            let sxy: f64 = people
                .iter()
                .map(|(x, l)| (x - mx) * (f64::from(l[b]) - my))
                .sum();
            slope[b] = sxy / sxx;
            intercept[b] = my - slope[b] * mx;
        }
        Ok(Self {
            intercept,
            slope,
            people: n,
        })
    }

    /// The lengths of someone `stature_m` tall.
    pub fn predict(&self, stature_m: f64) -> Result<BoneLengths, StatureError> {
        if !(stature_m.is_finite() && stature_m > 0.0) {
            return Err(StatureError::BadStature(stature_m));
        }
        Ok(std::array::from_fn(|b| {
            (self.intercept[b] + self.slope[b] * stature_m) as f32
        }))
    }
}

impl From<&LinearFit> for StatureLines {
    /// The served form of a fitted line.
    fn from(fit: &LinearFit) -> Self {
        StatureLines {
            intercept: fit.intercept.to_vec(),
            slope: fit.slope.to_vec(),
            people: fit.people,
        }
    }
}

/// The fitted regression: one line per bone over everyone, and one per
/// bone and sex.
#[derive(Debug, Clone, PartialEq)]
pub struct StatureRegression {
    /// Over everyone (input `height`).
    pub pooled: LinearFit,
    /// Men only (`None`: fewer than two, or no spread).
    pub male: Option<LinearFit>,
    /// Women only (`None`: fewer than two, or no spread).
    pub female: Option<LinearFit>,
    /// `(subject id, sex)` of every person fitted on, in input order.
    pub fitted_on: Vec<(u64, Sex)>,
}

impl StatureRegression {
    /// Fit on exactly `people` (use [`Self::fit_training`] for the
    /// benchmark: it leaves the held-out split out).
    pub fn fit<'a>(people: impl IntoIterator<Item = &'a Person>) -> Result<Self, StatureError> {
        let mut all = Vec::new();
        let mut male = Vec::new();
        let mut female = Vec::new();
        let mut fitted_on = Vec::new();
        for p in people {
            let x = f64::from(p.stature_m);
            if !x.is_finite() || p.lengths.iter().any(|l| !l.is_finite()) {
                return Err(StatureError::NonFinite {
                    subject_id: p.subject_id,
                });
            }
            all.push((x, p.lengths));
            match p.sex {
                Sex::Male => male.push((x, p.lengths)),
                Sex::Female => female.push((x, p.lengths)),
            }
            fitted_on.push((p.subject_id, p.sex));
        }
        Ok(Self {
            pooled: LinearFit::fit("everyone", &all)?,
            male: LinearFit::fit("male", &male).ok(),
            female: LinearFit::fit("female", &female).ok(),
            fitted_on,
        })
    }

    /// Fit on the ANSUR training split: every person of `everyone` (e.g.
    /// [`crate::ansur_split::AnsurSplit::everyone`]) outside the held-out
    /// split.
    pub fn fit_training(everyone: &[Person]) -> Result<Self, StatureError> {
        Self::fit(
            everyone
                .iter()
                .filter(|p| !is_held_out(p.subject_id, p.sex)),
        )
    }

    /// The line a prediction with `input` uses for someone of `sex`.
    fn line(&self, input: StatureInput, sex: Sex) -> Result<&LinearFit, StatureError> {
        match input {
            StatureInput::Height => Ok(&self.pooled),
            StatureInput::HeightSex => match sex {
                Sex::Male => self.male.as_ref(),
                Sex::Female => self.female.as_ref(),
            }
            .ok_or(StatureError::NoFitForSex(sex_name(sex))),
        }
    }

    /// The served form ([`blapose_model::stature::StatureModel`], written by
    /// `blapose fit-stature`); both sexes must have a fit.
    pub fn to_model(&self, source: &str) -> Result<StatureModel, StatureError> {
        let lines = StatureLines::from;
        let female = self
            .female
            .as_ref()
            .ok_or(StatureError::NoFitForSex("female"))?;
        let male = self
            .male
            .as_ref()
            .ok_or(StatureError::NoFitForSex("male"))?;
        Ok(StatureModel {
            format: STATURE_FORMAT.into(),
            source: source.into(),
            pooled: lines(&self.pooled),
            female: lines(female),
            male: lines(male),
        })
    }

    /// The lengths of someone `stature_m` tall; `sex` is read only by
    /// [`StatureInput::HeightSex`].
    pub fn predict(
        &self,
        input: StatureInput,
        stature_m: f64,
        sex: Sex,
    ) -> Result<BoneLengths, StatureError> {
        self.line(input, sex)?.predict(stature_m)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A known relation: bone b = 0.02 * b + (0.1 + 0.01 * b) * stature,
    /// with a sex offset on the intercept and slope.
    fn truth(b: usize, stature: f64, sex: Sex) -> f64 {
        let (da, ds) = match sex {
            Sex::Male => (0.0, 0.0),
            Sex::Female => (0.03, -0.02),
        };
        0.02 * b as f64 + da + (0.1 + 0.01 * b as f64 + ds) * stature
    }

    fn person(id: u64, sex: Sex, stature: f64) -> Person {
        Person {
            subject_id: id,
            sex,
            stature_m: stature as f32,
            lengths: std::array::from_fn(|b| truth(b, f64::from(stature as f32), sex) as f32),
        }
    }

    fn people(n: u64) -> Vec<Person> {
        (0..n)
            .map(|i| {
                let sex = if i % 3 == 0 { Sex::Female } else { Sex::Male };
                person(i, sex, 1.45 + 0.5 * ((i * 37) % 101) as f64 / 100.0)
            })
            .collect()
    }

    #[test]
    fn recovers_a_known_linear_relation_per_sex() {
        let ps = people(300);
        let r = StatureRegression::fit(&ps).unwrap();
        for (sex, fit) in [(Sex::Male, &r.male), (Sex::Female, &r.female)] {
            let fit = fit.as_ref().unwrap();
            for b in 0..NUM_BONES {
                let a = truth(b, 0.0, sex);
                let s = truth(b, 1.0, sex) - a;
                assert!((fit.intercept[b] - a).abs() < 1e-5, "{sex:?} bone {b}");
                assert!((fit.slope[b] - s).abs() < 1e-5, "{sex:?} bone {b}");
            }
            let p = r.predict(StatureInput::HeightSex, 1.8, sex).unwrap();
            for b in 0..NUM_BONES {
                assert!((f64::from(p[b]) - truth(b, 1.8, sex)).abs() < 1e-5);
            }
        }
        assert_eq!(r.male.as_ref().unwrap().people, 200);
        assert_eq!(r.female.as_ref().unwrap().people, 100);
        assert_eq!(r.pooled.people, 300);
        // Pooled over one sex only, the pooled line is that sex's line.
        let men: Vec<Person> = ps.into_iter().filter(|p| p.sex == Sex::Male).collect();
        let m = StatureRegression::fit(&men).unwrap();
        for b in 0..NUM_BONES {
            assert!(
                (m.pooled.slope[b] - (truth(b, 1.0, Sex::Male) - truth(b, 0.0, Sex::Male))).abs()
                    < 1e-5
            );
        }
        // ...and a sex with nobody has no fit: an error, not a panic.
        assert_eq!(
            m.predict(StatureInput::HeightSex, 1.7, Sex::Female),
            Err(StatureError::NoFitForSex("female"))
        );
        assert!(m.predict(StatureInput::Height, 1.7, Sex::Female).is_ok());
    }

    #[test]
    fn degenerate_inputs_are_errors_not_panics() {
        assert!(matches!(
            StatureRegression::fit(&[]),
            Err(StatureError::TooFewPeople { people: 0, .. })
        ));
        let one = [person(1, Sex::Male, 1.7)];
        assert!(matches!(
            StatureRegression::fit(&one),
            Err(StatureError::TooFewPeople { people: 1, .. })
        ));
        let same = [person(1, Sex::Male, 1.7), person(2, Sex::Female, 1.7)];
        assert!(matches!(
            StatureRegression::fit(&same),
            Err(StatureError::NoStatureSpread { .. })
        ));
        let mut nan = people(10);
        nan[3].stature_m = f32::NAN;
        assert_eq!(
            StatureRegression::fit(&nan),
            Err(StatureError::NonFinite { subject_id: 3 })
        );
        let mut inf = people(10);
        inf[4].lengths[2] = f32::INFINITY;
        assert!(StatureRegression::fit(&inf).is_err());
        let r = StatureRegression::fit(&people(10)).unwrap();
        for bad in [0.0, -1.7, f64::NAN, f64::INFINITY] {
            assert!(r.predict(StatureInput::Height, bad, Sex::Male).is_err());
        }
    }

    #[test]
    fn fitted_on_the_training_split_only() {
        let ps = people(3000);
        let held: Vec<usize> = (0..ps.len())
            .filter(|&i| is_held_out(ps[i].subject_id, ps[i].sex))
            .collect();
        assert!(held.len() > 100, "{}", held.len());
        let r = StatureRegression::fit_training(&ps).unwrap();
        assert_eq!(r.fitted_on.len(), ps.len() - held.len());
        assert!(r.fitted_on.iter().all(|&(id, sex)| !is_held_out(id, sex)));
        // Changing every held-out person's body changes nothing...
        let mut moved = ps.clone();
        for &i in &held {
            moved[i].lengths = moved[i].lengths.map(|l| l * 3.0);
            moved[i].stature_m *= 0.5;
        }
        assert_eq!(StatureRegression::fit_training(&moved).unwrap(), r);
        // ...changing one training person's body does.
        let i = (0..ps.len()).find(|i| !held.contains(i)).unwrap();
        moved[i].lengths[1] += 0.05;
        assert_ne!(StatureRegression::fit_training(&moved).unwrap(), r);
    }
}

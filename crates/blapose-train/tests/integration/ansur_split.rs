//! The held-out ANSUR II split on the real data (skipped when
//! ../shared/data is absent): both sexes, at least 500 people,
//! deterministic, never drawn by training, never in the stature
//! regression's fit.

use std::collections::HashSet;
use std::path::PathBuf;
use std::sync::OnceLock;

use blapose_core::skeleton::NUM_BONES;
use blapose_core::BoneLengths;
use blapose_data::ansur::Sex;
use blapose_data::test_data_root;
use blapose_train::ansur::load_population;
use blapose_train::ansur_split::{is_held_out, AnsurPeople, AnsurSplit};
use blapose_train::dataset::TrainingSet;
use blapose_train::lengths::{LengthSampler, LengthStrategy, TrainingLengthStats};
use blapose_train::stature::StatureRegression;
use rand::SeedableRng;

struct Fixture {
    root: PathBuf,
    stats: TrainingLengthStats,
    split: AnsurSplit,
}

fn fixture() -> Option<&'static Fixture> {
    static F: OnceLock<Option<Fixture>> = OnceLock::new();
    F.get_or_init(|| {
        let root = test_data_root("h36m/poses_3d.npz", "held-out split tests")?;
        test_data_root("ansur2/ANSUR_II_MALE_Public.csv", "held-out split tests")?;
        let set = TrainingSet::load(&root).expect("training set loads");
        let stats = TrainingLengthStats::from_training(&set.lengths_list()).unwrap();
        let split = AnsurSplit::load(&root, &stats).unwrap();
        Some(Fixture { root, stats, split })
    })
    .as_ref()
}

fn key(l: &BoneLengths) -> [u32; NUM_BONES] {
    l.map(f32::to_bits)
}

#[test]
fn the_split_has_both_sexes_500_people_and_is_deterministic() {
    let Some(f) = fixture() else { return };
    let held = f.split.held_out();
    let male = held.iter().filter(|p| p.sex == Sex::Male).count();
    let female = held.len() - male;
    assert!(held.len() >= 500, "{} held out", held.len());
    assert!(male >= 300 && female >= 150, "{male} male, {female} female");
    // Each sex about one in ten.
    for sex in [Sex::Male, Sex::Female] {
        let all = f.split.everyone.iter().filter(|p| p.sex == sex).count();
        let out = held.iter().filter(|p| p.sex == sex).count();
        let share = out as f64 / all as f64;
        assert!((0.08..0.12).contains(&share), "{sex:?}: {share}");
    }
    // Loading again gives the same people in the same order.
    let again = AnsurSplit::load(&f.root, &f.stats).unwrap();
    let ids = |s: &AnsurSplit| {
        s.held_out()
            .iter()
            .map(|p| (p.subject_id, p.sex == Sex::Male))
            .collect::<Vec<_>>()
    };
    assert_eq!(ids(&again), ids(&f.split));
    // Subject ids are unique within a sex, so (id, sex) names one person.
    let mut seen = HashSet::new();
    for p in &f.split.everyone {
        assert!(seen.insert((p.subject_id, p.sex == Sex::Male)));
    }
}

#[test]
fn the_stature_regression_is_fitted_on_the_training_split_only() {
    let Some(f) = fixture() else { return };
    let r = StatureRegression::fit_training(&f.split.everyone).unwrap();
    let held: HashSet<(u64, bool)> = f
        .split
        .held_out()
        .iter()
        .map(|p| (p.subject_id, p.sex == Sex::Male))
        .collect();
    assert_eq!(r.fitted_on.len(), f.split.everyone.len() - held.len());
    assert!(r
        .fitted_on
        .iter()
        .all(|&(id, sex)| !held.contains(&(id, sex == Sex::Male))));
    // Moving every held-out body leaves the fit bit-identical.
    let mut moved = f.split.everyone.clone();
    for p in moved
        .iter_mut()
        .filter(|p| is_held_out(p.subject_id, p.sex))
    {
        p.lengths = p.lengths.map(|l| l * 2.0);
        p.stature_m += 0.3;
    }
    assert_eq!(StatureRegression::fit_training(&moved).unwrap(), r);
    // Statures are the survey's (metres, plausible) and both sexes fit.
    assert!(f
        .split
        .everyone
        .iter()
        .all(|p| (1.3..2.2).contains(&p.stature_m)));
    assert!(r.male.is_some() && r.female.is_some());
}

#[test]
fn training_never_draws_a_held_out_individual_by_default() {
    let Some(f) = fixture() else { return };
    let held: HashSet<[u32; NUM_BONES]> =
        f.split.held_out().iter().map(|p| key(&p.lengths)).collect();
    let kept: Vec<[u32; NUM_BONES]> = f
        .split
        .everyone
        .iter()
        .filter(|p| !is_held_out(p.subject_id, p.sex))
        .map(|p| key(&p.lengths))
        .collect();
    // No kept person happens to share a held-out body (else the checks
    // below could not tell them apart).
    assert!(kept.iter().all(|k| !held.contains(k)));

    let train = f.split.training_population(AnsurPeople::Train).unwrap();
    assert_eq!(
        train.len(),
        f.split.everyone.len() - f.split.held_out().len()
    );
    assert!(train.people().iter().all(|p| !held.contains(&key(p))));
    // Same calibration, so the held-out bodies are in the training units.
    let all = f.split.training_population(AnsurPeople::All).unwrap();
    assert_eq!(train.scale, all.scale);
    // `all` is exactly the population every shipped model was trained on.
    assert_eq!(all, load_population(&f.root, &f.stats).unwrap());
    assert!(held
        .iter()
        .all(|h| all.people().iter().any(|p| key(p) == *h)));

    // What the sampler draws (a population row, unchanged by the bounds):
    // over many draws, never a held-out body, and bodies of the kept people
    // do come up. (`--ansur-spread` then maps each drawn row affinely; it
    // cannot bring a removed person back.)
    let sampler = LengthSampler::new(LengthStrategy::Ansur, f.stats.clone(), Some(train)).unwrap();
    let kept: HashSet<[u32; NUM_BONES]> = kept.into_iter().collect();
    let mut rng = rand::rngs::StdRng::seed_from_u64(11);
    for _ in 0..20_000 {
        let l = sampler.sample(&f.stats.mean, &mut rng);
        assert!(!held.contains(&key(&l)), "drew a held-out body");
        assert!(kept.contains(&key(&l)), "drew a body of nobody");
    }
}

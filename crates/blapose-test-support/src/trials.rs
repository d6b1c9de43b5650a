//! Evaluation trials of random keypoints: the fixture the online
//! estimator's tests run (the trainer's against an independent network,
//! the lab's with the state restarted), one definition so both read the
//! same inputs for a seed.

use blapose_train::dataset::EvalSequence;
use rand::{Rng, SeedableRng};

/// Trials of `lens` frames each, every keypoint coordinate uniform in
/// `[-0.8, 0.8)` from `seed`; true lengths 0.2 m.
pub fn random_trials(seed: u64, lens: &[usize]) -> Vec<EvalSequence> {
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
    lens.iter()
        .map(|&n| EvalSequence {
            subject: "S9".into(),
            sequence: "Walking 1".into(),
            camera: "c".into(),
            input: (0..n * 34)
                .map(|_| rng.random_range(-0.8f32..0.8))
                .collect(),
            gt: [0.2; 16],
        })
        .collect()
}

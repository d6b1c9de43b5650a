//! The online GRU with its state restarted (`blapose-lab diagnose
//! --state-frames`) against an independent implementation of the same
//! network run on fresh segments.

#![allow(clippy::needless_range_loop)]

use blapose_lab::diagnose::state_frames;
use blapose_model::{LoadedWeights, ModelKind};
use blapose_test_support::trials::random_trials;
use blapose_train::eval::{GruEstimator, LengthEstimator};
use blapose_train::fastnet::FastNet;

#[test]
fn restarting_the_state_averages_the_predictions_of_fresh_segments() {
    let w = LoadedWeights::random(ModelKind::Gru, 5).unwrap();
    let net = FastNet::from_tensors(ModelKind::Gru, w.tensors()).unwrap();
    let est = state_frames(GruEstimator::new(&w).unwrap(), Some(4));
    let trials = random_trials(2, &[10, 4, 3]);
    let out = est.estimate(&trials).unwrap();
    let plain = GruEstimator::new(&w).unwrap().estimate(&trials).unwrap();
    for ((t, e), p) in trials.iter().zip(&out).zip(&plain) {
        let n = t.frames();
        // Segments of 4 frames, each run from a fresh state.
        let mut sums = [0.0f32; 16];
        for start in (0..n).step_by(4) {
            let len = 4.min(n - start);
            let per = net.predict_per_frame(&t.input[start * 34..(start + len) * 34], 1, len);
            for f in 0..len {
                for j in 0..16 {
                    sums[j] += per[f * 16 + j];
                }
            }
        }
        for j in 0..16 {
            assert!(
                (e.lengths[j] - sums[j] / n as f32).abs() < 1e-4,
                "segment means differ"
            );
        }
        if n > 4 {
            assert_ne!(e.lengths, p.lengths, "a restart changes a long trial");
        } else {
            assert_eq!(e.lengths, p.lengths, "a short trial never restarts");
        }
    }
    assert_eq!(
        state_frames(GruEstimator::new(&w).unwrap(), Some(0))
            .estimate(&trials)
            .unwrap()[0]
            .lengths,
        plain[0].lengths,
        "0 means never"
    );
}

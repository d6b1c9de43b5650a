//! Lifter data on the real Human3.6M files (skipped when ../shared/data is
//! absent): inputs and targets are frame-aligned, the targets are
//! root-relative camera-space poses of the subject.

use blapose_core::bones::bone_lengths;
use blapose_data::h36m::{H36m, Parts};
use blapose_data::test_data_root;
use blapose_train::lifter::data::lifter_sequences;

#[test]
fn s9_streams_are_aligned_root_relative_camera_space() {
    let Some(root) = test_data_root("h36m/detections_sh.npz", "lifter data test") else {
        return;
    };
    let h36m = H36m::load(&root, &["S9"], Parts::ALL).unwrap();
    let seqs = lifter_sequences(&h36m, &["S9"]).unwrap();
    assert!(seqs.len() > 50, "{} streams", seqs.len());
    for s in &seqs {
        assert_eq!(s.trial.frames(), s.frames());
        assert!(s.frames() > 0);
        for p in s.target.iter().step_by(97) {
            assert_eq!(p[0], [0.0; 3], "root-relative");
            let l = bone_lengths(p);
            for (b, (&got, &want)) in l.iter().zip(&s.trial.gt).enumerate() {
                assert!((got - want).abs() < 2e-3, "bone {b}: {got} vs {want}");
            }
        }
        // Camera space: y points down, the person is upright in every
        // camera, so the head is above (smaller y than) the pelvis in most frames.
        let up = s.target.iter().filter(|p| p[10][1] < 0.0).count();
        assert!(
            up * 10 > s.frames() * 7,
            "{} {}: head above pelvis in {up}/{} frames",
            s.trial.sequence,
            s.trial.camera,
            s.frames()
        );
        // The 2D input sees the same person: the head is above the pelvis on screen too.
        let up2 = (0..s.frames())
            .filter(|&t| s.trial.input[t * 34 + 21] < s.trial.input[t * 34 + 1])
            .count();
        assert!(
            up2 * 10 > s.frames() * 7,
            "{} {}: 2D head above pelvis in {up2}/{}",
            s.trial.sequence,
            s.trial.camera,
            s.frames()
        );
    }
}

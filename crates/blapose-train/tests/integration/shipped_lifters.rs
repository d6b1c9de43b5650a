//! The shipped lifter weights load and reproduce the model card's subset
//! numbers.
//!
//! `models/lifter_subset_check.json` is the `--json` output of
//! `blapose eval-adjust --every 20 --lifter-weights models/lifter_*.safetensors`
//! run from the repository root when the lifters are shipped: per lifter its
//! weights file and its MPJPE / P-MPJPE before and after adjustment with the
//! shipped GRU and Bi-GRU. This test repeats that evaluation on the same
//! S9/S11 subset (every 20th trial). Skips when the data or that file are
//! absent.

use std::path::Path;

use blapose_data::h36m::{H36m, Parts, TEST_SUBJECTS};
use blapose_model::ModelKind;
use blapose_train::eval_adjust::{evaluate_lifter, LengthEstimates, MethodReport};
use blapose_train::lifter::data::lifter_sequences;
use blapose_train::lifter::predict::StreamLifter;
use blapose_train::lifter::weights;

#[test]
fn shipped_lifters_reproduce_the_model_card() {
    let repo = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    let check = repo.join("models/lifter_subset_check.json");
    let Ok(text) = std::fs::read_to_string(&check) else {
        println!(
            "skipping shipped-lifter check: {} not found",
            check.display()
        );
        return;
    };
    let Some(root) = blapose_data::test_data_root("h36m/detections_sh.npz", "shipped-lifter check")
    else {
        return;
    };
    let spec: serde_json::Value = serde_json::from_str(&text).unwrap();
    let lifters = spec.as_object().expect("a JSON object of lifters");
    assert!(!lifters.is_empty());
    let h = H36m::load(&root, &TEST_SUBJECTS, Parts::ALL).unwrap();
    let trials: Vec<_> = lifter_sequences(&h, &TEST_SUBJECTS)
        .unwrap()
        .into_iter()
        .step_by(20)
        .collect();
    let models = repo.join("models");
    let gru =
        blapose_model::weights::load(models.join("bone_length_gru.safetensors"), ModelKind::Gru)
            .unwrap();
    let bigru = blapose_model::weights::load(
        models.join("bone_length_bigru.safetensors"),
        ModelKind::BiGru,
    )
    .unwrap();
    let estimates = LengthEstimates::compute(&trials, Some(&gru), Some(&bigru)).unwrap();
    for (name, card) in lifters {
        let file = card["weights"].as_str().expect("weights path");
        let lifter = weights::load(&repo.join(file)).expect("shipped lifter loads");
        let streams = StreamLifter::new(&lifter).unwrap();
        let lift = |s: &blapose_train::lifter::data::LifterSequence| streams.lift(&s.trial, true);
        let got = evaluate_lifter(&trials, &lift, estimates.adjusters()).unwrap();
        assert_eq!(
            got.trials as u64,
            card["trials"].as_u64().unwrap(),
            "{name}: subset"
        );
        let close = |what: &str, m: Option<&MethodReport>| {
            let want = &card[what];
            let m = m.unwrap_or_else(|| panic!("{name}: no {what}"));
            for (key, value) in [
                ("mpjpe_mm", m.avg.mpjpe_mm),
                ("p_mpjpe_mm", m.avg.p_mpjpe_mm),
            ] {
                let expected = want[key].as_f64().unwrap();
                assert!(
                    (value - expected).abs() < 0.05,
                    "{name} {what} {key}: {value:.3} mm, the model card says {expected:.3}"
                );
            }
        };
        close("before", Some(&got.before));
        close("gru", got.gru.as_ref());
        close("bigru", got.bigru.as_ref());
    }
}

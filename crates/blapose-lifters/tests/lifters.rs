//! The lifters against the facts of their reference implementations:
//! exact parameter counts, reference tensor names, output shapes, the
//! equivalence of VideoPose3D's two evaluation forms and the causality of
//! its causal variant.
//!
//! The full-size models are built once per test binary (random weights,
//! ~86 M parameters in all) and shared.

use std::collections::HashMap;
use std::sync::OnceLock;

use candle_core::{DType, Device, Tensor};
use candle_nn::VarBuilder;

use blapose_lifters::anatomy::{self, REFERENCE_BONES};
use blapose_lifters::{
    record_random, Anatomy3d, Anatomy3dConfig, Lifter, LifterError, OnlineBoneLengths, PoseFormer,
    PoseFormerConfig, ReferenceLifter, VideoPose3d, VideoPose3dConfig,
};

/// A model built by [`record_random`], with the tensors it loaded.
struct Built<M> {
    model: M,
    tensors: HashMap<String, Tensor>,
}

fn record<M>(
    seed: u64,
    build: impl FnOnce(VarBuilder<'static>) -> blapose_lifters::Result<M>,
) -> Built<M> {
    let (model, tensors) = record_random(seed, build).unwrap();
    Built { model, tensors }
}

fn videopose() -> &'static Built<VideoPose3d> {
    static M: OnceLock<Built<VideoPose3d>> = OnceLock::new();
    M.get_or_init(|| {
        record(1, |vb| {
            VideoPose3d::new(VideoPose3dConfig::receptive_field_243(), vb)
        })
    })
}

fn poseformer() -> &'static Built<PoseFormer> {
    static M: OnceLock<Built<PoseFormer>> = OnceLock::new();
    M.get_or_init(|| record(2, |vb| PoseFormer::new(PoseFormerConfig::frames_81(), vb)))
}

fn anatomy3d() -> &'static Built<Anatomy3d> {
    static M: OnceLock<Built<Anatomy3d>> = OnceLock::new();
    M.get_or_init(|| {
        record(3, |vb| {
            Anatomy3d::new(Anatomy3dConfig::receptive_field_243(), vb)
        })
    })
}

/// Deterministic, pose-like 2D input: joints spread over the unit square,
/// moving a little from frame to frame.
fn keypoints(batch: usize, frames: usize, phase: f32) -> Tensor {
    let data: Vec<f32> = (0..batch * frames * 17 * 2)
        .map(|i| {
            let (f, j) = ((i / 34) as f32, (i % 34) as f32);
            0.4 * (0.7 * j + phase).sin() + 0.05 * (0.3 * f + j).cos()
        })
        .collect();
    Tensor::from_vec(data, (batch, frames, 17, 2), &Device::Cpu).unwrap()
}

fn max_abs_diff(a: &Tensor, b: &Tensor) -> f32 {
    a.sub(b)
        .unwrap()
        .abs()
        .unwrap()
        .flatten_all()
        .unwrap()
        .max(0)
        .unwrap()
        .to_scalar()
        .unwrap()
}

fn max_abs(a: &Tensor) -> f32 {
    a.abs()
        .unwrap()
        .flatten_all()
        .unwrap()
        .max(0)
        .unwrap()
        .to_scalar()
        .unwrap()
}

/// Replace frames `from..` of a `(1, T, 17, 2)` sequence with other values.
fn change_from(seq: &Tensor, from: usize) -> Tensor {
    let t = seq.dim(1).unwrap();
    let other = keypoints(1, t - from, 2.5);
    Tensor::cat(&[&seq.narrow(1, 0, from).unwrap(), &other], 1).unwrap()
}

#[test]
fn parameter_counts_match_the_reference_implementations() {
    assert_eq!(videopose().model.params(), 16_952_371);
    assert_eq!(poseformer().model.params(), 9_602_885);
    assert_eq!(anatomy3d().model.params(), 59_177_580);
    assert_eq!(anatomy3d().model.bone_length().params(), 8_557_219);
    // The published constants say the same.
    assert_eq!(blapose_lifters::videopose::PARAMS_243, 16_952_371);
    assert_eq!(blapose_lifters::poseformer::PARAMS_81, 9_602_885);
    assert_eq!(anatomy::PARAMS, 59_177_580);
    assert_eq!(anatomy::PARAMS_BONE_LENGTH, 8_557_219);
}

#[test]
fn parameter_counts_exclude_batch_norm_statistics() {
    // Everything loaded, minus the running statistics, is the count.
    for (count, tensors) in [
        (videopose().model.params(), &videopose().tensors),
        (anatomy3d().model.params(), &anatomy3d().tensors),
        (poseformer().model.params(), &poseformer().tensors),
    ] {
        let stats: usize = tensors
            .iter()
            .filter(|(n, _)| n.ends_with("running_mean") || n.ends_with("running_var"))
            .map(|(_, t)| t.elem_count())
            .sum();
        let all: usize = tensors.values().map(Tensor::elem_count).sum();
        assert_eq!(all - stats, count);
    }
}

#[test]
fn tensors_have_the_reference_state_dict_names_and_shapes() {
    let shape = |b: &HashMap<String, Tensor>, n: &str| b.get(n).map(|t| t.dims().to_vec());
    let vp = &videopose().tensors;
    assert_eq!(shape(vp, "expand_conv.weight"), Some(vec![1024, 34, 3]));
    assert_eq!(shape(vp, "layers_conv.6.weight"), Some(vec![1024, 1024, 3]));
    assert_eq!(shape(vp, "layers_conv.7.weight"), Some(vec![1024, 1024, 1]));
    assert_eq!(shape(vp, "layers_bn.7.running_var"), Some(vec![1024]));
    assert_eq!(shape(vp, "shrink.bias"), Some(vec![51]));
    assert!(
        !vp.contains_key("expand_conv.bias"),
        "VideoPose3D convolutions have no bias"
    );

    let pf = &poseformer().tensors;
    assert_eq!(shape(pf, "Spatial_pos_embed"), Some(vec![1, 17, 32]));
    assert_eq!(shape(pf, "Temporal_pos_embed"), Some(vec![1, 81, 544]));
    assert_eq!(
        shape(pf, "Spatial_blocks.3.attn.qkv.weight"),
        Some(vec![96, 32])
    );
    assert_eq!(shape(pf, "blocks.3.mlp.fc1.weight"), Some(vec![1088, 544]));
    assert_eq!(shape(pf, "weighted_mean.weight"), Some(vec![1, 81, 1]));
    assert_eq!(shape(pf, "head.0.weight"), Some(vec![544]));
    assert_eq!(shape(pf, "head.1.weight"), Some(vec![51, 544]));

    let an = &anatomy3d().tensors;
    assert_eq!(
        shape(an, "expand_convscore.weight"),
        Some(vec![1024, 17, 3])
    );
    assert_eq!(shape(an, "layers_conv.0.weight"), Some(vec![1024, 2048, 3]));
    assert_eq!(shape(an, "layers_conv.2.weight"), Some(vec![1024, 1024, 3]));
    assert_eq!(
        shape(an, "layers_conv1.6.weight"),
        Some(vec![1024, 2048, 3])
    );
    assert_eq!(shape(an, "layers_convbone.0.weight"), Some(vec![1024, 34]));
    assert_eq!(shape(an, "layers_convbone.9.weight"), Some(vec![51, 1024]));
    assert_eq!(shape(an, "layers_bnbone.8.running_mean"), Some(vec![1024]));
    assert!(
        !an.contains_key("layers_bnbone.9.weight"),
        "the last bone layer has no norm"
    );
    assert_eq!(shape(an, "boneatt.weight"), Some(vec![16, 102]));
    assert_eq!(shape(an, "shrink_js_2.weight"), Some(vec![411, 1024, 1]));
    assert_eq!(shape(an, "lengthlinear_2.weight"), Some(vec![1024, 16]));
}

#[test]
fn every_lifter_outputs_one_pose_per_window() {
    let lifters: [&dyn Lifter; 3] = [&videopose().model, &poseformer().model, &anatomy3d().model];
    for lifter in lifters {
        let window = keypoints(2, lifter.receptive_field(), 0.0);
        let out = lifter.predict_frame(&window).unwrap();
        assert_eq!(out.dims(), &[2, 17, 3], "{}", lifter.name());
        let v: Vec<f32> = out.flatten_all().unwrap().to_vec1().unwrap();
        assert!(v.iter().all(|x| x.is_finite()), "{}", lifter.name());
        assert!(
            max_abs(&out) > 0.0,
            "{}: output is all zeros",
            lifter.name()
        );
        // Batch elements are independent.
        let single = lifter
            .predict_frame(&window.narrow(0, 1, 1).unwrap())
            .unwrap();
        assert!(
            max_abs_diff(&single, &out.narrow(0, 1, 1).unwrap()) <= 1e-4 * max_abs(&out).max(1.0),
            "{}",
            lifter.name()
        );
    }
    assert_eq!(videopose().model.receptive_field(), 243);
    assert_eq!(poseformer().model.receptive_field(), 81);
    assert_eq!(anatomy3d().model.receptive_field(), 243);
}

#[test]
fn windows_of_the_wrong_shape_are_typed_errors() {
    let too_short = keypoints(1, 80, 0.0);
    assert!(matches!(
        poseformer().model.predict_frame(&too_short),
        Err(LifterError::Shape { .. })
    ));
    assert!(matches!(
        videopose().model.predict_frame(&too_short),
        Err(LifterError::Shape { .. })
    ));
    let three_features = Tensor::zeros((1, 243, 17, 3), DType::F32, &Device::Cpu).unwrap();
    assert!(matches!(
        anatomy3d().model.predict_frame(&three_features),
        Err(LifterError::Shape { .. })
    ));
}

#[test]
fn videopose_single_frame_form_equals_dilated_form() {
    let vp = &videopose().model;
    let seq = keypoints(1, 250, 0.3);
    let full = vp.forward_sequence(&seq).unwrap();
    assert_eq!(full.dims(), &[1, 8, 17, 3]);
    let scale = max_abs(&full);
    for i in [0, 3, 7] {
        let one = vp.forward_window(&seq.narrow(1, i, 243).unwrap()).unwrap();
        let diff = max_abs_diff(&one, &full.narrow(1, i, 1).unwrap().squeeze(1).unwrap());
        assert!(
            diff <= 1e-4 * scale,
            "window {i}: diff {diff} (scale {scale})"
        );
    }
}

#[test]
fn causal_videopose_forms_agree_and_use_only_past_frames() {
    // Same weights as the shared model, causal alignment.
    let tensors = videopose().tensors.clone();
    let vb = VarBuilder::from_tensors(tensors, DType::F32, &Device::Cpu);
    let causal = VideoPose3d::new(
        VideoPose3dConfig::receptive_field_243().with_causal(true),
        vb,
    )
    .unwrap();
    assert_eq!(causal.params(), 16_952_371);

    let seq = keypoints(1, 250, 0.1);
    let full = causal.forward_sequence(&seq).unwrap();
    let one = causal
        .forward_window(&seq.narrow(1, 5, 243).unwrap())
        .unwrap();
    let diff = max_abs_diff(&one, &full.narrow(1, 5, 1).unwrap().squeeze(1).unwrap());
    assert!(diff <= 1e-4 * max_abs(&full), "diff {diff}");
    // Causal and centred alignment are different models.
    let centred = videopose()
        .model
        .forward_window(&seq.narrow(1, 5, 243).unwrap())
        .unwrap();
    assert!(max_abs_diff(&one, &centred) > 1e-3);

    // One output per input frame; changing frames 30.. leaves outputs 0..30 alone.
    let seq = keypoints(1, 60, 0.7);
    let changed = change_from(&seq, 30);
    let (a, b) = (
        causal.predict_sequence(&seq).unwrap(),
        causal.predict_sequence(&changed).unwrap(),
    );
    assert_eq!(a.dims(), &[1, 60, 17, 3]);
    let scale = max_abs(&a);
    let past = max_abs_diff(&a.narrow(1, 0, 30).unwrap(), &b.narrow(1, 0, 30).unwrap());
    assert!(
        past <= 1e-6 * scale,
        "a future frame changed a past output by {past}"
    );
    let now = max_abs_diff(&a.narrow(1, 30, 1).unwrap(), &b.narrow(1, 30, 1).unwrap());
    assert!(
        now > 1e-3 * scale,
        "the changed frame itself must matter ({now})"
    );

    // The centred model, by contrast, looks ahead.
    let vp = &videopose().model;
    let (a, b) = (
        vp.predict_sequence(&seq).unwrap(),
        vp.predict_sequence(&changed).unwrap(),
    );
    assert_eq!(a.dims(), &[1, 60, 17, 3]);
    assert!(
        max_abs_diff(&a.narrow(1, 29, 1).unwrap(), &b.narrow(1, 29, 1).unwrap())
            > 1e-3 * max_abs(&a)
    );
}

#[test]
fn models_load_from_plain_tensors_and_reject_missing_ones() {
    let small = VideoPose3dConfig {
        filter_widths: vec![3, 3],
        channels: 8,
        causal: false,
    };
    let built = record(9, |vb| VideoPose3d::new(small.clone(), vb));
    assert_eq!(
        built.model.params(),
        34 * 8 * 3 + 2 * 8 + (8 * 8 * 3 + 2 * 8) + (8 * 8 + 2 * 8) + (8 * 51 + 51)
    );
    let vb = VarBuilder::from_tensors(built.tensors.clone(), DType::F32, &Device::Cpu);
    let loaded = VideoPose3d::new(small.clone(), vb).unwrap();
    let w = keypoints(1, 9, 0.0);
    assert_eq!(
        max_abs_diff(
            &built.model.forward_window(&w).unwrap(),
            &loaded.forward_window(&w).unwrap()
        ),
        0.0
    );

    let mut missing = built.tensors;
    missing.remove("layers_bn.1.running_var");
    let vb = VarBuilder::from_tensors(missing, DType::F32, &Device::Cpu);
    assert!(matches!(
        VideoPose3d::new(small, vb),
        Err(LifterError::Candle(_))
    ));
    let even = VideoPose3dConfig {
        filter_widths: vec![3, 4],
        channels: 8,
        causal: false,
    };
    assert!(matches!(
        VideoPose3d::random(even, 0),
        Err(LifterError::Config(_))
    ));
}

#[test]
fn anatomy_directions_are_unit_vectors_and_lengths_drive_the_pose() {
    let model = &anatomy3d().model;
    let window = keypoints(1, 243, 0.2);
    let d = model.bone_directions(&window, None).unwrap();
    assert_eq!(d.dims(), &[1, 16, 3]);
    let norms: Vec<f32> = d
        .sqr()
        .unwrap()
        .sum(2)
        .unwrap()
        .sqrt()
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1()
        .unwrap();
    assert!(norms.iter().all(|n| (n - 1.0).abs() < 1e-5), "{norms:?}");

    // Visibility scores are an input: all-ones equals the default.
    let ones = Tensor::ones((1, 243, 17), DType::F32, &Device::Cpu).unwrap();
    assert_eq!(
        max_abs_diff(&model.bone_directions(&window, Some(&ones)).unwrap(), &d),
        0.0
    );
    let halves = (ones * 0.5).unwrap();
    assert!(max_abs_diff(&model.bone_directions(&window, Some(&halves)).unwrap(), &d) > 1e-4);

    let l1 = Tensor::full(0.2f32, (1, 16), &Device::Cpu).unwrap();
    let l2 = Tensor::full(0.4f32, (1, 16), &Device::Cpu).unwrap();
    let p1 = model.predict_frame_with(&window, None, &l1).unwrap();
    let p2 = model.predict_frame_with(&window, None, &l2).unwrap();
    assert_eq!(p1.dims(), &[1, 17, 3]);
    assert!(max_abs_diff(&p1, &p2) > 1e-4);
}

#[test]
fn online_bone_lengths_equal_attention_over_all_frames_seen() {
    let branch = anatomy3d().model.bone_length();
    let frames = keypoints(1, 12, 0.9);
    let batch = branch.predict_lengths(&frames).unwrap();
    assert_eq!(batch.dims(), &[1, 16]);
    let batch: Vec<f32> = batch.flatten_all().unwrap().to_vec1().unwrap();

    let mut state = OnlineBoneLengths::new();
    assert!(state.lengths().is_none());
    let mut last = [0.0; 16];
    for t in 0..12 {
        last = branch
            .step(&frames.narrow(1, t, 1).unwrap(), &mut state)
            .unwrap();
    }
    assert_eq!(state.frames(), 12);
    for (a, b) in last.iter().zip(&batch) {
        assert!(
            (a - b).abs() <= 1e-4 * b.abs().max(1e-3),
            "online {a} vs batch {b}"
        );
    }
    // The lengths are those of the branch's per-frame poses.
    let (lengths, _) = branch.frame_outputs(&frames.squeeze(0).unwrap()).unwrap();
    assert_eq!(lengths.dims(), &[12, 16]);
    assert_eq!(REFERENCE_BONES.len(), 16);
}

#[test]
fn streaming_softmax_is_exact_and_overflow_free() {
    let mut s = OnlineBoneLengths::new();
    let lengths = |v: f32| [v; 16];
    s.push(&lengths(1.0), &[0.0; 16]);
    s.push(&lengths(3.0), &[0.0; 16]);
    assert!((s.lengths().unwrap()[0] - 2.0).abs() < 1e-6);
    // Huge logits must not overflow: the newest frame dominates.
    s.push(&lengths(10.0), &[1000.0; 16]);
    assert!((s.lengths().unwrap()[5] - 10.0).abs() < 1e-6);
    let mut s = OnlineBoneLengths::new();
    s.push(&lengths(1.0), &[2f32.ln(); 16]);
    s.push(&lengths(4.0), &[0.0; 16]);
    // weights 2:1
    assert!((s.lengths().unwrap()[0] - 2.0).abs() < 1e-6);
}

#[test]
fn reference_lifters_build_with_random_weights() {
    // The cheapest only; the others are the shared models above.
    let pf = ReferenceLifter::PoseFormer.random(false, 4).unwrap();
    assert_eq!(
        (pf.name(), pf.receptive_field(), pf.params()),
        ("PoseFormer", 81, 9_602_885)
    );
    assert_eq!(ReferenceLifter::ALL.len(), 3);
}

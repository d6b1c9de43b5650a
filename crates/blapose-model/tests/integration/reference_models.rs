//! The reference candle models: parameter counts, PyTorch semantics (checked
//! against a direct scalar transcription of the `nn.GRU` equations), the
//! per-frame output, dropout and gradients.

use std::collections::HashMap;

use blapose_core::skeleton::SYMMETRIC_BONE_PAIRS;
use blapose_model::names::{GruNames, EMBED_BIAS, EMBED_WEIGHT, FC_WEIGHT};
use blapose_model::reference::{count_parameters, frames_tensor, GruImpl};
use blapose_model::{
    BoneLengthBiGru, BoneLengthGru, LoadedWeights, ModelKind, HIDDEN, INPUT_DIM, OUTPUT_DIM, PARAMS,
};
use candle_core::{DType, Device, Tensor};
use candle_nn::{VarBuilder, VarMap};

fn vals(w: &LoadedWeights, name: &str) -> Vec<f32> {
    w.values(name).unwrap()
}

fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

/// One PyTorch GRU direction over `xs` (embedded frames), scalar, f64 accumulation.
fn naive_gru(w: &LoadedWeights, n: &GruNames, xs: &[Vec<f32>]) -> Vec<f32> {
    let (wi, wh, bi, bh) = (
        vals(w, &n.weight_ih),
        vals(w, &n.weight_hh),
        vals(w, &n.bias_ih),
        vals(w, &n.bias_hh),
    );
    let e = xs[0].len();
    let mut h = vec![0.0f32; HIDDEN];
    for x in xs {
        let dot_i = |row: usize| -> f32 {
            (0..e)
                .map(|k| wi[row * e + k] as f64 * x[k] as f64)
                .sum::<f64>() as f32
                + bi[row]
        };
        let dot_h = |row: usize, h: &[f32]| -> f32 {
            (0..HIDDEN)
                .map(|k| wh[row * HIDDEN + k] as f64 * h[k] as f64)
                .sum::<f64>() as f32
                + bh[row]
        };
        let mut next = vec![0.0; HIDDEN];
        for j in 0..HIDDEN {
            let r = sigmoid(dot_i(j) + dot_h(j, &h));
            let z = sigmoid(dot_i(HIDDEN + j) + dot_h(HIDDEN + j, &h));
            let nn = (dot_i(2 * HIDDEN + j) + r * dot_h(2 * HIDDEN + j, &h)).tanh();
            next[j] = (1.0 - z) * nn + z * h[j];
        }
        h = next;
    }
    h
}

fn naive_embed(w: &LoadedWeights, frames: &[f32]) -> Vec<Vec<f32>> {
    let (ew, eb) = (vals(w, EMBED_WEIGHT), vals(w, EMBED_BIAS));
    frames
        .chunks_exact(INPUT_DIM)
        .map(|x| {
            (0..eb.len())
                .map(|j| {
                    let v: f32 = (0..INPUT_DIM).map(|k| ew[j * INPUT_DIM + k] * x[k]).sum();
                    (v + eb[j]).max(0.0)
                })
                .collect()
        })
        .collect()
}

fn naive_head(w: &LoadedWeights, features: &[f32]) -> Vec<f32> {
    let fc = vals(w, FC_WEIGHT);
    let mut y: Vec<f32> = (0..OUTPUT_DIM)
        .map(|o| {
            features
                .iter()
                .enumerate()
                .map(|(k, &f)| fc[o * features.len() + k] * sigmoid(f))
                .sum()
        })
        .collect();
    for &(r, l) in &SYMMETRIC_BONE_PAIRS {
        let m = 0.5 * (y[r] + y[l]);
        y[r] = m;
        y[l] = m;
    }
    y
}

fn frames(n: usize, seed: u32) -> Vec<f32> {
    (0..n * INPUT_DIM)
        .map(|i| ((i as f32 * 0.731 + seed as f32).sin() * 1.3).clamp(-1.0, 1.0))
        .collect()
}

fn to_vec(t: &Tensor) -> Vec<f32> {
    t.flatten_all().unwrap().to_vec1().unwrap()
}

fn assert_close(a: &[f32], b: &[f32], tol: f32) {
    assert_eq!(a.len(), b.len());
    for (i, (x, y)) in a.iter().zip(b).enumerate() {
        assert!((x - y).abs() < tol, "index {i}: {x} vs {y}");
    }
}

#[test]
fn both_models_have_exactly_the_paper_parameter_count() {
    for kind in [ModelKind::Gru, ModelKind::BiGru] {
        let vm = VarMap::new();
        let vb = VarBuilder::from_varmap(&vm, DType::F32, &Device::Cpu);
        match kind {
            ModelKind::Gru => drop(BoneLengthGru::new(vb).unwrap()),
            ModelKind::BiGru => drop(BoneLengthBiGru::new(vb).unwrap()),
        }
        let vars = vm.all_vars();
        assert_eq!(vars.len(), 11, "{kind}");
        assert_eq!(
            count_parameters(vars.iter().map(|v| v.as_tensor())),
            PARAMS,
            "{kind}"
        );
        assert_eq!(PARAMS, 2_390_784);
    }
}

#[test]
fn online_model_matches_the_pytorch_equations() {
    let w = LoadedWeights::random(ModelKind::Gru, 17).unwrap();
    let model = BoneLengthGru::new(w.var_builder()).unwrap();
    let (batch, steps) = (2, 6);
    let fr = frames(batch * steps, 1);
    let got = to_vec(
        &model
            .forward(&frames_tensor(&fr, batch, steps).unwrap(), false)
            .unwrap(),
    );
    let [a, b] = GruNames::for_kind(ModelKind::Gru);
    for s in 0..batch {
        let e = naive_embed(&w, &fr[s * steps * INPUT_DIM..(s + 1) * steps * INPUT_DIM]);
        let mut features = naive_gru(&w, &a, &e);
        features.extend(naive_gru(&w, &b, &e));
        let expect = naive_head(&w, &features);
        assert_close(&got[s * OUTPUT_DIM..(s + 1) * OUTPUT_DIM], &expect, 2e-5);
    }
}

#[test]
fn bidirectional_model_matches_the_pytorch_equations() {
    let w = LoadedWeights::random(ModelKind::BiGru, 18).unwrap();
    let model = BoneLengthBiGru::new(w.var_builder()).unwrap();
    let steps = 7;
    let fr = frames(steps, 2);
    let got = to_vec(
        &model
            .forward(&frames_tensor(&fr, 1, steps).unwrap(), false)
            .unwrap(),
    );
    let [fwd, bwd] = GruNames::for_kind(ModelKind::BiGru);
    let e = naive_embed(&w, &fr);
    let h_fwd = naive_gru(&w, &fwd, &e);
    let rev: Vec<Vec<f32>> = e.iter().rev().cloned().collect();
    let mut features = naive_gru(&w, &bwd, &rev); // backward state first
    features.extend(h_fwd);
    assert_close(&got, &naive_head(&w, &features), 2e-5);
}

#[test]
fn per_frame_output_ends_with_the_final_state_prediction() {
    let w = LoadedWeights::random(ModelKind::Gru, 19).unwrap();
    let model = BoneLengthGru::new(w.var_builder()).unwrap();
    let (batch, steps) = (3, 9);
    let x = frames_tensor(&frames(batch * steps, 3), batch, steps).unwrap();
    let per_frame = model.forward_per_frame(&x).unwrap();
    assert_eq!(per_frame.dims(), &[batch, steps, OUTPUT_DIM]);
    let last = to_vec(&per_frame.narrow(1, steps - 1, 1).unwrap());
    assert_close(&last, &to_vec(&model.forward(&x, false).unwrap()), 1e-6);
    // prefix property: the prediction after frame 4 is the forward of frames 0..=4
    let prefix = to_vec(&model.forward(&x.narrow(1, 0, 5).unwrap(), false).unwrap());
    assert_close(&to_vec(&per_frame.narrow(1, 4, 1).unwrap()), &prefix, 1e-6);
    // symmetric pairs are equal
    let all = to_vec(&per_frame);
    for row in all.chunks_exact(OUTPUT_DIM) {
        for &(r, l) in &SYMMETRIC_BONE_PAIRS {
            assert_eq!(row[r], row[l]);
        }
    }
}

#[test]
fn dropout_only_in_training() {
    let w = LoadedWeights::random(ModelKind::BiGru, 20).unwrap();
    let model = BoneLengthBiGru::new(w.var_builder()).unwrap();
    let x = frames_tensor(&frames(8, 4), 1, 8).unwrap();
    let eval1 = to_vec(&model.forward(&x, false).unwrap());
    let eval2 = to_vec(&model.forward(&x, false).unwrap());
    assert_eq!(eval1, eval2);
    let train = to_vec(&model.forward(&x, true).unwrap());
    assert_ne!(train, eval1);
}

#[test]
fn bad_input_shapes_are_errors() {
    let w = LoadedWeights::random(ModelKind::Gru, 1).unwrap();
    let model = BoneLengthGru::new(w.var_builder()).unwrap();
    let x = Tensor::zeros((1, 4, 33), DType::F32, &Device::Cpu).unwrap();
    assert!(model.forward(&x, false).is_err());
    let x = Tensor::zeros((1, 0, INPUT_DIM), DType::F32, &Device::Cpu).unwrap();
    assert!(model.forward(&x, false).is_err());
    assert!(frames_tensor(&[0.0; 10], 1, 1).is_err());
}

#[test]
fn every_parameter_receives_a_gradient() {
    for kind in [ModelKind::Gru, ModelKind::BiGru] {
        let vm = VarMap::new();
        let vb = VarBuilder::from_varmap(&vm, DType::F32, &Device::Cpu);
        let x = frames_tensor(&frames(2 * 5, 5), 2, 5).unwrap();
        let y = match kind {
            ModelKind::Gru => BoneLengthGru::new(vb).unwrap().forward(&x, true).unwrap(),
            ModelKind::BiGru => BoneLengthBiGru::new(vb).unwrap().forward(&x, true).unwrap(),
        };
        let loss = y.sqr().unwrap().sum_all().unwrap();
        let grads = loss.backward().unwrap();
        let named: HashMap<String, _> = vm.data().lock().unwrap().clone();
        for (name, var) in named {
            let g = grads
                .get(var.as_tensor())
                .unwrap_or_else(|| panic!("{kind}: no grad for {name}"));
            let norm: f32 = g.sqr().unwrap().sum_all().unwrap().to_scalar().unwrap();
            assert!(norm > 0.0 && norm.is_finite(), "{kind} {name}: {norm}");
        }
    }
}

/// The fused recurrence op against the plain-ops recurrence: outputs and
/// the gradient of every parameter.
#[test]
fn fused_recurrence_matches_autograd_values_and_gradients() {
    for kind in [ModelKind::Gru, ModelKind::BiGru] {
        let w = LoadedWeights::random(kind, 23).unwrap();
        let (batch, steps) = (3, 7);
        let x = frames_tensor(&frames(batch * steps, 6), batch, steps).unwrap();
        let target = Tensor::full(0.3f32, (batch, OUTPUT_DIM), &Device::Cpu).unwrap();
        let mut results = Vec::new();
        for imp in [GruImpl::Fused, GruImpl::Autograd] {
            let vm = w.to_varmap().unwrap();
            let vb = VarBuilder::from_varmap(&vm, DType::F32, &Device::Cpu);
            let (y, per_frame) = match kind {
                ModelKind::Gru => {
                    let m = BoneLengthGru::new(vb).unwrap().with_gru_impl(imp);
                    (
                        m.forward(&x, false).unwrap(),
                        Some(m.forward_per_frame(&x).unwrap()),
                    )
                }
                ModelKind::BiGru => {
                    let m = BoneLengthBiGru::new(vb).unwrap().with_gru_impl(imp);
                    (m.forward(&x, false).unwrap(), None)
                }
            };
            // a loss that weights frames differently, so per-frame gradients matter
            let mut loss = (&y - &target).unwrap().abs().unwrap().sum_all().unwrap();
            if let Some(pf) = &per_frame {
                let ramp = Tensor::arange(0f32, steps as f32, &Device::Cpu)
                    .unwrap()
                    .reshape((1, steps, 1))
                    .unwrap();
                let extra = pf
                    .broadcast_mul(&ramp)
                    .unwrap()
                    .sqr()
                    .unwrap()
                    .sum_all()
                    .unwrap();
                loss = (loss + extra).unwrap();
            }
            let grads = loss.backward().unwrap();
            let data = vm.data().lock().unwrap().clone();
            let mut g: Vec<(String, Vec<f32>)> = data
                .iter()
                .map(|(n, v)| (n.clone(), to_vec(grads.get(v.as_tensor()).unwrap())))
                .collect();
            g.sort_by(|a, b| a.0.cmp(&b.0));
            results.push((to_vec(&y), per_frame.map(|p| to_vec(&p)), g));
        }
        let (fused, plain) = (&results[0], &results[1]);
        assert_close(&fused.0, &plain.0, 1e-5);
        if let (Some(a), Some(b)) = (&fused.1, &plain.1) {
            assert_close(a, b, 1e-5);
        }
        for ((name, ga), (_, gb)) in fused.2.iter().zip(&plain.2) {
            let scale = gb.iter().fold(0f32, |m, v| m.max(v.abs())).max(1e-3);
            for (i, (a, b)) in ga.iter().zip(gb).enumerate() {
                assert!(
                    (a - b).abs() <= 1e-3 * scale,
                    "{kind} {name}[{i}]: {a} vs {b}"
                );
            }
        }
    }
}

#[test]
fn stepper_reproduces_the_per_frame_output() {
    let w = LoadedWeights::random(ModelKind::Gru, 24).unwrap();
    let model = BoneLengthGru::new(w.var_builder()).unwrap();
    let (batch, steps) = (2, 5);
    let fr = frames(batch * steps, 7);
    let expect = to_vec(
        &model
            .forward_per_frame(&frames_tensor(&fr, batch, steps).unwrap())
            .unwrap(),
    );
    let stepper = model.stepper().unwrap();
    let mut state = Tensor::zeros((batch, 2 * HIDDEN), DType::F32, &Device::Cpu).unwrap();
    for t in 0..steps {
        let x: Vec<f32> = (0..batch)
            .flat_map(|b| fr[(b * steps + t) * INPUT_DIM..(b * steps + t + 1) * INPUT_DIM].to_vec())
            .collect();
        let x = Tensor::from_vec(x, (batch, INPUT_DIM), &Device::Cpu).unwrap();
        let (next, y) = stepper.step(&x, &state).unwrap();
        state = next;
        let y = to_vec(&y);
        for b in 0..batch {
            let at = (b * steps + t) * OUTPUT_DIM;
            assert_close(
                &y[b * OUTPUT_DIM..(b + 1) * OUTPUT_DIM],
                &expect[at..at + OUTPUT_DIM],
                1e-5,
            );
        }
    }
}

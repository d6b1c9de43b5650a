//! The hand-written training network must be the reference model: same
//! outputs and the same gradients as candle autograd on
//! `blapose_model::reference`, for both kinds and both losses.

use blapose_model::weights::LoadedWeights;
use blapose_model::{BoneLengthBiGru, BoneLengthGru, ModelKind};
use blapose_train::fastnet::{FastNet, LossConfig};
use candle_core::{DType, Device, Tensor};
use candle_nn::VarBuilder;
use rand::{Rng, SeedableRng};

const B: usize = 3;
const T: usize = 6;

fn inputs(seed: u64) -> (Vec<f32>, Vec<f32>) {
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
    let x: Vec<f32> = (0..B * T * 34)
        .map(|_| rng.random_range(-1.0f32..1.0))
        .collect();
    let y: Vec<f32> = (0..B * 16).map(|_| rng.random_range(0.0f32..0.6)).collect();
    (x, y)
}

fn check(kind: ModelKind, running_weight: f32) {
    let w = LoadedWeights::random(kind, 11).unwrap();
    let varmap = w.to_varmap().unwrap();
    let vb = VarBuilder::from_varmap(&varmap, DType::F32, &Device::Cpu);
    let (x, y) = inputs(3);
    let xt = Tensor::from_slice(&x, (B, T, 34), &Device::Cpu).unwrap();
    let yt = Tensor::from_slice(&y, (B, 16), &Device::Cpu).unwrap();
    let (pred, loss) = match kind {
        ModelKind::Gru => {
            let m = BoneLengthGru::new(vb).unwrap();
            let per = m.forward_per_frame_with(&xt, false).unwrap();
            let last = per.narrow(1, T - 1, 1).unwrap().squeeze(1).unwrap();
            let mut loss = last
                .broadcast_sub(&yt)
                .unwrap()
                .abs()
                .unwrap()
                .mean_all()
                .unwrap();
            if running_weight > 0.0 {
                let counts = Tensor::from_vec(
                    (1..=T).map(|i| i as f32).collect::<Vec<_>>(),
                    (1, T, 1),
                    &Device::Cpu,
                )
                .unwrap();
                let run = per.cumsum(1).unwrap().broadcast_div(&counts).unwrap();
                let l2 = run
                    .broadcast_sub(&yt.unsqueeze(1).unwrap())
                    .unwrap()
                    .abs()
                    .unwrap()
                    .mean_all()
                    .unwrap();
                loss = (loss + (l2 * running_weight as f64).unwrap()).unwrap();
            }
            (last, loss)
        }
        ModelKind::BiGru => {
            let m = BoneLengthBiGru::new(vb).unwrap();
            let p = m.forward(&xt, false).unwrap();
            let loss = p
                .broadcast_sub(&yt)
                .unwrap()
                .abs()
                .unwrap()
                .mean_all()
                .unwrap();
            (p, loss)
        }
    };
    let grads = loss.backward().unwrap();
    let net = FastNet::from_tensors(kind, w.tensors()).unwrap();
    let mine = net.predict(&x, B, T);
    let theirs: Vec<f32> = pred.flatten_all().unwrap().to_vec1().unwrap();
    for (a, b) in mine.iter().zip(&theirs) {
        assert!((a - b).abs() < 1e-5, "{kind}: prediction {a} vs {b}");
    }
    let mut grad = vec![0.0f32; net.params.len()];
    let mut rng = rand::rngs::StdRng::seed_from_u64(0);
    let cfg = LossConfig {
        running_mean_weight: running_weight,
        dropout: 0.0,
    };
    let res = net.train_step(&x, &y, B, T, cfg, &mut rng, &mut grad);
    let l: f32 = loss.to_scalar().unwrap();
    assert!(
        (res.loss as f32 - l).abs() < 1e-5,
        "{kind}: loss {} vs {l}",
        res.loss
    );
    let data = varmap.data().lock().unwrap();
    for (name, range, _) in net.layout.tensors() {
        let var = &data[&name];
        let g: Vec<f32> = grads
            .get(var.as_tensor())
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1()
            .unwrap();
        let scale = g.iter().fold(0.0f32, |m, v| m.max(v.abs())).max(1e-6);
        let worst = g
            .iter()
            .zip(&grad[range])
            .fold(0.0f32, |m, (a, b)| m.max((a - b).abs()));
        assert!(
            worst <= 2e-3 * scale + 1e-7,
            "{kind} (running {running_weight}): gradient of {name} off by {worst} (scale {scale})"
        );
    }
}

#[test]
fn gru_matches_reference_final_loss() {
    check(ModelKind::Gru, 0.0);
}

#[test]
fn gru_matches_reference_running_mean_loss() {
    check(ModelKind::Gru, 0.7);
}

#[test]
fn bigru_matches_reference() {
    check(ModelKind::BiGru, 0.0);
}

#[test]
fn per_frame_prediction_ends_with_the_final_prediction() {
    let w = LoadedWeights::random(ModelKind::Gru, 5).unwrap();
    let net = FastNet::from_tensors(ModelKind::Gru, w.tensors()).unwrap();
    let (x, _) = inputs(9);
    let fin = net.predict(&x, B, T);
    let per = net.predict_per_frame(&x, B, T);
    for b in 0..B {
        for j in 0..16 {
            assert!((per[(b * T + T - 1) * 16 + j] - fin[b * 16 + j]).abs() < 1e-6);
        }
    }
}

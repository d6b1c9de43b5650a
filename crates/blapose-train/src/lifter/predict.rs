//! Running a lifter over whole streams, with or without test-time flip.
//!
//! Validation goes through [`predict_rows`] (windows, the training form).
//! Evaluation lifts whole streams with a [`StreamLifter`]: temporal models
//! through the inference crate's dilated form — one pass per stream instead
//! of one window per frame, about half the arithmetic and packed kernels —
//! which a test checks gives the windowed numbers; other models window by
//! window.

use blapose_core::Pose;
use candle_core::{Device, Tensor};

use super::data::{
    average_flipped, flip_input, outputs_to_poses, push_window, LifterSequence, SampleIndex,
};
use super::weights::{named_tensors, LoadedLifter};
use super::{LifterArch, LifterNet};
use crate::dataset::EvalSequence;
use crate::error::TrainError;
use crate::synth::FRAME_DIM;

/// Rows per forward pass.
const CHUNK: usize = 2048;

/// Lift `inputs` (`n * receptive_field * 34`, one window per row) in
/// evaluation mode; with `flip`, average with the mirrored-back prediction
/// of the mirrored input.
pub fn predict_rows(
    net: &dyn LifterNet,
    inputs: &[f32],
    flip: bool,
) -> Result<Vec<Pose>, TrainError> {
    let width = net.window().values();
    if !inputs.len().is_multiple_of(width) {
        return Err(TrainError::InvalidArgument(format!(
            "{} input values is not a whole number of {width}-value windows",
            inputs.len()
        )));
    }
    let run = |x: &[f32]| -> Result<Vec<Pose>, TrainError> {
        let mut out = Vec::with_capacity(x.len() / width);
        for c in x.chunks(CHUNK * width) {
            let t = Tensor::from_slice(c, (c.len() / width, width), &Device::Cpu)?;
            let y = net.forward(&t, None)?.flatten_all()?.to_vec1::<f32>()?;
            out.extend(outputs_to_poses(&y));
        }
        Ok(out)
    };
    let plain = run(inputs)?;
    if !flip {
        return Ok(plain);
    }
    let mirrored = run(&flip_input(inputs))?;
    Ok(average_flipped(&plain, &mirrored))
}

/// The lifter's pose for every frame of `trial`.
pub fn predict_sequence(
    net: &dyn LifterNet,
    trial: &EvalSequence,
    flip: bool,
) -> Result<Vec<Pose>, TrainError> {
    let window = net.window();
    if window.frames == 1 {
        return predict_rows(net, &trial.input, flip);
    }
    let mut rows = Vec::with_capacity(trial.frames() * window.values());
    for t in 0..trial.frames() {
        push_window(trial, t, window, &mut rows);
    }
    predict_rows(net, &rows, flip)
}

/// The lifter's pose for each sample.
pub fn predict_samples(
    net: &dyn LifterNet,
    seqs: &[LifterSequence],
    idx: &[SampleIndex],
    flip: bool,
) -> Result<Vec<Pose>, TrainError> {
    let window = net.window();
    let mut rows = Vec::with_capacity(idx.len() * window.values());
    for &(s, t) in idx {
        push_window(&seqs[s].trial, t, window, &mut rows);
    }
    predict_rows(net, &rows, flip)
}

/// Lifts whole streams for evaluation.
pub enum StreamLifter<'a> {
    /// Window by window through the trained network.
    Windows(&'a dyn LifterNet),
    /// A temporal model in the inference crate's dilated form.
    Dilated(Box<blapose_lifters::VideoPose3d>),
}

impl<'a> StreamLifter<'a> {
    /// The fastest exact form for `lifter`.
    pub fn new(lifter: &'a LoadedLifter) -> Result<Self, TrainError> {
        match lifter.metadata.arch {
            LifterArch::VideoPose(c) => {
                let tensors = named_tensors(&lifter.varmap)?.into_iter().collect();
                let vb = candle_nn::VarBuilder::from_tensors(
                    tensors,
                    candle_core::DType::F32,
                    &Device::Cpu,
                );
                Ok(Self::Dilated(Box::new(blapose_lifters::VideoPose3d::new(
                    c.config(),
                    vb,
                )?)))
            }
            LifterArch::Mlp(_) => Ok(Self::Windows(lifter.net.as_ref())),
        }
    }

    /// The lifter's pose for every frame of `trial`, with or without
    /// test-time flip.
    pub fn lift(&self, trial: &EvalSequence, flip: bool) -> Result<Vec<Pose>, TrainError> {
        match self {
            Self::Windows(net) => predict_sequence(*net, trial, flip),
            Self::Dilated(model) => {
                let run = |input: &[f32]| -> Result<Vec<Pose>, TrainError> {
                    let n = input.len() / FRAME_DIM;
                    let x = Tensor::from_slice(input, (1, n, 17, 2), &Device::Cpu)?;
                    let y = model.predict_sequence(&x)?.squeeze(0)?;
                    Ok(blapose_lifters::poses_from_tensor(&y)?)
                };
                let plain = run(&trial.input)?;
                if !flip {
                    return Ok(plain);
                }
                Ok(average_flipped(&plain, &run(&flip_input(&trial.input))?))
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lifter::weights::metadata;
    use crate::lifter::{build, VideoPoseArch};

    #[test]
    fn dilated_streams_match_windowed_prediction() {
        for causal in [false, true] {
            let arch = LifterArch::VideoPose(VideoPoseArch {
                filter_width: 3,
                blocks: 1,
                channels: 16,
                dropout: 0.1,
                causal,
            });
            let (net, varmap) = build(&arch, 4).unwrap();
            let x: Vec<f32> = (0..8 * net.window().values())
                .map(|i| (i as f32 * 0.21).cos())
                .collect();
            let x = Tensor::from_vec(x, (8, net.window().values()), &Device::Cpu).unwrap();
            let mut rng = crate::synth::sample_rng(7, 0, 0);
            net.forward(&x, Some(&mut rng)).unwrap(); // non-trivial running statistics
            let loaded = LoadedLifter {
                net,
                varmap,
                metadata: metadata(arch, "test", 0),
            };
            let trial = EvalSequence {
                subject: "S9".into(),
                sequence: "Walking 1".into(),
                camera: "c".into(),
                input: (0..23 * FRAME_DIM)
                    .map(|i| (i as f32 * 0.13).sin())
                    .collect(),
                gt: [0.2; 16],
            };
            let windows = predict_sequence(loaded.net.as_ref(), &trial, true).unwrap();
            let fast = StreamLifter::new(&loaded).unwrap();
            assert!(matches!(fast, StreamLifter::Dilated(_)));
            let dilated = fast.lift(&trial, true).unwrap();
            assert_eq!(windows.len(), dilated.len());
            for (a, b) in windows.iter().zip(&dilated) {
                for (p, q) in a.iter().flatten().zip(b.iter().flatten()) {
                    assert!((p - q).abs() < 1e-4, "causal={causal}: {p} vs {q}");
                }
            }
        }
    }
}

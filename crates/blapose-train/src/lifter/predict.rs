//! Running a lifter over whole streams, with or without test-time flip.
//!
//! Evaluation and validation both go through [`predict_rows`], so the
//! numbers the training log reports and the numbers eval-adjust reports are
//! produced by the same code.

use blapose_core::Pose;
use candle_core::{Device, Tensor};

use super::data::{
    average_flipped, flip_input, outputs_to_poses, push_window, LifterSequence, SampleIndex,
};
use super::LifterNet;
use crate::dataset::EvalSequence;
use crate::error::TrainError;

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

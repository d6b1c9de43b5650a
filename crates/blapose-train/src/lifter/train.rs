//! Training a lifter: MPJPE loss on root-relative camera-space joints, flip
//! augmentation, Adam with exponential decay, held-out validation,
//! checkpoints and resume, with the run directory, schedule and log of
//! every trainer here ([`crate::run`]).
//!
//! * **Gradients** come from candle autograd on the [`LifterNet`]; the
//!   update is the crate's [`Adam`] over one flat vector of the trainable
//!   variables (name order; batch-norm running statistics are variables but
//!   not trained), because candle-nn's optimizers keep their moments private
//!   and a checkpoint must carry them.
//! * **Batches.** Step `s` draws `batch` samples with replacement from the
//!   subsampled training frames and mirrors each with probability
//!   `flip_prob`, from a generator seeded by `(seed, s)` only; dropout masks
//!   likewise. So a resumed run continues the same sample stream.
//! * **Loss** is the mean over the batch and the 16 predicted joints of the
//!   Euclidean joint error (metres); the log shows it in mm. Validation is
//!   the standard 17-joint MPJPE (the root, fixed at 0, counts with zero
//!   error) on held-out frames of the training subjects, without and with
//!   test-time flip.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use blapose_core::bones::adjust_pose_lenient;
use blapose_core::metrics::{mpjpe, MM_PER_M};
use blapose_core::pose::flip_bone_lengths;
use blapose_core::{BoneLengths, Pose};
use candle_core::{Device, Tensor, Var};
use candle_nn::VarMap;
use serde::{Deserialize, Serialize};

use super::data::{held_out_samples, random_batch, training_samples, LifterSequence, SampleIndex};
use super::objective::{mpjpe_loss, AdjustmentGraph, Objective};
use super::predict::predict_samples;
use super::weights::{self, named_tensors};
use super::{LifterArch, LifterNet, OUTPUT_DIM};
use crate::adam::{Adam, AdamConfig};
use crate::error::TrainError;
use crate::run::{
    check_resumable, write_atomic, CheckpointMeta, CheckpointTimer, LogWindow, Progress, RunClock,
    RunDir, Schedule,
};
use crate::synth::sample_rng;

/// Columns of the lifter training log.
pub const LOG_HEADER: &str =
    "step,epoch,lr,train_loss_mm,grad_norm,samples_per_s,val_mpjpe_mm,val_mpjpe_flip_mm,elapsed_s";
/// Header key of the checkpoint metadata.
const CHECKPOINT_KEY: &str = "blapose_lifter_checkpoint";
/// Seed offsets of the batch stream and of the dropout masks.
const BATCH_SEED_SALT: u64 = 0x11F7_BA7C;
const DROPOUT_SEED_SALT: u64 = 0x11F7_D0D0;
/// Tensor names of the Adam moments inside a checkpoint.
const ADAM_M: &str = "__adam.m";
const ADAM_V: &str = "__adam.v";

/// Everything that defines a lifter training run.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LifterTrainConfig {
    /// Architecture and size.
    pub arch: LifterArch,
    /// Use every `every`-th 50 Hz frame for training.
    pub every: usize,
    /// Samples per batch.
    pub batch: usize,
    /// Total optimizer steps.
    pub steps: u64,
    /// Steps per epoch (learning-rate decay period).
    pub epoch_steps: u64,
    /// Initial learning rate.
    pub lr: f64,
    /// Learning-rate factor per epoch.
    pub lr_decay: f64,
    /// Gradient-norm clip (0 = none).
    pub clip_norm: f64,
    /// Probability of mirroring a training sample.
    pub flip_prob: f32,
    /// Master seed (initial weights, batches, dropout).
    pub seed: u64,
    /// Validate every this many steps (0 = only at the end).
    pub val_every: u64,
    /// Held-out validation frames.
    pub val_samples: usize,
    /// Seconds between checkpoints.
    pub checkpoint_secs: u64,
    /// What the run minimises.
    #[serde(default)]
    pub objective: Objective,
    /// Weight of `L_direction` in [`Objective::Adjusted`] (the paper: 1).
    #[serde(default = "unit_weight")]
    pub direction_weight: f64,
    /// Start from these weights instead of a seeded initialization
    /// (fine-tuning); the file's architecture must be `arch`.
    #[serde(default)]
    pub init_weights: Option<PathBuf>,
}

impl LifterTrainConfig {
    /// The learning-rate schedule.
    pub fn schedule(&self) -> Schedule {
        Schedule {
            lr: self.lr,
            decay: self.lr_decay,
            epoch_steps: self.epoch_steps,
        }
    }

    /// The fields a resumed run may change: length, logging, checkpoints.
    fn compatible(&self, other: &LifterTrainConfig) -> Result<(), String> {
        check_resumable(self, other, |a, o| {
            a.steps = o.steps;
            a.val_every = o.val_every;
            a.checkpoint_secs = o.checkpoint_secs;
        })
    }
}

fn unit_weight() -> f64 {
    1.0
}

/// Held-out validation (mm, 17-joint MPJPE).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct LifterValidation {
    /// Single prediction.
    pub mpjpe_mm: f64,
    /// With test-time flip.
    pub mpjpe_flip_mm: f64,
}

/// What a finished run reports.
#[derive(Debug, Clone, PartialEq)]
pub struct LifterTrainOutcome {
    /// The final weights.
    pub weights: PathBuf,
    /// Last validation.
    pub validation: LifterValidation,
    /// Mean training throughput of this invocation (samples/s).
    pub samples_per_s: f64,
    /// Wall-clock seconds of this invocation.
    pub elapsed_s: f64,
    /// Steps run in this invocation.
    pub steps_run: u64,
    /// Last logged training loss (mm).
    pub train_loss_mm: f64,
}

/// The trainable variables (batch-norm running statistics excluded), in
/// name order: the layout of the optimizer's flat vectors.
pub fn trainable_vars(varmap: &VarMap) -> Result<Vec<(String, Var)>, TrainError> {
    let data = varmap
        .data()
        .lock()
        .map_err(|_| TrainError::InvalidArgument("variable map lock poisoned".into()))?;
    let mut v: Vec<(String, Var)> = data
        .iter()
        .filter(|(k, _)| !k.contains("running_"))
        .map(|(k, v)| (k.clone(), v.clone()))
        .collect();
    v.sort_by(|a, b| a.0.cmp(&b.0));
    Ok(v)
}

fn flatten_vars(vars: &[(String, Var)]) -> Result<Vec<f32>, TrainError> {
    let mut out = Vec::new();
    for (_, v) in vars {
        out.extend(v.as_tensor().flatten_all()?.to_vec1::<f32>()?);
    }
    Ok(out)
}

fn write_vars(vars: &[(String, Var)], flat: &[f32]) -> Result<(), TrainError> {
    let mut o = 0;
    for (_, v) in vars {
        let n = v.as_tensor().elem_count();
        v.set(&Tensor::from_slice(
            &flat[o..o + n],
            v.as_tensor().shape(),
            &Device::Cpu,
        )?)?;
        o += n;
    }
    Ok(())
}

/// The data a run trains on.
struct TrainingSet<'a> {
    seqs: &'a [LifterSequence],
    pool: &'a [SampleIndex],
    /// Per sequence, for [`Objective::Adjusted`].
    lengths: Option<&'a [BoneLengths]>,
    graph: &'a AdjustmentGraph,
}

/// The lengths of each batch sample (mirrored with the sample), `(B, 16)`.
fn batch_lengths(
    lengths: &[BoneLengths],
    samples: &[SampleIndex],
    flipped: &[bool],
) -> Result<Tensor, TrainError> {
    let mut flat = Vec::with_capacity(samples.len() * 16);
    for (&(s, _), &f) in samples.iter().zip(flipped) {
        let l = if f {
            flip_bone_lengths(&lengths[s])
        } else {
            lengths[s]
        };
        flat.extend_from_slice(&l);
    }
    Ok(Tensor::from_vec(flat, (samples.len(), 16), &Device::Cpu)?)
}

/// One optimizer step on a random batch; returns `(loss_mm, grad_norm)`.
fn train_step(
    cfg: &LifterTrainConfig,
    net: &dyn LifterNet,
    vars: &[(String, Var)],
    params: &mut [f32],
    opt: &mut Adam,
    data: &TrainingSet,
    step: u64,
) -> Result<(f64, f64), TrainError> {
    let (seqs, pool) = (data.seqs, data.pool);
    let window = net.window();
    let mut rng = sample_rng(cfg.seed ^ BATCH_SEED_SALT, step, 0);
    let b = random_batch(seqs, pool, window, cfg.batch, cfg.flip_prob, &mut rng);
    let x = Tensor::from_slice(&b.inputs, (b.batch, window.values()), &Device::Cpu)?;
    let y = Tensor::from_slice(&b.targets, (b.batch, OUTPUT_DIM), &Device::Cpu)?;
    let mut drop_rng = sample_rng(cfg.seed ^ DROPOUT_SEED_SALT, step, 0);
    let pred = net.forward(&x, Some(&mut drop_rng))?;
    let loss = match (cfg.objective, data.lengths) {
        (Objective::Mpjpe, _) => mpjpe_loss(&pred, &y)?,
        (Objective::Adjusted, Some(lengths)) => {
            let l = batch_lengths(lengths, &b.samples, &b.flipped)?;
            data.graph.loss(&pred, &y, &l, cfg.direction_weight)?.0
        }
        (Objective::Adjusted, None) => {
            return Err(TrainError::InvalidArgument(
                "the adjusted objective needs bone lengths per sequence".into(),
            ))
        }
    };
    let loss_m = f64::from(loss.to_scalar::<f32>()?);
    if !loss_m.is_finite() {
        return Err(TrainError::Data(format!("non-finite loss at step {step}")));
    }
    let grads = loss.backward()?;
    let mut grad = Vec::with_capacity(params.len());
    for (_, v) in vars {
        match grads.get(v.as_tensor()) {
            Some(g) => grad.extend(g.flatten_all()?.to_vec1::<f32>()?),
            None => grad.extend(std::iter::repeat_n(0.0, v.as_tensor().elem_count())),
        }
    }
    opt.config.lr = cfg.schedule().lr_at(step);
    let norm = opt
        .step(params, &grad)
        .ok_or_else(|| TrainError::Data(format!("non-finite gradient at step {step}")))?;
    write_vars(vars, params)?;
    Ok((loss_m * MM_PER_M, norm))
}

/// Held-out MPJPE (mm) without and with test-time flip; with `lengths`
/// (per sequence) the MPJPE of the poses adjusted to them.
pub fn validate(
    net: &dyn LifterNet,
    seqs: &[LifterSequence],
    idx: &[SampleIndex],
    lengths: Option<&[BoneLengths]>,
) -> Result<LifterValidation, TrainError> {
    if idx.is_empty() {
        return Ok(LifterValidation {
            mpjpe_mm: f64::NAN,
            mpjpe_flip_mm: f64::NAN,
        });
    }
    let gt: Vec<Pose> = idx.iter().map(|&(s, t)| seqs[s].target[t]).collect();
    let err = |flip: bool| -> Result<f64, TrainError> {
        let mut p = predict_samples(net, seqs, idx, flip)?;
        if let Some(lengths) = lengths {
            for (pose, &(s, _)) in p.iter_mut().zip(idx) {
                *pose = adjust_pose_lenient(pose, &lengths[s])
                    .map_err(|e| TrainError::Data(e.to_string()))?;
            }
        }
        mpjpe(&p, &gt)
            .map(|e| e * MM_PER_M)
            .map_err(|e| TrainError::Data(e.to_string()))
    };
    Ok(LifterValidation {
        mpjpe_mm: err(false)?,
        mpjpe_flip_mm: err(true)?,
    })
}

fn save_checkpoint(
    path: &Path,
    varmap: &VarMap,
    opt: &Adam,
    meta: &CheckpointMeta<LifterTrainConfig>,
) -> Result<(), TrainError> {
    let mut tensors = named_tensors(varmap)?;
    tensors.insert(
        ADAM_M.into(),
        Tensor::from_slice(&opt.m, opt.m.len(), &Device::Cpu)?,
    );
    tensors.insert(
        ADAM_V.into(),
        Tensor::from_slice(&opt.v, opt.v.len(), &Device::Cpu)?,
    );
    let mut header = HashMap::new();
    header.insert(CHECKPOINT_KEY.to_string(), serde_json::to_string(meta)?);
    write_atomic(path, &weights::serialize(&tensors, header, path)?)
}

/// Train in `out` (created if needed) on `seqs`, which must come from the
/// training subjects only; validation uses their held-out frames.
/// `lengths` (one per sequence) are the frozen bone-length model's
/// estimates, which [`Objective::Adjusted`] needs; validation then scores
/// the adjusted poses. `training_data` goes into the weights' metadata.
pub fn train(
    cfg: &LifterTrainConfig,
    seqs: &[LifterSequence],
    lengths: Option<&[BoneLengths]>,
    out: &Path,
    resume: bool,
    training_data: &str,
    progress: Progress,
) -> Result<LifterTrainOutcome, TrainError> {
    if cfg.batch < 2 || cfg.steps == 0 || cfg.every == 0 {
        return Err(TrainError::InvalidArgument(
            "batch must be at least 2 (batch norm), steps and every positive".into(),
        ));
    }
    let lengths = match (cfg.objective, lengths) {
        (Objective::Mpjpe, _) => None,
        (Objective::Adjusted, Some(l)) if l.len() == seqs.len() => Some(l),
        (Objective::Adjusted, l) => {
            return Err(TrainError::InvalidArgument(format!(
                "the adjusted objective needs one set of bone lengths per sequence ({} sequences, {} sets)",
                seqs.len(),
                l.map_or(0, <[BoneLengths]>::len)
            )))
        }
    };
    let pool = training_samples(seqs, cfg.every);
    if pool.is_empty() {
        return Err(TrainError::Data("no training frames".into()));
    }
    let val_idx = held_out_samples(seqs, cfg.every, cfg.val_samples);
    let run = RunDir::create(out)?;
    let schedule = cfg.schedule();

    let (net, varmap) = super::build(&cfg.arch, cfg.seed)?;
    if let Some(init) = &cfg.init_weights {
        // A resumed run overwrites these with the checkpoint below.
        let (meta, tensors) = weights::read_lifter(init)?;
        if meta.arch != cfg.arch {
            return Err(TrainError::InvalidArgument(format!(
                "{} is a {:?}, the run trains a {:?}",
                init.display(),
                meta.arch,
                cfg.arch
            )));
        }
        weights::assign(&varmap, &tensors, init)?;
    }
    let vars = trainable_vars(&varmap)?;
    let n_params = vars.iter().map(|(_, v)| v.as_tensor().elem_count()).sum();
    let clip = (cfg.clip_norm > 0.0).then_some(cfg.clip_norm);
    let mut opt = Adam::new(
        n_params,
        AdamConfig {
            lr: cfg.lr,
            clip_norm: clip,
            ..Default::default()
        },
    );
    let mut start_step = 0;
    let mut elapsed_before = 0.0;
    let resumed = run.checkpoint_to_resume(resume);
    if let Some(ckpt_path) = &resumed {
        let bad = |msg: String| TrainError::Checkpoint {
            path: ckpt_path.clone(),
            msg,
        };
        let weights::TensorFile {
            tensors,
            metadata: header,
        } = weights::read(ckpt_path)?;
        let meta: CheckpointMeta<LifterTrainConfig> = serde_json::from_str(
            header
                .get(CHECKPOINT_KEY)
                .ok_or_else(|| bad(format!("no {CHECKPOINT_KEY} metadata")))?,
        )?;
        cfg.compatible(&meta.config).map_err(bad)?;
        weights::assign(&varmap, &tensors, ckpt_path)?;
        let moment = |name: &str| -> Result<Vec<f32>, TrainError> {
            match tensors.get(name) {
                Some(t) if t.elem_count() == n_params => Ok(t.to_vec1::<f32>()?),
                _ => Err(bad(format!("missing or misshaped {name}"))),
            }
        };
        opt.m = moment(ADAM_M)?;
        opt.v = moment(ADAM_V)?;
        opt.t = meta.adam_steps;
        start_step = meta.step;
        elapsed_before = meta.elapsed_s;
    }
    run.start_log(LOG_HEADER, resumed.is_some().then_some(start_step))?;
    run.write_config(cfg)?;
    let mut params = flatten_vars(&vars)?;
    let graph = AdjustmentGraph::new()?;
    let data = TrainingSet {
        seqs,
        pool: &pool,
        lengths,
        graph: &graph,
    };

    let clock = RunClock::start(elapsed_before);
    let mut checkpoints = CheckpointTimer::new(cfg.checkpoint_secs);
    let mut window = LogWindow::new();
    let mut validation = LifterValidation::default();
    let mut last_loss = f64::NAN;
    let mut step = start_step;
    while step < cfg.steps {
        let (loss_mm, norm) =
            train_step(cfg, net.as_ref(), &vars, &mut params, &mut opt, &data, step)?;
        step += 1;
        window.add(loss_mm, norm, cfg.batch);
        let rate = window.rate();
        let mean_loss = window.mean_loss();
        progress(step, cfg.steps, mean_loss, rate);

        let at_end = step == cfg.steps;
        if at_end || (cfg.val_every > 0 && step.is_multiple_of(cfg.val_every)) {
            validation = validate(net.as_ref(), seqs, &val_idx, lengths)?;
            last_loss = mean_loss;
            let columns = [validation.mpjpe_mm, validation.mpjpe_flip_mm];
            run.append_log(&window.row(step, &schedule, rate, &columns, clock.total_s()))?;
            window = LogWindow::new();
        }
        if checkpoints.due(at_end) {
            let meta = CheckpointMeta {
                step,
                adam_steps: opt.t,
                elapsed_s: clock.total_s(),
                config: cfg.clone(),
            };
            save_checkpoint(&run.checkpoint(), &varmap, &opt, &meta)?;
        }
    }
    let elapsed = clock.this_run_s();
    let mut meta = weights::metadata(cfg.arch, training_data, step);
    meta.extra
        .insert("train_config".into(), serde_json::to_string(cfg)?);
    meta.extra.insert(
        "train_wall_clock_s".into(),
        format!("{:.0}", elapsed_before + elapsed),
    );
    meta.extra.insert(
        "val_mpjpe_flip_mm".into(),
        format!("{:.2}", validation.mpjpe_flip_mm),
    );
    meta.extra.insert(
        "version".into(),
        format!("blapose-train {}", env!("CARGO_PKG_VERSION")),
    );
    let weights_path = run.weights();
    weights::save(&weights_path, &varmap, &meta)?;
    let steps_run = step - start_step;
    Ok(LifterTrainOutcome {
        weights: weights_path,
        validation,
        samples_per_s: (steps_run as usize * cfg.batch) as f64 / elapsed.max(1e-9),
        elapsed_s: elapsed,
        steps_run,
        train_loss_mm: last_loss,
    })
}

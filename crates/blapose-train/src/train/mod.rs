//! The bone-length training loop: synthetic batches in, L1 on bone
//! lengths, Adam with exponential decay, validation, checkpoints, resume.
//!
//! * **Schedule, run directory, log, checkpoints** are those of every
//!   trainer here ([`crate::run`]): the learning rate decays per
//!   `epoch_steps` steps, checkpoints are written atomically and
//!   `--resume` continues from the last one.
//! * **Loss.** Mean absolute error between predicted and sampled lengths
//!   (metres; logged in mm). For the online GRU, `per_frame_weight > 0` adds
//!   the same L1 on the *running mean* of the per-frame predictions (what an
//!   online session serves), averaged over all frames of the window.
//! * **Determinism.** Batch `step` depends only on `(seed, step)`
//!   ([`crate::synth::sample_rng`]), the dropout masks only on `(seed,
//!   step)`, the initial weights only on `seed`: a resumed run reproduces an
//!   uninterrupted one bit for bit (tested in `tests/integration/train_loop.rs`).
//! * **Network.** The hot loop is [`crate::fastnet`] (hand-written BPTT,
//!   checked against candle autograd on the reference model), not candle's
//!   autograd, which was ~5x slower here.
//! * **Configuration.** [`TrainConfig`] is stored in the checkpoint and, as
//!   JSON, in the weights' metadata (`train_config`, for provenance).
//!   What the weights expect as input is written beside it as the typed
//!   contract ([`TrainConfig::model_input`], [`blapose_model::input`]),
//!   which the server, the evaluation and the benchmarks read. Files
//!   written before an option was removed still parse: unknown fields are
//!   ignored, and a checkpoint that used a removed option is refused
//!   ([`removed_options`]).

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::sync::Arc;

use blapose_core::skeleton::NUM_BONES;
use blapose_model::input::KEY_TRAIN_CONFIG;
use blapose_model::weights::{self, LoadedWeights, WeightsMetadata};
use blapose_model::{ModelKind, DROPOUT};
use candle_core::{Device, Tensor};

use crate::adam::{Adam, AdamConfig, ParamEma};
use crate::dataset::EvalSequence;
use crate::error::TrainError;
use crate::fastnet::{FastNet, LossConfig};
use crate::loader::Prefetcher;
use crate::run::{
    read_tensor_file, write_atomic, CheckpointMeta, CheckpointTimer, LogWindow, RunClock, RunDir,
};
pub use crate::run::{Progress, LOG_FILE, WEIGHTS_FILE};
use crate::synth::{sample_rng, Batch, SynthConfig, SynthSource, FRAME_DIM};

mod config;

pub use config::{removed_options, TrainConfig};

/// Columns of the training log.
pub const LOG_HEADER: &str =
    "step,epoch,lr,train_loss_mm,grad_norm,frames_per_s,val_synth_mm,val_real_sh_mm,val_real_sh_running_mm,elapsed_s";
/// Seed offset of the fixed synthetic validation set.
const VAL_SEED_SALT: u64 = 0x05EE_D0F7_A11D;
/// Seed offset of the dropout masks.
const DROPOUT_SEED_SALT: u64 = 0xD0_0D_0D_0D;

/// Validation numbers (mm).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Validation {
    /// L1 on the fixed synthetic validation set (final-state prediction).
    pub synth_mm: f64,
    /// L1 on the training subjects' real SH windows with their true lengths.
    pub real_sh_mm: f64,
    /// For the GRU: the running mean of per-frame predictions on the same
    /// windows (what serving answers); NaN for the Bi-GRU.
    pub real_sh_running_mm: f64,
}

/// The fixed synthetic validation set (independent of the training stream).
pub fn validation_batches(
    source: &SynthSource,
    cfg: &SynthConfig,
    seed: u64,
    samples: usize,
    batch: usize,
) -> Vec<Batch> {
    let mut out = Vec::new();
    let mut i = 0;
    while i < samples {
        let n = batch.min(samples - i);
        let mut inputs = Vec::with_capacity(n * cfg.seq_len * FRAME_DIM);
        let mut targets = Vec::with_capacity(n * NUM_BONES);
        for k in 0..n {
            let s = source.sample(
                cfg,
                &mut sample_rng(seed ^ VAL_SEED_SALT, u64::MAX, (i + k) as u64),
            );
            inputs.extend_from_slice(&s.input);
            targets.extend_from_slice(&s.target);
        }
        out.push(Batch {
            batch: n,
            seq_len: cfg.seq_len,
            inputs,
            targets,
        });
        i += n;
    }
    out
}

/// Real-SH validation windows: from each sequence/camera the `frames`
/// frames in its middle (whole sequence when shorter is not possible:
/// sequences shorter than `frames` are skipped), batched by `batch`.
pub fn real_validation_batches(real: &[EvalSequence], frames: usize, batch: usize) -> Vec<Batch> {
    let windows: Vec<(&[f32], &[f32])> = real
        .iter()
        .filter(|s| s.frames() >= frames)
        .map(|s| {
            let start = (s.frames() - frames) / 2;
            (
                &s.input[start * FRAME_DIM..(start + frames) * FRAME_DIM],
                &s.gt[..],
            )
        })
        .collect();
    windows
        .chunks(batch.max(1))
        .map(|c| Batch {
            batch: c.len(),
            seq_len: frames,
            inputs: c.iter().flat_map(|w| w.0.iter().copied()).collect(),
            targets: c.iter().flat_map(|w| w.1.iter().copied()).collect(),
        })
        .collect()
}

fn l1_mm(pred: &[f32], target: &[f32]) -> f64 {
    pred.iter()
        .zip(target)
        .map(|(a, b)| f64::from((a - b).abs()))
        .sum::<f64>()
        * 1000.0
}

/// Run the validation sets through `net` (eval mode).
pub fn validate(net: &FastNet, synth: &[Batch], real: &[Batch]) -> Validation {
    let mut v = Validation {
        real_sh_running_mm: f64::NAN,
        ..Default::default()
    };
    let (mut s, mut n) = (0.0, 0usize);
    for b in synth {
        s += l1_mm(&net.predict(&b.inputs, b.batch, b.seq_len), &b.targets);
        n += b.targets.len();
    }
    v.synth_mm = s / n.max(1) as f64;
    let (mut s, mut n, mut sr) = (0.0, 0usize, 0.0);
    for b in real {
        match net.kind() {
            ModelKind::Gru => {
                let per = net.predict_per_frame(&b.inputs, b.batch, b.seq_len);
                let mut last = Vec::with_capacity(b.batch * NUM_BONES);
                let mut run = Vec::with_capacity(b.batch * NUM_BONES);
                for i in 0..b.batch {
                    let rows = &per[i * b.seq_len * NUM_BONES..(i + 1) * b.seq_len * NUM_BONES];
                    last.extend_from_slice(&rows[(b.seq_len - 1) * NUM_BONES..]);
                    for j in 0..NUM_BONES {
                        run.push(
                            rows.chunks_exact(NUM_BONES).map(|r| r[j]).sum::<f32>()
                                / b.seq_len as f32,
                        );
                    }
                }
                s += l1_mm(&last, &b.targets);
                sr += l1_mm(&run, &b.targets);
            }
            ModelKind::BiGru => s += l1_mm(&net.predict(&b.inputs, b.batch, b.seq_len), &b.targets),
        }
        n += b.targets.len();
    }
    v.real_sh_mm = s / n.max(1) as f64;
    if net.kind() == ModelKind::Gru {
        v.real_sh_running_mm = sr / n.max(1) as f64;
    }
    v
}

fn save_checkpoint(
    path: &Path,
    net: &FastNet,
    opt: &Adam,
    ema: Option<&ParamEma>,
    meta: &CheckpointMeta<TrainConfig>,
) -> Result<(), TrainError> {
    let mut tensors: BTreeMap<&str, Tensor> = BTreeMap::new();
    tensors.insert(
        "params",
        Tensor::from_slice(&net.params, net.params.len(), &Device::Cpu)?,
    );
    tensors.insert(
        "adam_m",
        Tensor::from_slice(&opt.m, opt.m.len(), &Device::Cpu)?,
    );
    tensors.insert(
        "adam_v",
        Tensor::from_slice(&opt.v, opt.v.len(), &Device::Cpu)?,
    );
    if let Some(e) = ema {
        tensors.insert(
            "ema",
            Tensor::from_slice(&e.values, e.values.len(), &Device::Cpu)?,
        );
    }
    let mut header = HashMap::new();
    header.insert(
        "blapose_checkpoint".to_string(),
        serde_json::to_string(meta)?,
    );
    let bytes = safetensors::serialize(tensors.iter().map(|(k, v)| (*k, v)), Some(header))
        .map_err(|e| TrainError::Checkpoint {
            path: path.into(),
            msg: e.to_string(),
        })?;
    write_atomic(path, &bytes)
}

/// A checkpoint read back: its metadata and its flat tensors by name.
type Checkpoint = (CheckpointMeta<TrainConfig>, BTreeMap<String, Vec<f32>>);

fn load_checkpoint(path: &Path) -> Result<Checkpoint, TrainError> {
    let bad = |msg: String| TrainError::Checkpoint {
        path: path.into(),
        msg,
    };
    let file = read_tensor_file(path)?;
    let meta_json = file
        .metadata
        .get("blapose_checkpoint")
        .ok_or_else(|| bad("no blapose_checkpoint metadata".into()))?;
    let raw: serde_json::Value = serde_json::from_str(meta_json).map_err(|e| bad(e.to_string()))?;
    let removed = removed_options(&raw["config"]);
    if !removed.is_empty() {
        return Err(bad(format!(
            "written with removed research options ({}); this trainer cannot continue it",
            removed.join(", ")
        )));
    }
    let meta = serde_json::from_str(meta_json).map_err(|e| bad(e.to_string()))?;
    let mut tensors = BTreeMap::new();
    for (name, t) in file.tensors {
        tensors.insert(name, t.flatten_all()?.to_vec1::<f32>()?);
    }
    Ok((meta, tensors))
}

/// What a finished run reports.
#[derive(Debug, Clone, PartialEq)]
pub struct TrainOutcome {
    /// Path of the final weights.
    pub weights: PathBuf,
    /// Last validation.
    pub validation: Validation,
    /// Mean training throughput of this invocation (frames/s).
    pub frames_per_s: f64,
    /// Wall-clock seconds of this invocation.
    pub elapsed_s: f64,
    /// Steps done in this invocation.
    pub steps_run: u64,
}

/// Train in `out` (created if needed). `source` must be built from the
/// training subjects only; `real_val` are their real SH sequences.
/// `training_data` goes into the weights' metadata.
pub fn train(
    cfg: &TrainConfig,
    source: Arc<SynthSource>,
    real_val: &[EvalSequence],
    out: &Path,
    resume: bool,
    training_data: &str,
    progress: Progress,
) -> Result<TrainOutcome, TrainError> {
    if cfg.batch == 0 || cfg.steps == 0 {
        return Err(TrainError::InvalidArgument(
            "batch and steps must be positive".into(),
        ));
    }
    let kind = cfg.kind;
    let synth = cfg.synth()?;
    let schedule = cfg.schedule();
    let run = RunDir::create(out)?;

    // The fixed validation sets.
    let val_synth = validation_batches(
        &source,
        &synth,
        cfg.seed,
        cfg.val_samples,
        cfg.batch.min(64),
    );
    let val_real = real_validation_batches(real_val, cfg.val_frames, 64);

    let mut net = match &cfg.init_weights {
        Some(path) => {
            let init = weights::load(Path::new(path), kind)?;
            FastNet::from_tensors(kind, init.tensors())?
        }
        None => {
            let init = LoadedWeights::random(kind, cfg.seed)?;
            let mut net = FastNet::from_tensors(kind, init.tensors())?;
            net.init_output_at(&source.sampler().stats().mean, 0.05);
            net
        }
    };
    let clip = (cfg.clip_norm > 0.0).then_some(cfg.clip_norm);
    let mut opt = Adam::new(
        net.params.len(),
        AdamConfig {
            lr: cfg.lr,
            clip_norm: clip,
            ..Default::default()
        },
    );
    if !(cfg.ema_decay >= 0.0 && cfg.ema_decay < 1.0 && cfg.head_lr_scale >= 0.0) {
        return Err(TrainError::InvalidArgument(
            "need 0 <= ema_decay < 1 and head_lr_scale >= 0".into(),
        ));
    }
    if cfg.head_lr_scale != 1.0 {
        opt.set_lr_groups(vec![(net.layout.fc_w.clone(), cfg.head_lr_scale)]);
    }
    let mut ema = (cfg.ema_decay > 0.0).then(|| ParamEma::new(&net.params, cfg.ema_decay));

    let mut start_step = 0u64;
    let mut elapsed_before = 0.0;
    let resumed = run.checkpoint_to_resume(resume);
    if let Some(ckpt_path) = &resumed {
        let (meta, mut tensors) = load_checkpoint(ckpt_path)?;
        cfg.compatible(&meta.config)
            .map_err(|msg| TrainError::Checkpoint {
                path: ckpt_path.clone(),
                msg,
            })?;
        let n = net.params.len();
        let mut take = |name: &str| -> Result<Vec<f32>, TrainError> {
            match tensors.remove(name) {
                Some(v) if v.len() == n => Ok(v),
                _ => Err(TrainError::Checkpoint {
                    path: ckpt_path.clone(),
                    msg: format!("missing or misshaped {name}"),
                }),
            }
        };
        net.params = take("params")?;
        opt.m = take("adam_m")?;
        opt.v = take("adam_v")?;
        if let Some(e) = ema.as_mut() {
            e.values = take("ema")?;
        }
        opt.t = meta.adam_steps;
        start_step = meta.step;
        elapsed_before = meta.elapsed_s;
    }
    run.start_log(LOG_HEADER, resumed.is_some().then_some(start_step))?;
    run.write_config(cfg)?;

    let clock = RunClock::start(elapsed_before);
    let mut checkpoints = CheckpointTimer::new(cfg.checkpoint_secs);
    let mut window = LogWindow::new();
    let mut validation = Validation::default();
    let mut frames_total = 0usize;
    let mut grad = vec![0.0f32; net.params.len()];
    let mut loader = Prefetcher::spawn(
        source.clone(),
        synth,
        cfg.seed,
        cfg.batch,
        start_step..cfg.steps,
        2,
    );
    if start_step == 0 {
        // Row 0: the untrained network (about the constant prior-mean
        // predictor, or the warm start), the bar every later row must beat.
        let v = validate(&net, &val_synth, &val_real);
        let row = format!(
            "0,0.000,{:.3e},NaN,NaN,NaN,{:.3},{:.3},{:.3},0.0\n",
            schedule.lr_at(0),
            v.synth_mm,
            v.real_sh_mm,
            v.real_sh_running_mm
        );
        run.append_log(&row)?;
    }
    let mut step = start_step;
    while let Some((s, batch)) = loader.next_batch() {
        opt.config.lr = schedule.lr_at(s);
        let loss_cfg = LossConfig {
            running_mean_weight: cfg.per_frame_weight,
            dropout: DROPOUT,
        };
        let mut drop_rng = sample_rng(cfg.seed ^ DROPOUT_SEED_SALT, s, 0);
        let res = net.train_step(
            &batch.inputs,
            &batch.targets,
            batch.batch,
            batch.seq_len,
            loss_cfg,
            &mut drop_rng,
            &mut grad,
        );
        if !res.loss.is_finite() {
            return Err(TrainError::Data(format!("non-finite loss at step {s}")));
        }
        let Some(norm) = opt.step(&mut net.params, &grad) else {
            return Err(TrainError::Data(format!("non-finite gradient at step {s}")));
        };
        if let Some(e) = ema.as_mut() {
            e.update(&net.params);
        }
        step = s + 1;
        let frames = batch.batch * batch.seq_len;
        frames_total += frames;
        window.add(res.final_l1 * 1000.0, norm, frames);
        let fps = window.rate();
        progress(step, cfg.steps, window.mean_loss(), fps);

        let at_end = step == cfg.steps;
        if at_end || (cfg.val_every > 0 && step.is_multiple_of(cfg.val_every)) {
            validation = validate(&averaged(&net, ema.as_ref()), &val_synth, &val_real);
            let v = &validation;
            let columns = [v.synth_mm, v.real_sh_mm, v.real_sh_running_mm];
            run.append_log(&window.row(step, &schedule, fps, &columns, clock.total_s()))?;
            window = LogWindow::new();
        }
        if checkpoints.due(at_end) {
            let meta = CheckpointMeta {
                step,
                adam_steps: opt.t,
                elapsed_s: clock.total_s(),
                config: cfg.clone(),
            };
            save_checkpoint(&run.checkpoint(), &net, &opt, ema.as_ref(), &meta)?;
        }
    }
    drop(loader);
    let elapsed = clock.this_run_s();
    let mut meta = WeightsMetadata::new(kind);
    meta.training_data = training_data.to_string();
    if cfg.rectify {
        meta.input_normalization = format!(
            "rectified (blapose_core::level: as a level camera at the same place sees them) {}",
            meta.input_normalization
        );
    }
    meta.version = format!("blapose-train {}", env!("CARGO_PKG_VERSION"));
    meta.input = Some(cfg.model_input());
    meta.extra
        .insert(KEY_TRAIN_CONFIG.into(), serde_json::to_string(cfg)?);
    meta.extra.insert("train_steps".into(), step.to_string());
    meta.extra.insert(
        "train_wall_clock_s".into(),
        format!("{:.0}", elapsed_before + elapsed),
    );
    let weights_path = run.weights();
    let saved = averaged(&net, ema.as_ref());
    let bytes = weights::to_bytes(&saved.to_tensors()?, &meta)?;
    write_atomic(&weights_path, &bytes)?;
    Ok(TrainOutcome {
        weights: weights_path,
        validation,
        frames_per_s: frames_total as f64 / elapsed.max(1e-9),
        elapsed_s: elapsed,
        steps_run: step - start_step,
    })
}

/// The network validation and the weights file see: `net` with the
/// parameter average when there is one.
fn averaged(net: &FastNet, ema: Option<&ParamEma>) -> FastNet {
    let mut out = net.clone();
    if let Some(e) = ema {
        out.params.copy_from_slice(&e.values);
    }
    out
}

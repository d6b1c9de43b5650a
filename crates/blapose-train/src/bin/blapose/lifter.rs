//! `blapose train-lifter` and `blapose finetune`: the lifter runs. Both
//! load the training subjects' streams and call
//! [`blapose_train::lifter::train::train`]; fine-tuning adds the frozen
//! Bi-GRU's lengths per stream (cached, they take minutes). Why one
//! module: the two commands share their run flags ([`LifterRunArgs`]) and
//! everything after them.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Result;
use blapose_core::BoneLengths;
use blapose_data::h36m::{H36m, Parts, TRAIN_SUBJECTS};
use blapose_train::eval_adjust::LengthEstimates;
use blapose_train::lifter::data::{lifter_sequences, LifterSequence};
use blapose_train::lifter::objective::Objective;
use blapose_train::lifter::train::LifterTrainConfig;
use blapose_train::lifter::{LifterArch, LifterKind, MlpArch, VideoPoseArch};
use clap::builder::PossibleValue;

use crate::common::step_bar;

/// The run flags `train-lifter` and `finetune` share.
#[derive(clap::Args, Debug)]
pub struct LifterRunArgs {
    /// Run directory (log, checkpoint, weights, curve).
    #[arg(long)]
    out: PathBuf,
    /// Continue from OUT/checkpoint.safetensors.
    #[arg(long)]
    resume: bool,
    /// Optimizer steps (train-lifter: 10,000; finetune: 2,000). 10,000 x 256
    /// samples of the MLP is about 50 minutes on the project's 2-core VM.
    #[arg(long)]
    steps: Option<u64>,
    /// Samples per batch.
    #[arg(long, default_value_t = 256)]
    batch: usize,
    /// Train on every k-th 50 Hz frame (consecutive frames are redundant).
    #[arg(long, default_value_t = 4)]
    every: usize,
    /// Initial learning rate (train-lifter: 1e-3; finetune: 1e-4).
    #[arg(long)]
    lr: Option<f64>,
    /// Learning-rate factor per epoch.
    #[arg(long, default_value_t = 0.95)]
    lr_decay: f64,
    /// Steps per "epoch" (the learning-rate decay period).
    #[arg(long, default_value_t = 500)]
    epoch_steps: u64,
    /// Clip the global gradient norm (0 = off).
    #[arg(long, default_value_t = 5.0)]
    clip_norm: f64,
    /// Probability of mirroring each training sample.
    #[arg(long, default_value_t = 0.5)]
    flip_prob: f32,
    /// Master seed (initial weights, batches, dropout).
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Validate every N steps.
    #[arg(long, default_value_t = 500)]
    val_every: u64,
    /// Held-out validation frames (training subjects, between training frames).
    #[arg(long, default_value_t = 8192)]
    val_samples: usize,
    /// Seconds between checkpoints.
    #[arg(long, default_value_t = 300)]
    checkpoint_secs: u64,
    /// Data root (default: $BLAPOSE_DATA or ../shared/data).
    #[arg(long)]
    data: Option<PathBuf>,
}

/// Arguments of `blapose train-lifter`.
#[derive(clap::Args, Debug)]
pub struct TrainLifterArgs {
    /// Lifter architecture: mlp (Martinez et al. 2017 residual MLP, one
    /// frame) or videopose (VideoPose3D-style temporal convolutions).
    #[arg(long, value_enum, default_value_t = ModelFlag(LifterKind::Mlp))]
    model: ModelFlag,
    #[command(flatten)]
    run: LifterRunArgs,
    /// mlp: hidden width.
    #[arg(long, default_value_t = 1024)]
    hidden: usize,
    /// Residual blocks (videopose: receptive field = filter width^(blocks+1),
    /// so 2 blocks of width 3 read 27 frames).
    #[arg(long, default_value_t = 2)]
    blocks: usize,
    /// Dropout probability (default: 0.5 for mlp, 0.25 for videopose).
    #[arg(long)]
    dropout: Option<f32>,
    /// videopose: filter width of every layer (odd).
    #[arg(long, default_value_t = 3)]
    filter_width: usize,
    /// videopose: convolution channels.
    #[arg(long, default_value_t = 512)]
    channels: usize,
    /// videopose: causal convolutions (the output is the window's last
    /// frame; the variant for online use).
    #[arg(long)]
    causal: bool,
}

/// `--model`: a [`LifterKind`] as a clap value (the library type has no
/// clap), spelled and described as the library spells and describes it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ModelFlag(LifterKind);

impl ModelFlag {
    /// Every kind; an added one fails to compile here until listed.
    const ALL: [ModelFlag; LifterKind::ALL.len()] = {
        let [a, b] = LifterKind::ALL;
        [ModelFlag(a), ModelFlag(b)]
    };
}

impl clap::ValueEnum for ModelFlag {
    fn value_variants<'a>() -> &'a [Self] {
        &Self::ALL
    }

    fn to_possible_value(&self) -> Option<PossibleValue> {
        Some(PossibleValue::new(self.0.as_str()).help(self.0.description()))
    }
}

/// Arguments of `blapose finetune`.
#[derive(clap::Args, Debug)]
pub struct FinetuneArgs {
    /// Lifter weights to start from (written by `blapose train-lifter`).
    #[arg(long)]
    lifter_weights: PathBuf,
    /// The frozen bone-length model whose lengths the poses are adjusted to
    /// (offline Bi-GRU, one estimate per training stream).
    #[arg(long, default_value = "models/bone_length_bigru.safetensors")]
    bigru_weights: PathBuf,
    /// Cache of the frozen model's per-stream lengths (JSON; reused when it
    /// names the same Bi-GRU file and streams, written otherwise). Default:
    /// OUT/frozen_lengths.json.
    #[arg(long)]
    lengths_cache: Option<PathBuf>,
    /// adjusted (L_direction + L_MPJPE after adjustment, the paper's) or
    /// mpjpe (plain lifter MPJPE: the control that separates the effect of
    /// the objective from that of more training).
    #[arg(long, value_enum, default_value_t = Objective::Adjusted)]
    objective: Objective,
    /// Weight of L_direction in the adjusted objective (the paper: 1; 0 =
    /// L_MPJPE of the adjusted pose only).
    #[arg(long, default_value_t = 1.0)]
    direction_weight: f64,
    #[command(flatten)]
    run: LifterRunArgs,
}

/// `blapose train-lifter`.
pub fn train_lifter(a: TrainLifterArgs) -> Result<()> {
    let arch = match a.model.0 {
        LifterKind::Mlp => LifterArch::Mlp(MlpArch {
            hidden: a.hidden,
            blocks: a.blocks,
            dropout: a.dropout.unwrap_or(MlpArch::default().dropout),
        }),
        LifterKind::VideoPose => LifterArch::VideoPose(VideoPoseArch {
            filter_width: a.filter_width,
            blocks: a.blocks,
            channels: a.channels,
            dropout: a.dropout.unwrap_or(VideoPoseArch::default().dropout),
            causal: a.causal,
        }),
    };
    run_lifter_training(
        &a.run,
        arch,
        None,
        (Objective::Mpjpe, 1.0),
        (10_000, 1e-3),
        |_| Ok(None),
    )
}

/// `blapose finetune`.
pub fn finetune(a: FinetuneArgs) -> Result<()> {
    let (meta, _) = blapose_train::lifter::weights::read_lifter(&a.lifter_weights)?;
    let objective = a.objective;
    let init = Some(a.lifter_weights.clone());
    let goal = (objective, a.direction_weight);
    run_lifter_training(&a.run, meta.arch, init, goal, (2_000, 1e-4), |seqs| {
        if objective == Objective::Mpjpe {
            return Ok(None);
        }
        let cache = a
            .lengths_cache
            .clone()
            .unwrap_or_else(|| a.run.out.join("frozen_lengths.json"));
        let key = FrozenLengths {
            bigru_weights: a.bigru_weights.display().to_string(),
            streams: seqs
                .iter()
                .map(|s| {
                    format!(
                        "{}/{}/{}",
                        s.trial.subject, s.trial.sequence, s.trial.camera
                    )
                })
                .collect(),
            lengths: Vec::new(),
        };
        if let Some(hit) = std::fs::read_to_string(&cache)
            .ok()
            .and_then(|t| serde_json::from_str::<FrozenLengths>(&t).ok())
            .filter(|c| c.bigru_weights == key.bigru_weights && c.streams == key.streams)
        {
            eprintln!("frozen Bi-GRU lengths: {}", cache.display());
            return Ok(Some(hit.lengths));
        }
        let t = Instant::now();
        let bigru =
            blapose_model::weights::load(&a.bigru_weights, blapose_model::ModelKind::BiGru)?;
        let lengths = LengthEstimates::compute(seqs, None, Some(&bigru))?
            .bigru
            .unwrap_or_default();
        eprintln!(
            "frozen Bi-GRU lengths for {} training streams: {:.1}s",
            lengths.len(),
            t.elapsed().as_secs_f64()
        );
        if let Some(dir) = cache.parent() {
            std::fs::create_dir_all(dir)?;
        }
        let store = FrozenLengths {
            lengths: lengths.clone(),
            ..key
        };
        std::fs::write(&cache, serde_json::to_string(&store)?)?;
        Ok(Some(lengths))
    })
}

/// The frozen model's lengths per training stream, cached between
/// fine-tuning runs (computing them takes minutes).
#[derive(serde::Serialize, serde::Deserialize)]
struct FrozenLengths {
    bigru_weights: String,
    streams: Vec<String>,
    lengths: Vec<BoneLengths>,
}

/// Load the training subjects, train `objective` (with its direction
/// weight) from `init` (fine-tuning)
/// or from scratch, with the per-stream lengths `lengths_for` returns, plot
/// the curve and print the outcome. `defaults` are `(steps, lr)` when not
/// given.
fn run_lifter_training(
    a: &LifterRunArgs,
    arch: LifterArch,
    init: Option<PathBuf>,
    (objective, direction_weight): (Objective, f64),
    defaults: (u64, f64),
    lengths_for: impl FnOnce(&[LifterSequence]) -> Result<Option<Vec<BoneLengths>>>,
) -> Result<()> {
    let root = blapose_data::data_root(a.data.clone());
    let cfg = LifterTrainConfig {
        arch,
        every: a.every,
        batch: a.batch,
        steps: a.steps.unwrap_or(defaults.0),
        epoch_steps: a.epoch_steps,
        lr: a.lr.unwrap_or(defaults.1),
        lr_decay: a.lr_decay,
        clip_norm: a.clip_norm,
        flip_prob: a.flip_prob,
        seed: a.seed,
        val_every: a.val_every,
        val_samples: a.val_samples,
        checkpoint_secs: a.checkpoint_secs,
        objective,
        direction_weight,
        init_weights: init,
    };
    let t0 = Instant::now();
    let seqs = {
        let h36m = H36m::load(&root, &TRAIN_SUBJECTS, Parts::ALL)?;
        lifter_sequences(&h36m, &TRAIN_SUBJECTS)?
    };
    let frames: usize = seqs.iter().map(|s| s.frames()).sum();
    eprintln!(
        "data: {} streams (sequence x camera), {frames} frames ({} for training at every {}), loaded in {:.1}s",
        seqs.len(),
        frames.div_ceil(cfg.every.max(1)),
        cfg.every,
        t0.elapsed().as_secs_f64()
    );
    let lengths = lengths_for(&seqs)?;
    let mut training_data = format!(
        "Human3.6M {} (all cameras), Stacked Hourglass detections mapped to H36M-17, every {} frame(s), flip p={}",
        TRAIN_SUBJECTS.join(" "),
        cfg.every,
        cfg.flip_prob
    );
    if let Some(init) = &cfg.init_weights {
        training_data.push_str(&format!(
            "; fine-tuned from {} with {}",
            init.display(),
            match cfg.objective {
                Objective::Adjusted =>
                    "L_direction + L_MPJPE through the bone-length adjustment (frozen Bi-GRU lengths)",
                Objective::Mpjpe => "the plain MPJPE objective (control)",
            }
        ));
    }
    let pb = step_bar(cfg.steps);
    let mut progress = |step: u64, _total: u64, loss: f64, rate: f64| {
        pb.set_position(step);
        pb.set_message(format!("loss {loss:.1} mm, {rate:.0} samples/s"));
    };
    let outcome = blapose_train::lifter::train::train(
        &cfg,
        &seqs,
        lengths.as_deref(),
        &a.out,
        a.resume,
        &training_data,
        &mut progress,
    )?;
    pb.finish();
    let curve = a.out.join("curve.svg");
    blapose_train::plot::lifter_training_curve(&a.out.join(blapose_train::run::LOG_FILE), &curve)?;
    println!(
        "trained {} steps in {:.0}s ({:.0} samples/s); training loss {:.1} mm; held-out MPJPE {:.1} mm ({:.1} mm with test-time flip){}",
        outcome.steps_run,
        outcome.elapsed_s,
        outcome.samples_per_s,
        outcome.train_loss_mm,
        outcome.validation.mpjpe_mm,
        outcome.validation.mpjpe_flip_mm,
        if lengths.is_some() { ", after adjustment" } else { "" }
    );
    println!("weights: {}", outcome.weights.display());
    println!("curve: {}", curve.display());
    Ok(())
}

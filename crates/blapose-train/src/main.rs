//! The `blapose` command line (see `blapose --help`).

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

use anyhow::Result;
use blapose_core::skeleton::BONE_NAMES;
use blapose_core::BoneLengths;
use blapose_train::ansur::{load_population, AnsurPopulation};
use blapose_train::dataset::{rectify_streams, TrainingSet};
use blapose_train::detector_gain::DetectorGain;
use blapose_train::lengths::{LengthSampler, LengthStrategy, TrainingLengthStats};
use blapose_train::lifter::objective::Objective;
use blapose_train::synth::{SynthConfig, SynthSource};
use blapose_train::train::TrainConfig;
use clap::{Parser, Subcommand};
use indicatif::{ProgressBar, ProgressStyle};

#[derive(Parser)]
#[command(
    name = "blapose",
    version,
    about = "Train and evaluate the BLAPose bone-length models",
    // A flag given twice takes its last value, so scripts can append
    // overrides to a fixed recipe.
    args_override_self = true
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

/// Arguments of `blapose train`.
#[derive(clap::Args, Debug)]
struct TrainArgs {
    /// Model kind: gru (online) or bigru (offline).
    #[arg(long, default_value = "bigru")]
    model: String,
    /// Bone-length sampling strategy: true|uniform|normal|ansur.
    #[arg(long, default_value = "ansur")]
    lengths: String,
    /// ansur only: scale each bone's spread to this multiple of the training
    /// subjects' std, keeping the survey's correlations (e.g. 1.25). 0 keeps
    /// the survey's own spread (the shipped weights' recipe), which is far
    /// wider than Human3.6M's for thorax, calf and forearm.
    #[arg(long, default_value_t = 0.0)]
    ansur_spread: f32,
    /// 2D detector-noise model: none|gaussian|residual.
    #[arg(long, default_value = "residual")]
    noise: String,
    /// Scale the noise's deviation from the residuals' per-joint mean (1 =
    /// as measured on the training subjects, whose detections the SH
    /// detector was fine-tuned on).
    #[arg(long, default_value_t = 1.0)]
    noise_scale: f32,
    /// Run directory (log, checkpoint, weights, curve).
    #[arg(long)]
    out: PathBuf,
    /// Continue from OUT/checkpoint.safetensors.
    #[arg(long)]
    resume: bool,
    /// Optimizer steps.
    #[arg(long, default_value_t = 2000)]
    steps: u64,
    /// Steps per "epoch" (the learning rate is multiplied by --lr-decay each epoch).
    #[arg(long, default_value_t = 100)]
    epoch_steps: u64,
    /// Frames per training window.
    #[arg(long, default_value_t = 64)]
    seq_len: usize,
    /// Samples per batch.
    #[arg(long, default_value_t = 64)]
    batch: usize,
    /// Initial learning rate.
    #[arg(long, default_value_t = 1e-4)]
    lr: f64,
    /// Learning-rate factor per epoch.
    #[arg(long, default_value_t = 0.95)]
    lr_decay: f64,
    /// Clip the global gradient norm (0 = off).
    #[arg(long, default_value_t = 5.0)]
    clip_norm: f64,
    /// Smallest playback stride in 50 Hz frames (50/60: 60 fps streams).
    #[arg(long, default_value_t = 50.0 / 60.0)]
    stride_min: f32,
    /// Largest playback stride (2.0: 25 fps streams).
    #[arg(long, default_value_t = 2.0)]
    stride_max: f32,
    /// Std of the per-sequence 3D shift, metres.
    #[arg(long, default_value_t = 0.5)]
    shift_std: f32,
    /// Where the shift is drawn: camera (all three camera axes, the paper's
    /// recipe) or ground (along the world floor, so the feet's image height
    /// still tells the distance).
    #[arg(long, default_value = "camera")]
    shift_plane: String,
    /// Keep each frame's lowest joint at its original height when the bone
    /// lengths are replaced (otherwise longer legs push the feet through
    /// the floor and shorter ones lift them off it).
    #[arg(long)]
    floor_contact: bool,
    /// Show each drawn body as the 2D detector would: per bone, only the
    /// fraction of the change in length that the training subjects' real
    /// detections follow (fitted on them; e.g. the hips about a third).
    #[arg(long)]
    detector_gain: bool,
    /// Train on root-relative, standardized coordinates (a fixed map folded
    /// into the first layer of the saved weights, which read raw
    /// coordinates as always); speeds up learning the small differences
    /// between joints.
    #[arg(long)]
    precondition: bool,
    /// Move the camera up or down by N(0, this) metres per sample: each
    /// Human3.6M session calibrated its cameras anew, centimetres apart.
    #[arg(long, default_value_t = 0.0)]
    camera_height_std: f32,
    /// Turn the camera by N(0, this) degrees about each of its axes per
    /// sample.
    #[arg(long, default_value_t = 0.0)]
    camera_angle_std: f32,
    /// Turn each training window about the vertical by a random angle, so
    /// the cameras see every motion from any side (the recorded heading
    /// when the turned person would leave the picture).
    #[arg(long)]
    random_yaw: bool,
    /// Draw each body's proportions and its overall size independently
    /// (two draws of the length strategy): size then cannot be guessed
    /// from proportions, only from the geometry of the picture.
    #[arg(long)]
    decouple_size: bool,
    /// Synthesize through these cameras only (ids, comma separated; default
    /// all four). With one camera its geometry is fixed and known to the
    /// model, which the four together are not.
    #[arg(long, value_delimiter = ',')]
    cameras: Vec<String>,
    /// Give the network the keypoints as a level camera at the same place
    /// would see them (blapose_core::level): such a model needs each view's
    /// calibration, which the server gets from a session's `camera`;
    /// evaluate with `eval --rectify`.
    #[arg(long)]
    rectify: bool,
    /// With --rectify: targets as seen from a camera at the reference height
    /// (1.56 m), so every target agrees with its rectified picture; such a
    /// model's estimates are scaled by the camera's height (`eval
    /// --height-correction`, the server's CameraCalibration.height).
    #[arg(long, requires = "rectify")]
    height_normalized: bool,
    /// Horizontal flip probability.
    #[arg(long, default_value_t = 0.5)]
    flip_prob: f32,
    /// GRU only: weight of the L1 loss on the running mean of per-frame predictions.
    #[arg(long, default_value_t = 0.0)]
    per_frame_weight: f32,
    /// Initialize the output layer at the training mean lengths (false: PyTorch's random init).
    #[arg(long, default_value_t = true, action = clap::ArgAction::Set)]
    init_output_mean: bool,
    /// Warm start: initial weights from this file (same model kind), e.g.
    /// to continue training shipped weights with a new schedule.
    #[arg(long)]
    init_weights: Option<PathBuf>,
    /// Learning-rate multiplier of the output layer (its 1,024 inputs add
    /// up Adam's per-weight steps, so at the base rate predictions jitter
    /// by centimetres; runs with 1 never beat the constant predictor).
    #[arg(long, default_value_t = 0.01)]
    head_lr_scale: f32,
    /// Validate and save an exponential moving average of the weights with
    /// this decay per step (0 = off). Runs from before this option: resume
    /// them with `--head-lr-scale 1 --ema-decay 0`.
    #[arg(long, default_value_t = 0.999)]
    ema_decay: f32,
    /// Master seed (data, initial weights).
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Validate every N steps.
    #[arg(long, default_value_t = 100)]
    val_every: u64,
    /// Synthetic validation samples.
    #[arg(long, default_value_t = 256)]
    val_samples: usize,
    /// Frames per real-SH validation window (training subjects).
    #[arg(long, default_value_t = 128)]
    val_frames: usize,
    /// Seconds between checkpoints.
    #[arg(long, default_value_t = 300)]
    checkpoint_secs: u64,
    /// Data root (default: $BLAPOSE_DATA or ../shared/data).
    #[arg(long)]
    data: Option<PathBuf>,
}

/// Arguments of `blapose eval`.
#[derive(clap::Args, Debug)]
struct EvalArgs {
    /// Model kind: gru (online, running mean) or bigru (offline).
    #[arg(long)]
    model: String,
    /// 2D input: sh (real Stacked Hourglass detections) or gt (projected ground truth).
    #[arg(long, default_value = "sh")]
    input: String,
    /// Weights file (safetensors written by `blapose train`).
    #[arg(long)]
    weights: PathBuf,
    /// Write the full report as JSON here.
    #[arg(long)]
    json: Option<PathBuf>,
    /// Write the error-vs-frames plot (SVG) here (online GRU).
    #[arg(long)]
    plot: Option<PathBuf>,
    /// Subjects to evaluate (comma separated).
    #[arg(long, default_value = "S9,S11", value_delimiter = ',')]
    subjects: Vec<String>,
    /// Bi-GRU only: average the estimates of consecutive windows of this
    /// many frames instead of one pass over the whole sequence (0 = whole).
    #[arg(long, default_value_t = 0)]
    chunk: usize,
    /// Test-time flip: average the estimates of each trial and of its
    /// mirror image (twice the compute).
    #[arg(long)]
    flip_average: bool,
    /// Feed the model a stream of this many frames per second (the 50 Hz
    /// data linearly resampled; e.g. 25 or 60).
    #[arg(long, default_value_t = 50.0)]
    fps: f32,
    /// Start every trial this many 50 Hz frames in (a stream joined mid-way;
    /// shows whether an online error curve depends on the state's age or on
    /// how the recordings begin).
    #[arg(long, default_value_t = 0)]
    skip_frames: usize,
    /// With --rectify: scale each view's estimate by its camera's height
    /// over the reference height 1.56 m (blapose_core::level::height_scale),
    /// for models trained with `--height-normalized` (a rectified model
    /// cannot see the height; the scene scales with it).
    #[arg(long, requires = "rectify")]
    height_correction: bool,
    /// Evaluate the trials of these cameras only (ids, comma separated;
    /// default all).
    #[arg(long, value_delimiter = ',')]
    cameras: Vec<String>,
    /// Rectify every trial's keypoints with its camera's calibration, for
    /// models trained with `train --rectify`.
    #[arg(long)]
    rectify: bool,
    /// Evaluate only every k-th trial (quick subsets; 1 = all).
    #[arg(long, default_value_t = 1)]
    every: usize,
    /// Data root (default: $BLAPOSE_DATA or ../shared/data).
    #[arg(long)]
    data: Option<PathBuf>,
}

/// The run flags `train-lifter` and `finetune` share.
#[derive(clap::Args, Debug)]
struct LifterRunArgs {
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
struct TrainLifterArgs {
    /// Lifter architecture: mlp (Martinez et al. 2017 residual MLP, one
    /// frame) or videopose (VideoPose3D-style temporal convolutions).
    #[arg(long, default_value = "mlp")]
    model: String,
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

/// Arguments of `blapose finetune`.
#[derive(clap::Args, Debug)]
struct FinetuneArgs {
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
    #[arg(long, default_value = "adjusted")]
    objective: String,
    /// Weight of L_direction in the adjusted objective (the paper: 1; 0 =
    /// L_MPJPE of the adjusted pose only).
    #[arg(long, default_value_t = 1.0)]
    direction_weight: f64,
    #[command(flatten)]
    run: LifterRunArgs,
}

/// Arguments of `blapose eval-adjust`.
#[derive(clap::Args, Debug)]
struct EvalAdjustArgs {
    /// Lifter weights written by `blapose train-lifter` (repeat or comma
    /// separate for several lifters).
    #[arg(long, required = true, value_delimiter = ',')]
    lifter_weights: Vec<PathBuf>,
    /// Online GRU weights ("none" to skip).
    #[arg(long, default_value = "models/bone_length_gru.safetensors")]
    gru_weights: PathBuf,
    /// Offline Bi-GRU weights ("none" to skip).
    #[arg(long, default_value = "models/bone_length_bigru.safetensors")]
    bigru_weights: PathBuf,
    /// Write the report as JSON here.
    #[arg(long)]
    json: Option<PathBuf>,
    /// Evaluate only every k-th trial (quick subsets; 1 = all).
    #[arg(long, default_value_t = 1)]
    every: usize,
    /// Subjects to evaluate (comma separated).
    #[arg(long, default_value = "S9,S11", value_delimiter = ',')]
    subjects: Vec<String>,
    /// Turn test-time flip off.
    #[arg(long)]
    no_flip: bool,
    /// Data root (default: $BLAPOSE_DATA or ../shared/data).
    #[arg(long)]
    data: Option<PathBuf>,
}

#[derive(Subcommand)]
enum Command {
    /// Evaluate bone-length predictions on Human3.6M (default S9 and S11,
    /// all cameras, all sequences) beside the naive baselines.
    Eval(Box<EvalArgs>),
    /// Time training steps of the hand-written network on random input
    /// (prints frames_per_second=...).
    BenchTrain {
        /// gru or bigru.
        #[arg(long, default_value = "bigru")]
        model: String,
        /// Samples per batch.
        #[arg(long, default_value_t = 64)]
        batch: usize,
        /// Frames per window.
        #[arg(long, default_value_t = 64)]
        seq_len: usize,
        /// Timed steps (after one warm-up step).
        #[arg(long, default_value_t = 5)]
        steps: usize,
        /// Weight of the running-mean loss (GRU).
        #[arg(long, default_value_t = 0.0)]
        per_frame_weight: f32,
    },
    /// Train a bone-length model on synthetic sequences built from the
    /// Human3.6M training subjects (S1 S5 S6 S7 S8).
    Train(Box<TrainArgs>),
    /// Train a 2D-to-3D lifter on the training subjects' real Stacked
    /// Hourglass detections (root-relative camera-space MPJPE, flip
    /// augmentation).
    TrainLifter(Box<TrainLifterArgs>),
    /// Fine-tune a lifter through the bone-length adjustment (L_direction +
    /// L_MPJPE of the pose rebuilt with the frozen Bi-GRU's lengths).
    Finetune(Box<FinetuneArgs>),
    /// Score lifters on S9/S11 before and after the bone-length adjustment
    /// (online GRU running estimate, offline Bi-GRU): the paper's Tables 2
    /// and 3.
    EvalAdjust(Box<EvalAdjustArgs>),
    /// Print the training data statistics, the ANSUR calibration and the
    /// detector residuals; time the augmentation pipeline.
    DataReport {
        /// Data root (default: $BLAPOSE_DATA or ../shared/data).
        #[arg(long)]
        data: Option<PathBuf>,
    },
}

/// The progress bar of a training run (`steps` optimizer steps).
fn step_bar(steps: u64) -> ProgressBar {
    let pb = ProgressBar::new(steps);
    pb.set_style(
        ProgressStyle::with_template("{elapsed_precise} [{bar:30}] {pos}/{len} eta {eta} {msg}")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    pb
}

fn main() -> Result<()> {
    let cli = Cli::parse();
    match cli.command {
        Command::DataReport { data } => data_report(data),
        Command::Train(args) => train(*args),
        Command::Eval(args) => eval(*args),
        Command::TrainLifter(args) => train_lifter(*args),
        Command::Finetune(args) => finetune(*args),
        Command::EvalAdjust(args) => eval_adjust(*args),
        Command::BenchTrain {
            model,
            batch,
            seq_len,
            steps,
            per_frame_weight,
        } => bench_train(&model, batch, seq_len, steps, per_frame_weight),
    }
}

fn data_report(data: Option<PathBuf>) -> Result<()> {
    let root = blapose_data::data_root(data);
    let t0 = Instant::now();
    let set = TrainingSet::load(&root)?;
    println!(
        "loaded {} training sequences in {:.1}s",
        set.sequences.len(),
        t0.elapsed().as_secs_f64()
    );
    let stats = TrainingLengthStats::from_training(&set.lengths_list())?;
    let pop: AnsurPopulation = load_population(&root, &stats)?;
    let (pm, ps) = pop.moments();
    println!("| bone | train mean mm | train std mm | ANSUR scale | ANSUR std mm |");
    println!("|---|---|---|---|---|");
    for b in 0..16 {
        println!(
            "| {} | {:.1} | {:.1} | {:.3} | {:.1} (mean {:.1}) |",
            BONE_NAMES[b],
            stats.mean[b] * 1000.0,
            stats.std[b] * 1000.0,
            pop.scale[b],
            ps[b] * 1000.0,
            pm[b] * 1000.0
        );
    }
    let bank = &set.residuals;
    println!(
        "residual bank: {} frames; per-joint std (mm at subject) x/y and mean:",
        bank.frames()
    );
    for j in 0..17 {
        println!(
            "  {:>10}: std {:5.1} {:5.1}  mean {:6.1} {:6.1}",
            blapose_core::skeleton::JOINT_NAMES[j],
            bank.std()[j][0] * 1000.0,
            bank.std()[j][1] * 1000.0,
            bank.mean()[j][0] * 1000.0,
            bank.mean()[j][1] * 1000.0
        );
    }
    let gain = DetectorGain::fit(&set.subject_lengths, &set.image_bones)?;
    println!(
        "detector gain (SH bone change per true change, fitted on the training subjects): {}",
        format_gains(&gain)
    );
    let sampler = LengthSampler::new(LengthStrategy::Ansur, stats, Some(pop))?;
    let source = Arc::new(SynthSource::new(
        set.sequences.clone(),
        set.residuals.clone(),
        sampler,
    )?);
    let cfg = SynthConfig::default();
    let t0 = Instant::now();
    let n = 20;
    for step in 0..n {
        let b = source.batch(&cfg, 1, step, 64);
        std::hint::black_box(b);
    }
    let dt = t0.elapsed().as_secs_f64();
    println!(
        "synthesis: {:.0} frames/s (batch 64 x T {})",
        (n as usize * 64 * cfg.seq_len) as f64 / dt,
        cfg.seq_len
    );
    Ok(())
}

/// A `--cameras` list for messages: the ids, or `all` when none is given.
fn camera_list(ids: &[String]) -> String {
    if ids.is_empty() {
        "all".to_string()
    } else {
        ids.join(",")
    }
}

/// `name=gain` for every bone whose gain is not 1, or `unit`.
fn format_gains(g: &DetectorGain) -> String {
    if g.is_unit() {
        return "unit".into();
    }
    let parts: Vec<String> = g
        .gain
        .iter()
        .enumerate()
        .filter(|(_, &v)| v != 1.0)
        .map(|(b, v)| format!("{}={v:.2}", BONE_NAMES[b]))
        .collect();
    parts.join(" ")
}

fn train(a: TrainArgs) -> Result<()> {
    let root = blapose_data::data_root(a.data.clone());
    let strategy: LengthStrategy = a.lengths.parse()?;
    let cfg = TrainConfig {
        kind: a.model.parse::<blapose_model::ModelKind>()?.to_string(),
        lengths: strategy.to_string(),
        ansur_spread: if strategy == LengthStrategy::Ansur {
            a.ansur_spread
        } else {
            0.0
        },
        noise: a
            .noise
            .parse::<blapose_train::noise::NoiseKind>()?
            .to_string(),
        noise_scale: a.noise_scale,
        seq_len: a.seq_len,
        stride_min: a.stride_min,
        stride_max: a.stride_max,
        shift_std: a.shift_std,
        shift_plane: a
            .shift_plane
            .parse::<blapose_train::synth::ShiftPlane>()?
            .to_string(),
        floor_contact: a.floor_contact,
        detector_gain: a.detector_gain,
        precondition: a.precondition,
        camera_height_std: a.camera_height_std,
        camera_angle_std_deg: a.camera_angle_std,
        random_yaw: a.random_yaw,
        decouple_size: a.decouple_size,
        cameras: a.cameras.clone(),
        rectify: a.rectify,
        height_normalized: a.height_normalized,
        flip_prob: a.flip_prob,
        batch: a.batch,
        steps: a.steps,
        epoch_steps: a.epoch_steps,
        lr: a.lr,
        lr_decay: a.lr_decay,
        clip_norm: a.clip_norm,
        per_frame_weight: a.per_frame_weight,
        init_output_mean: a.init_output_mean,
        init_weights: a.init_weights.as_ref().map(|p| p.display().to_string()),
        head_lr_scale: a.head_lr_scale,
        ema_decay: a.ema_decay,
        seed: a.seed,
        val_every: a.val_every,
        val_samples: a.val_samples,
        val_frames: a.val_frames,
        checkpoint_secs: a.checkpoint_secs,
    };
    let t0 = Instant::now();
    let set = TrainingSet::load(&root)?;
    let stats = TrainingLengthStats::from_training(&set.lengths_list())?;
    let pop = if strategy == LengthStrategy::Ansur {
        let mut pop = load_population(&root, &stats)?;
        if cfg.ansur_spread > 0.0 {
            pop.match_spread(&stats, cfg.ansur_spread)?;
        }
        Some(pop)
    } else {
        None
    };
    let mut sampler = LengthSampler::new(strategy, stats, pop)?;
    if cfg.decouple_size {
        sampler = sampler.with_decoupled_size();
    }
    let gain = if cfg.detector_gain {
        let g = DetectorGain::fit(&set.subject_lengths, &set.image_bones)?;
        eprintln!("detector gain per bone: {}", format_gains(&g));
        g
    } else {
        DetectorGain::unit()
    };
    let source = Arc::new(
        SynthSource::new(set.sequences.clone(), set.residuals.clone(), sampler)?
            .with_detector_gain(gain)
            .with_cameras(&cfg.cameras)?,
    );
    if cfg.rectify {
        source.check_rectifiable()?;
    }
    eprintln!(
        "data: {} training sequences, {} real SH validation streams, loaded in {:.1}s",
        set.sequences.len(),
        set.real_sh.len(),
        t0.elapsed().as_secs_f64()
    );
    let training_data = format!(
        "Human3.6M S1 S5 S6 S7 S8, lengths={} (ansur spread {}), noise={} (x{}), seq_len={}, stride=[{:.3},{:.3}], shift_std={} m ({}), floor_contact={}, detector_gain={}, camera jitter={} m / {} deg, random yaw={}, size decoupled from proportions={}, cameras={}, rectified={}, height-normalized={}, flip={}",
        cfg.lengths, cfg.ansur_spread, cfg.noise, cfg.noise_scale, cfg.seq_len, cfg.stride_min, cfg.stride_max, cfg.shift_std, cfg.shift_plane, cfg.floor_contact, format_gains(source.detector_gain()), cfg.camera_height_std, cfg.camera_angle_std_deg, cfg.random_yaw, cfg.decouple_size, camera_list(&cfg.cameras), cfg.rectify, cfg.height_normalized, cfg.flip_prob
    );
    let pb = step_bar(cfg.steps);
    let mut progress = |step: u64, _total: u64, loss: f64, fps: f64| {
        pb.set_position(step);
        pb.set_message(format!("loss {loss:.2} mm, {fps:.0} frames/s"));
    };
    // The real validation streams as the model reads them.
    let mut real_sh = std::borrow::Cow::Borrowed(&set.real_sh[..]);
    let camera = |subject: &str, id: &str| {
        set.sequences
            .iter()
            .find(|s| s.subject == subject)
            .and_then(|s| s.cameras.iter().find(|c| c.id == id))
    };
    if cfg.rectify {
        rectify_streams(real_sh.to_mut(), camera)?;
    }
    if cfg.height_normalized {
        // Their targets as the model is asked for them.
        for t in real_sh.to_mut() {
            let cam = camera(&t.subject, &t.camera)
                .ok_or_else(|| anyhow::anyhow!("no camera {} for {}", t.camera, t.subject))?;
            let k = (1.0 / blapose_core::level::height_scale(cam.center[2])) as f32;
            t.gt = t.gt.map(|l| l * k);
        }
    }
    let outcome = blapose_train::train::train(
        &cfg,
        source,
        &real_sh,
        &a.out,
        a.resume,
        &training_data,
        &mut progress,
    )?;
    pb.finish();
    let curve = a.out.join("curve.svg");
    blapose_train::plot::training_curve(&a.out.join(blapose_train::train::LOG_FILE), &curve)?;
    println!(
        "trained {} steps in {:.0}s ({:.0} frames/s); validation: synthetic {:.2} mm, real SH (training subjects) {:.2} mm{}",
        outcome.steps_run,
        outcome.elapsed_s,
        outcome.frames_per_s,
        outcome.validation.synth_mm,
        outcome.validation.real_sh_mm,
        if outcome.validation.real_sh_running_mm.is_finite() {
            format!(", running mean {:.2} mm", outcome.validation.real_sh_running_mm)
        } else {
            String::new()
        }
    );
    println!("weights: {}", outcome.weights.display());
    println!("curve: {}", curve.display());
    Ok(())
}

fn bench_train(
    model: &str,
    batch: usize,
    seq_len: usize,
    steps: usize,
    per_frame_weight: f32,
) -> Result<()> {
    use blapose_train::fastnet::{FastNet, LossConfig};
    use rand::{Rng, SeedableRng};
    let kind: blapose_model::ModelKind = model.parse()?;
    let w = blapose_model::LoadedWeights::random(kind, 0)?;
    let net = FastNet::from_tensors(kind, w.tensors())?;
    let mut rng = rand::rngs::StdRng::seed_from_u64(0);
    let x: Vec<f32> = (0..batch * seq_len * 34)
        .map(|_| rng.random_range(-1.0f32..1.0))
        .collect();
    let y: Vec<f32> = (0..batch * 16)
        .map(|_| rng.random_range(0.1f32..0.5))
        .collect();
    let mut grad = vec![0.0f32; net.params.len()];
    let cfg = LossConfig {
        running_mean_weight: per_frame_weight,
        ..Default::default()
    };
    net.train_step(&x, &y, batch, seq_len, cfg, &mut rng, &mut grad);
    let t0 = Instant::now();
    for _ in 0..steps {
        net.train_step(&x, &y, batch, seq_len, cfg, &mut rng, &mut grad);
    }
    let dt = t0.elapsed().as_secs_f64();
    println!(
        "{model} batch {batch} seq_len {seq_len}: {:.3} s/step",
        dt / steps as f64
    );
    println!(
        "frames_per_second={:.0}",
        (batch * seq_len * steps) as f64 / dt
    );
    Ok(())
}

fn eval(a: EvalArgs) -> Result<()> {
    use blapose_data::h36m::{H36m, Parts, ALL_SUBJECTS, TRAIN_SUBJECTS};
    use blapose_train::dataset::{eval_sequences, subject_lengths, InputKind};
    use blapose_train::eval::{
        evaluate, markdown, BiGruEstimator, FlipAveraged, GruEstimator, HeightCorrected,
        LengthEstimator,
    };
    let root = blapose_data::data_root(a.data.clone());
    let kind: blapose_model::ModelKind = a.model.parse()?;
    let input: InputKind = a.input.parse()?;
    let weights = blapose_model::weights::load(&a.weights, kind)?;
    let subjects: Vec<&str> = a.subjects.iter().map(String::as_str).collect();
    if let Some(bad) = subjects.iter().find(|s| !ALL_SUBJECTS.contains(s)) {
        anyhow::bail!("unknown subject {bad} (known: {})", ALL_SUBJECTS.join(","));
    }
    let t0 = Instant::now();
    let all = H36m::load(&root, &ALL_SUBJECTS, Parts::POSES)?;
    let lengths = subject_lengths(&all);
    let parts = if input == InputKind::Sh {
        Parts::ALL
    } else {
        Parts::POSES
    };
    let h36m = H36m::load(&root, &subjects, parts)?;
    let mut trials = eval_sequences(&h36m, &subjects, input, &lengths)?;
    if !a.cameras.is_empty() {
        trials.retain(|t| a.cameras.contains(&t.camera));
    }
    if a.every > 1 {
        trials = trials.into_iter().step_by(a.every).collect();
    }
    if a.rectify {
        rectify_streams(&mut trials, |subject, id| h36m.cameras.get(subject, id))?;
    }
    if a.skip_frames > 0 {
        trials = trials.iter().map(|t| t.skipped(a.skip_frames)).collect();
    }
    if a.fps != blapose_train::dataset::SOURCE_FPS {
        trials = trials
            .iter()
            .map(|t| t.resampled(a.fps))
            .collect::<Result<_, _>>()?;
    }
    if trials.is_empty() {
        anyhow::bail!(
            "no trials for subjects {} (cameras: {})",
            a.subjects.join(","),
            camera_list(&a.cameras)
        );
    }
    eprintln!(
        "loaded {} trials in {:.1}s",
        trials.len(),
        t0.elapsed().as_secs_f64()
    );
    let mean_of = |names: &[&str]| -> Result<BoneLengths> {
        let ls: Vec<&BoneLengths> = names.iter().filter_map(|s| lengths.get(*s)).collect();
        anyhow::ensure!(ls.len() == names.len(), "missing subject lengths");
        Ok(std::array::from_fn(|b| {
            ls.iter().map(|l| l[b]).sum::<f32>() / ls.len() as f32
        }))
    };
    let baselines = [
        ("training_mean", mean_of(&TRAIN_SUBJECTS)?),
        ("all_subjects_mean", mean_of(&ALL_SUBJECTS)?),
    ];
    let model: Box<dyn LengthEstimator> = match kind {
        blapose_model::ModelKind::BiGru => Box::new(BiGruEstimator::new(&weights, a.chunk)?),
        blapose_model::ModelKind::Gru => Box::new(GruEstimator::new(&weights)?),
    };
    let (estimator, model_label): (Box<dyn LengthEstimator>, String) = if a.flip_average {
        (
            Box::new(FlipAveraged::new(model)),
            format!("{}+flip", kind.as_str()),
        )
    } else {
        (model, kind.as_str().to_string())
    };
    let (estimator, model_label): (Box<dyn LengthEstimator>, String) = if a.height_correction {
        let mut scales = std::collections::BTreeMap::new();
        for t in &trials {
            let cam = h36m
                .cameras
                .get(&t.subject, &t.camera)
                .ok_or_else(|| anyhow::anyhow!("no camera {} for {}", t.camera, t.subject))?;
            scales.insert(
                (t.subject.clone(), t.camera.clone()),
                blapose_core::level::height_scale(cam.center[2]) as f32,
            );
        }
        (
            Box::new(HeightCorrected::new(estimator, scales)),
            format!("{model_label}+height"),
        )
    } else {
        (estimator, model_label)
    };
    let report = evaluate(
        estimator.as_ref(),
        &trials,
        &baselines,
        &model_label,
        input.name(),
        &a.weights.display().to_string(),
        &a.subjects,
    )?;
    println!("{}", markdown(&report));
    println!(
        "model pass: {:.1}s for {} frames ({:.0} frames/s)",
        report.seconds,
        report.frames,
        report.frames as f64 / report.seconds.max(1e-9)
    );
    if let Some(p) = &a.json {
        std::fs::write(p, serde_json::to_string_pretty(&report)?)?;
    }
    if let Some(p) = &a.plot {
        if report.curve.is_empty() {
            eprintln!("no error curve for the offline model; plot not written");
        } else {
            blapose_train::plot::error_curve(&report, p)?;
            eprintln!("plot: {}", p.display());
        }
    }
    Ok(())
}

fn train_lifter(a: TrainLifterArgs) -> Result<()> {
    use blapose_train::lifter::mlp::MlpConfig;
    use blapose_train::lifter::temporal::TemporalConfig;
    use blapose_train::lifter::{LifterArch, LifterKind};
    let arch = match a.model.parse::<LifterKind>()? {
        LifterKind::Mlp => {
            let d = MlpConfig::default();
            LifterArch::Mlp(MlpConfig {
                hidden: a.hidden,
                blocks: a.blocks,
                dropout: a.dropout.unwrap_or(d.dropout),
            })
        }
        LifterKind::Temporal => {
            let d = TemporalConfig::default();
            LifterArch::Temporal(TemporalConfig {
                filter_width: a.filter_width,
                blocks: a.blocks,
                channels: a.channels,
                dropout: a.dropout.unwrap_or(d.dropout),
                causal: a.causal,
            })
        }
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

fn finetune(a: FinetuneArgs) -> Result<()> {
    use blapose_train::eval_adjust::LengthEstimates;
    let (meta, _) = blapose_train::lifter::weights::read_lifter(&a.lifter_weights)?;
    let objective = match a.objective.as_str() {
        "adjusted" => Objective::Adjusted,
        "mpjpe" => Objective::Mpjpe,
        other => anyhow::bail!("unknown objective {other:?} (adjusted, mpjpe)"),
    };
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
    arch: blapose_train::lifter::LifterArch,
    init: Option<PathBuf>,
    (objective, direction_weight): (Objective, f64),
    defaults: (u64, f64),
    lengths_for: impl FnOnce(
        &[blapose_train::lifter::data::LifterSequence],
    ) -> Result<Option<Vec<BoneLengths>>>,
) -> Result<()> {
    use blapose_data::h36m::{H36m, Parts, TRAIN_SUBJECTS};
    use blapose_train::lifter::data::lifter_sequences;
    use blapose_train::lifter::train::LifterTrainConfig;
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
    blapose_train::plot::lifter_training_curve(
        &a.out.join(blapose_train::train::LOG_FILE),
        &curve,
    )?;
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

fn eval_adjust(a: EvalAdjustArgs) -> Result<()> {
    use std::collections::BTreeMap;

    use blapose_data::h36m::{H36m, Parts, ALL_SUBJECTS};
    use blapose_train::eval_adjust::{evaluate_lifter, markdown, LengthEstimates};
    use blapose_train::lifter::data::lifter_sequences;
    use blapose_train::lifter::predict::StreamLifter;
    use blapose_train::lifter::weights as lifter_weights;
    let root = blapose_data::data_root(a.data.clone());
    let subjects: Vec<&str> = a.subjects.iter().map(String::as_str).collect();
    if let Some(bad) = subjects.iter().find(|s| !ALL_SUBJECTS.contains(s)) {
        anyhow::bail!("unknown subject {bad} (known: {})", ALL_SUBJECTS.join(","));
    }
    let skip = |p: &PathBuf| p.as_os_str() == "none";
    let mut lifters = BTreeMap::new();
    for p in &a.lifter_weights {
        let l = lifter_weights::load(p)?;
        let mut name = l.metadata.arch.name();
        if lifters.contains_key(&name) {
            name = p
                .file_stem()
                .map_or(name.clone(), |s| s.to_string_lossy().into_owned());
        }
        anyhow::ensure!(!lifters.contains_key(&name), "two lifters named {name}");
        lifters.insert(name, (p.clone(), l));
    }
    let t0 = Instant::now();
    let mut trials = {
        let h36m = H36m::load(&root, &subjects, Parts::ALL)?;
        lifter_sequences(&h36m, &subjects)?
    };
    if a.every > 1 {
        trials = trials.into_iter().step_by(a.every).collect();
    }
    anyhow::ensure!(!trials.is_empty(), "no trials for {}", a.subjects.join(","));
    eprintln!(
        "loaded {} trials ({} frames) in {:.1}s",
        trials.len(),
        trials.iter().map(|t| t.frames()).sum::<usize>(),
        t0.elapsed().as_secs_f64()
    );
    let load = |path: &PathBuf, kind| -> Result<Option<blapose_model::weights::LoadedWeights>> {
        Ok(if skip(path) {
            None
        } else {
            Some(blapose_model::weights::load(path, kind)?)
        })
    };
    let t = Instant::now();
    let estimates = LengthEstimates::compute(
        &trials,
        load(&a.gru_weights, blapose_model::ModelKind::Gru)?.as_ref(),
        load(&a.bigru_weights, blapose_model::ModelKind::BiGru)?.as_ref(),
    )?;
    eprintln!(
        "bone-length estimates (online GRU running, offline Bi-GRU): {:.1}s",
        t.elapsed().as_secs_f64()
    );
    let adjusters = estimates.adjusters();
    let mut reports = BTreeMap::new();
    for (name, (path, l)) in &lifters {
        let t = Instant::now();
        let lifter = StreamLifter::new(l)?;
        let lift =
            |s: &blapose_train::lifter::data::LifterSequence| lifter.lift(&s.trial, !a.no_flip);
        let mut report = evaluate_lifter(&trials, &lift, adjusters)?;
        report.weights = Some(path.display().to_string());
        reports.insert(name.clone(), report);
        eprintln!(
            "{name}: lifted and scored in {:.1}s",
            t.elapsed().as_secs_f64()
        );
    }
    println!("{}", markdown(&reports));
    if let Some(p) = &a.json {
        std::fs::write(p, serde_json::to_string_pretty(&reports)?)?;
        eprintln!("json: {}", p.display());
    }
    Ok(())
}

//! `blapose train`: its flags become a [`TrainConfig`], the training
//! subjects' data a [`SynthSource`]; [`blapose_train::train::train`] runs
//! it. Why here: the flags, their defaults (those of the paper's recipe
//! where it gives one) and the weights' `training_data` text are the
//! command's, not the library's.

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

use anyhow::Result;
use blapose_train::ansur_split::{AnsurPeople, AnsurSplit};
use blapose_train::dataset::{prepare_streams, undistort_streams, TrainingSet};
use blapose_train::lengths::{LengthSampler, LengthStrategy, TrainingLengthStats};
use blapose_train::noise::NoiseKind;
use blapose_train::synth::{ShiftPlane, SynthSource};
use blapose_train::train::TrainConfig;

use crate::common::{camera_list, step_bar, ModelArg};

/// Arguments of `blapose train`.
#[derive(clap::Args, Debug)]
pub struct TrainArgs {
    /// Model kind: gru (online) or bigru (offline).
    #[arg(long, value_enum, ignore_case = true, default_value_t = ModelArg::BiGru)]
    model: ModelArg,
    /// Bone-length sampling strategy.
    #[arg(long, value_enum, default_value_t = LengthStrategy::Ansur)]
    lengths: LengthStrategy,
    /// ansur only: scale each bone's spread to this multiple of the training
    /// subjects' std, keeping the survey's correlations (e.g. 1.25). 0 keeps
    /// the survey's own spread (the shipped weights' recipe), which is far
    /// wider than Human3.6M's for thorax, calf and forearm.
    #[arg(long, default_value_t = 0.0)]
    ansur_spread: f32,
    /// ansur only: which survey people to draw from: `train` leaves out the
    /// held-out split of the many-bodies benchmark (`blapose-lab
    /// bodies`); `all` draws from everyone, the shipped weights' recipe.
    #[arg(long, value_enum, default_value_t = AnsurPeople::Train)]
    ansur_people: AnsurPeople,
    /// 2D detector-noise model.
    #[arg(long, value_enum, default_value_t = NoiseKind::Residual)]
    noise: NoiseKind,
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
    #[arg(long, value_enum, default_value_t = ShiftPlane::Camera)]
    shift_plane: ShiftPlane,
    /// Keep each frame's lowest joint at its original height when the bone
    /// lengths are replaced (otherwise longer legs push the feet through
    /// the floor and shorter ones lift them off it).
    #[arg(long)]
    floor_contact: bool,
    /// Turn each training window about the vertical by a random angle, so
    /// the cameras see every motion from any side (the recorded heading
    /// when the turned person would leave the picture).
    #[arg(long)]
    random_yaw: bool,
    /// Synthesize through these cameras only (ids, comma separated; default
    /// all four). With one camera its geometry is fixed and known to the
    /// model, which the four together are not.
    #[arg(long, value_delimiter = ',')]
    cameras: Vec<String>,
    /// Give the network the keypoints as a level camera at the same place
    /// would see them (blapose_core::level): such a model needs each view's
    /// calibration, which the server gets from a session's `camera`;
    /// evaluate with `eval --calibrated`.
    #[arg(long)]
    rectify: bool,
    /// With --rectify: divide each frame's keypoints by the lowest joint's
    /// drop below the horizon, so the picture shows the body in units of
    /// the camera's height whatever the distance and lens
    /// (blapose_core::level::LevelCamera::scaled_to_floor).
    #[arg(long, requires = "rectify")]
    floor_scaled: bool,
    /// Share of samples (0-1) seen through a camera drawn from the
    /// many-bodies benchmark's wide distribution (height 0.5-3 m, any
    /// heading, tilt and field of view) instead of a recorded Human3.6M
    /// camera: for models that must work wherever a user puts the camera.
    #[arg(long, default_value_t = 0.0)]
    wide_cameras: f32,
    /// Horizontal flip probability.
    #[arg(long, default_value_t = 0.5)]
    flip_prob: f32,
    /// GRU only: weight of the L1 loss on the running mean of per-frame predictions.
    #[arg(long, default_value_t = 0.0)]
    per_frame_weight: f32,
    /// Warm start: initial weights from this file (same model kind), e.g.
    /// to continue training shipped weights with a new schedule. Without
    /// it the weights are random and the output layer starts at the
    /// training subjects' mean lengths.
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

impl TrainArgs {
    /// The run's configuration.
    pub fn config(&self) -> TrainConfig {
        TrainConfig {
            kind: self.model.into(),
            lengths: self.lengths,
            ansur_spread: if self.lengths == LengthStrategy::Ansur {
                self.ansur_spread
            } else {
                0.0
            },
            ansur_people: self.ansur_people,
            noise: self.noise,
            seq_len: self.seq_len,
            stride_min: self.stride_min,
            stride_max: self.stride_max,
            shift_std: self.shift_std,
            shift_plane: self.shift_plane,
            floor_contact: self.floor_contact,
            random_yaw: self.random_yaw,
            cameras: self.cameras.clone(),
            rectify: self.rectify,
            floor_scaled: self.floor_scaled,
            wide_cameras: self.wide_cameras,
            flip_prob: self.flip_prob,
            batch: self.batch,
            steps: self.steps,
            epoch_steps: self.epoch_steps,
            lr: self.lr,
            lr_decay: self.lr_decay,
            clip_norm: self.clip_norm,
            per_frame_weight: self.per_frame_weight,
            init_weights: self.init_weights.as_ref().map(|p| p.display().to_string()),
            head_lr_scale: self.head_lr_scale,
            ema_decay: self.ema_decay,
            seed: self.seed,
            val_every: self.val_every,
            val_samples: self.val_samples,
            val_frames: self.val_frames,
            checkpoint_secs: self.checkpoint_secs,
        }
    }
}

/// The weights' `training_data` text: the data and augmentation of `cfg`.
fn training_data(cfg: &TrainConfig) -> String {
    format!(
        "Human3.6M S1 S5 S6 S7 S8, lengths={} (ansur spread {}, people {}), noise={}, seq_len={}, stride=[{:.3},{:.3}], shift_std={} m ({}), floor_contact={}, random yaw={}, cameras={}, rectified={}{}, flip={}",
        cfg.lengths,
        cfg.ansur_spread,
        cfg.ansur_people,
        cfg.noise,
        cfg.seq_len,
        cfg.stride_min,
        cfg.stride_max,
        cfg.shift_std,
        cfg.shift_plane,
        cfg.floor_contact,
        cfg.random_yaw,
        camera_list(&cfg.cameras),
        cfg.rectify,
        if cfg.wide_cameras > 0.0 || cfg.floor_scaled {
            format!(
                ", floor-scaled={}, wide cameras={}",
                cfg.floor_scaled, cfg.wide_cameras
            )
        } else {
            String::new()
        },
        cfg.flip_prob
    )
}

/// `blapose train`.
pub fn run(a: TrainArgs) -> Result<()> {
    let root = blapose_data::data_root(a.data.clone());
    let cfg = a.config();
    let t0 = Instant::now();
    let set = TrainingSet::load(&root)?;
    let stats = TrainingLengthStats::from_training(&set.lengths_list())?;
    let pop = if cfg.lengths == LengthStrategy::Ansur {
        let mut pop = AnsurSplit::load(&root, &stats)?.training_population(cfg.ansur_people)?;
        if cfg.ansur_spread > 0.0 {
            pop.match_spread(&stats, cfg.ansur_spread)?;
        }
        Some(pop)
    } else {
        None
    };
    let sampler = LengthSampler::new(cfg.lengths, stats, pop)?;
    let source = Arc::new(
        SynthSource::new(set.sequences.clone(), set.residuals.clone(), sampler)?
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
    let input = cfg.model_input();
    if input.framing.needs_calibration() {
        // A model trained through the wide (distortion-free) cameras only
        // reads undistorted keypoints, as served; one trained through
        // Human3.6M's cameras saw their distortion, as the detections have it.
        if cfg.wide_cameras >= 1.0 {
            undistort_streams(real_sh.to_mut(), &camera)?;
        }
        prepare_streams(real_sh.to_mut(), &input, &camera)?;
    }
    let outcome = blapose_train::train::train(
        &cfg,
        source,
        &real_sh,
        &a.out,
        a.resume,
        &training_data(&cfg),
        &mut progress,
    )?;
    pb.finish();
    let curve = a.out.join("curve.svg");
    blapose_train::plot::training_curve(&a.out.join(blapose_train::run::LOG_FILE), &curve)?;
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

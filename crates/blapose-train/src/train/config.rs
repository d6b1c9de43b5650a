//! [`TrainConfig`]: everything that defines a bone-length training run,
//! stored in the checkpoint and in the weights' metadata (`train_config`)
//! with the command line's names; and the options that were removed,
//! which a checkpoint that used them is refused for.

use blapose_model::input::ModelInput;
use blapose_model::ModelKind;
use serde::{Deserialize, Serialize};

use crate::ansur_split::AnsurPeople;
use crate::error::TrainError;
use crate::lengths::LengthStrategy;
use crate::noise::NoiseKind;
use crate::run::{check_resumable, Schedule};
use crate::synth::{ShiftPlane, SynthConfig};

/// Everything that defines a training run. Serialized with the names
/// and spellings of the command line (`"kind": "bigru"`, `"lengths":
/// "ansur"`, ...), which every shipped file's `train_config` uses.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrainConfig {
    /// The model trained.
    pub kind: ModelKind,
    /// Length strategy (for the metadata; the sampler is passed in).
    pub lengths: LengthStrategy,
    /// `ansur` only: each bone's std as a multiple of the training
    /// subjects' std ([`crate::ansur::AnsurPopulation::match_spread`]);
    /// 0 keeps the survey's own spread (runs before this field existed).
    #[serde(default)]
    pub ansur_spread: f32,
    /// `ansur` only: which survey people training draws from
    /// ([`crate::ansur_split`]); configurations written before the
    /// held-out split read as `all`, what they were trained with.
    #[serde(default = "AnsurPeople::before_the_split")]
    pub ansur_people: AnsurPeople,
    /// Noise model.
    pub noise: NoiseKind,
    /// Frames per training window.
    pub seq_len: usize,
    /// Smallest playback stride.
    pub stride_min: f32,
    /// Largest playback stride.
    pub stride_max: f32,
    /// 3D shift std, metres.
    pub shift_std: f32,
    /// Where the shift is drawn; runs before this field were `camera`.
    #[serde(default)]
    pub shift_plane: ShiftPlane,
    /// Keep the lowest joint at its original height after the lengths are
    /// replaced ([`SynthConfig::floor_contact`]); runs before this field
    /// did not.
    #[serde(default)]
    pub floor_contact: bool,
    /// Turn each window by a random yaw ([`SynthConfig::random_yaw`]); runs
    /// before this field did not.
    #[serde(default)]
    pub random_yaw: bool,
    /// Synthesize through these cameras only (ids; empty = all;
    /// [`crate::synth::SynthSource::with_cameras`]); runs before this
    /// field used all.
    #[serde(default)]
    pub cameras: Vec<String>,
    /// Rectified keypoints ([`blapose_core::level`]); runs before this field
    /// read them as the camera gave them.
    #[serde(default)]
    pub rectify: bool,
    /// Floor-scaled rectified keypoints
    /// ([`crate::synth::SynthConfig::floor_scaled`]); runs before this
    /// field read them unscaled.
    #[serde(default)]
    pub floor_scaled: bool,
    /// Share of samples seen through a camera of the wide distribution
    /// ([`crate::synth::SynthConfig::wide_cameras`]); runs before this
    /// field used recorded cameras only.
    #[serde(default)]
    pub wide_cameras: f32,
    /// Flip probability.
    pub flip_prob: f32,
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
    /// Weight of the online GRU's running-mean loss (0 = off).
    pub per_frame_weight: f32,
    /// Start from these weights (a `model.safetensors` of the same kind)
    /// instead of a random initialization with the output layer at the
    /// training mean lengths ([`FastNet::init_output_at`]). Recorded so a
    /// resumed run can check it.
    #[serde(default)]
    pub init_weights: Option<String>,
    /// Learning-rate multiplier of the output layer (`fc.weight`): its
    /// 1,024 inputs add up Adam's per-weight steps coherently, so at the
    /// base rate the prediction jitters by centimetres; runs before this
    /// field used 1.
    #[serde(default = "one")]
    pub head_lr_scale: f32,
    /// Decay of the parameter average used for validation and the saved
    /// weights ([`crate::adam::ParamEma`]; 0 = off, runs before this field).
    #[serde(default)]
    pub ema_decay: f32,
    /// Master seed.
    pub seed: u64,
    /// Validate every this many steps (0 = only at the end).
    pub val_every: u64,
    /// Synthetic validation samples.
    pub val_samples: usize,
    /// Frames per real-SH validation window.
    pub val_frames: usize,
    /// Seconds between checkpoints.
    pub checkpoint_secs: u64,
}

fn one() -> f32 {
    1.0
}

/// Research options measured and removed since (models/README.md,
/// "Removed research options"), each with the test of the value that
/// meant "off". A checkpoint whose configuration turns one on cannot be
/// continued by this trainer.
type IsOff = fn(&serde_json::Value) -> bool;
const REMOVED_OPTIONS: [(&str, IsOff); 7] = [
    ("noise_scale", |v| v.as_f64() == Some(1.0)),
    ("camera_height_std", |v| v.as_f64() == Some(0.0)),
    ("camera_angle_std_deg", |v| v.as_f64() == Some(0.0)),
    ("detector_gain", |v| v.as_bool() == Some(false)),
    ("precondition", |v| v.as_bool() == Some(false)),
    ("decouple_size", |v| v.as_bool() == Some(false)),
    ("height_normalized", |v| v.as_bool() == Some(false)),
];

/// The removed research options a serialized configuration turns on.
pub fn removed_options(config: &serde_json::Value) -> Vec<&'static str> {
    REMOVED_OPTIONS
        .iter()
        .filter(|(name, is_off)| config.get(name).is_some_and(|v| !is_off(v)))
        .map(|(name, _)| *name)
        .collect()
}

impl TrainConfig {
    /// The augmentation knobs.
    pub fn synth(&self) -> Result<SynthConfig, TrainError> {
        let cfg = SynthConfig {
            seq_len: self.seq_len,
            stride_min: self.stride_min,
            stride_max: self.stride_max,
            shift_std: self.shift_std,
            shift_plane: self.shift_plane,
            min_depth: 1.5,
            flip_prob: self.flip_prob,
            noise: self.noise,
            floor_contact: self.floor_contact,
            random_yaw: self.random_yaw,
            rectify: self.rectify,
            floor_scaled: self.floor_scaled,
            wide_cameras: self.wide_cameras,
        };
        cfg.validate()?;
        Ok(cfg)
    }

    /// What the trained weights expect as input: rectified or not, scaled
    /// to the floor or not, through the wide cameras or Human3.6M's (the
    /// contract the samples were made for: [`SynthConfig::model_input`]).
    pub fn model_input(&self) -> ModelInput {
        ModelInput::from_training(self.rectify, self.floor_scaled, self.wide_cameras > 0.0)
    }

    /// The learning-rate schedule.
    pub fn schedule(&self) -> Schedule {
        Schedule {
            lr: self.lr,
            decay: self.lr_decay,
            epoch_steps: self.epoch_steps,
        }
    }

    /// The fields a resumed run must share with its checkpoint.
    pub(super) fn compatible(&self, other: &TrainConfig) -> Result<(), String> {
        check_resumable(self, other, |a, o| {
            // These may change on resume (e.g. train longer, log more often).
            a.steps = o.steps;
            a.val_every = o.val_every;
            a.checkpoint_secs = o.checkpoint_secs;
        })
    }
}

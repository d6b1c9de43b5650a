//! What a synthetic sample is drawn with ([`SynthConfig`]: window,
//! playback stride, shift, cameras, noise, flips), as flags and a run's
//! configuration spell it.

use blapose_core::camera::Camera;
use blapose_model::input::{ContractError, InputCamera, ModelInput, ViewCalibration};
use rand::Rng;
use serde::{Deserialize, Serialize};

use crate::error::TrainError;
use crate::lengths::normal_f32;
use crate::noise::NoiseKind;

/// In which space the per-window 3D shift is drawn (`--shift-plane`; the
/// same spelling in a run's configuration).
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, Hash, Default, Serialize, Deserialize, clap::ValueEnum,
)]
#[serde(rename_all = "lowercase")]
pub enum ShiftPlane {
    /// `N(0, std)` on all three camera axes (the paper's reference code).
    #[default]
    Camera,
    /// `N(0, std)` on the two horizontal world axes (Human3.6M's world
    /// `z` is up): the person stays on the floor.
    Ground,
}

impl ShiftPlane {
    /// The flag spelling.
    pub fn name(self) -> &'static str {
        match self {
            Self::Camera => "camera",
            Self::Ground => "ground",
        }
    }

    /// A shift drawn with `rng`, in `cam`'s coordinates.
    pub(super) fn draw<R: Rng + ?Sized>(self, cam: &Camera, std: f32, rng: &mut R) -> [f32; 3] {
        match self {
            Self::Camera => [
                normal_f32(rng, std),
                normal_f32(rng, std),
                normal_f32(rng, std),
            ],
            Self::Ground => {
                let w = [normal_f32(rng, std) as f64, normal_f32(rng, std) as f64];
                // A direction: rotate only, `R (w, 0)`.
                cam.rotation
                    .map(|row| (row[0] * w[0] + row[1] * w[1]) as f32)
            }
        }
    }
}

impl std::fmt::Display for ShiftPlane {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// Knobs of the augmentation (see the module docs).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SynthConfig {
    /// Output frames per sample (`T`).
    pub seq_len: usize,
    /// Smallest playback stride (source frames per output frame).
    pub stride_min: f32,
    /// Largest playback stride.
    pub stride_max: f32,
    /// Standard deviation of each component of the 3D shift, metres.
    pub shift_std: f32,
    /// Where the shift is drawn.
    pub shift_plane: ShiftPlane,
    /// The root must stay at least this deep in front of the camera, metres.
    pub min_depth: f32,
    /// Probability of a horizontal flip.
    pub flip_prob: f32,
    /// Detector-noise model.
    pub noise: NoiseKind,
    /// Keep the lowest joint at its original height in every frame (see
    /// the module docs, step 3).
    pub floor_contact: bool,
    /// Turn each window about the vertical through its first root by a
    /// uniform random yaw (see [`turn_about_vertical`]).
    pub random_yaw: bool,
    /// Give the keypoints as the camera's level twin would see them
    /// ([`blapose_core::level`]; such models need the camera's calibration).
    pub rectify: bool,
    /// Rectified keypoints further scaled, frame by frame, by the camera's
    /// height over the lowest joint's drop below the horizon
    /// ([`blapose_core::level::LevelCamera::scaled_to_floor`]): the body at a fixed metric
    /// scale, whatever the camera.
    pub floor_scaled: bool,
    /// Probability that a sample is seen through a camera drawn from the
    /// wide distribution ([`crate::camera_range::wide_cameras`]) instead of
    /// a recorded Human3.6M camera (0: recorded cameras only).
    pub wide_cameras: f32,
}

impl Default for SynthConfig {
    fn default() -> Self {
        Self {
            seq_len: 64,
            stride_min: 50.0 / 60.0,
            stride_max: 2.0,
            shift_std: 0.5,
            shift_plane: ShiftPlane::Camera,
            min_depth: 1.5,
            flip_prob: 0.5,
            noise: NoiseKind::Residual,
            floor_contact: false,
            random_yaw: false,
            rectify: false,
            floor_scaled: false,
            wide_cameras: 0.0,
        }
    }
}

impl SynthConfig {
    /// What a network trained on these samples reads: the input contract
    /// the trainer records in its weights ([`blapose_model::input`]).
    pub fn model_input(&self) -> ModelInput {
        ModelInput::from_training(self.rectify, self.floor_scaled, self.wide_cameras > 0.0)
    }

    /// The camera a sample seen through `cam` (Human3.6M convention, a
    /// pinhole: the lens is applied by the projection) is read through,
    /// as the contract prepares a served session's keypoints
    /// ([`ModelInput::camera`]): `Ok(None)` when the keypoints are read as
    /// the camera gives them, an error when `cam` does not rectify.
    pub(super) fn input_camera(&self, cam: &Camera) -> Result<Option<InputCamera>, ContractError> {
        self.model_input()
            .camera(&ViewCalibration::from_camera(cam))
    }

    /// Check the knobs.
    pub fn validate(&self) -> Result<(), TrainError> {
        let bad = |m: &str| Err(TrainError::InvalidArgument(m.to_string()));
        if self.seq_len == 0 {
            return bad("seq_len must be positive");
        }
        if self.floor_scaled && !self.rectify {
            return bad("floor scaling needs rectified keypoints (--rectify)");
        }
        if !(self.stride_min > 0.0
            && self.stride_max >= self.stride_min
            && self.stride_max.is_finite())
        {
            return bad("need 0 < stride_min <= stride_max");
        }
        if !(self.shift_std >= 0.0 && self.shift_std.is_finite()) {
            return bad("shift_std must be finite and >= 0");
        }
        if self.min_depth.is_nan() || self.min_depth <= 0.0 {
            return bad("min_depth must be positive");
        }
        if !(0.0..=1.0).contains(&self.flip_prob) {
            return bad("flip_prob must be in [0, 1]");
        }
        if !(0.0..=1.0).contains(&self.wide_cameras) {
            return bad("wide_cameras must be in [0, 1]");
        }
        Ok(())
    }
}

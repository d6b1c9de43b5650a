//! The model-input contract: what a set of weights expects to be fed, and
//! the one recipe that turns a session's keypoints (plus its calibration)
//! into that input.
//!
//! Why one typed contract: the calibration-free models read normalized
//! screen coordinates as the camera gave them; the camera-aware ones read
//! keypoints undistorted and rectified to the camera's level twin, some of
//! them also scaled to the floor, and only for calibrations inside the
//! envelope they were trained through. Each of those choices is made once,
//! by the trainer, and written into the weights' metadata
//! ([`KEY_MODEL_INPUT`]); the server (streams and whole sequences), the
//! evaluation and the many-bodies benchmark all read it through
//! [`ModelInput`] and feed the model through [`ModelInput::camera`] and
//! [`InputCamera::prepare_frames`], so a model is always served what it
//! was trained on. (The model's output needs no conversion: every shipped
//! contract predicts metres directly.) A view's lens, in either model
//! ([`blapose_core::lens`]), is undone here too: on each viewing ray by the
//! [`InputCamera`] (a served calibration's), or on the picture's pixels by
//! [`ViewCalibration::undistort_frames`] (what a client does before it
//! sends, and the evaluation with Human3.6M's cameras).
//!
//! Weights written before the contract existed carry the trainer's
//! `train_config` instead; it is read once, here, into the same struct
//! ([`ModelInput::from_train_config`]). Files that record neither (e.g.
//! converted reference checkpoints) declare nothing, and their user
//! decides ([`ModelInput::screen`] or [`ModelInput::level`]).

use blapose_core::camera::Camera;
use blapose_core::lens::LensDistortion;
use blapose_core::level::{CameraEnvelope, LevelCamera, LevelError, OutsideEnvelope};
use serde::{Deserialize, Serialize};

/// The weights-metadata key that holds the contract (JSON).
pub const KEY_MODEL_INPUT: &str = "model_input";
/// The metadata key of the trainer's configuration, read for weights that
/// predate [`KEY_MODEL_INPUT`].
pub const KEY_TRAIN_CONFIG: &str = "train_config";

/// How a model's keypoints are framed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Framing {
    /// Normalized screen coordinates as the camera gave them (the
    /// calibration-free models; a calibration is not used).
    Screen,
    /// Undistorted and rectified to the camera's level twin
    /// ([`blapose_core::level`]); needs a calibration.
    Level,
    /// [`Framing::Level`], then scaled to the floor
    /// ([`LevelCamera::scaled_to_floor`]); needs a calibration with the
    /// camera's height above the floor.
    LevelFloorScaled,
}

impl Framing {
    /// Whether this framing reads a calibration.
    pub const fn needs_calibration(self) -> bool {
        !matches!(self, Framing::Screen)
    }

    /// Whether this framing needs the camera's height above the floor.
    pub const fn needs_camera_height(self) -> bool {
        matches!(self, Framing::LevelFloorScaled)
    }
}

/// What a set of weights expects as input: always Human3.6M-17 keypoints
/// in normalized screen coordinates (`x/w*2-1, y/w*2-h/w`, joint-major),
/// framed as [`Framing`] says, from cameras inside `trained_cameras`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ModelInput {
    /// How the keypoints are framed.
    pub framing: Framing,
    /// The calibrations the weights were trained through; `None`: any
    /// calibration that rectifies (Human3.6M's own cameras).
    #[serde(default, with = "envelope_json")]
    pub trained_cameras: Option<CameraEnvelope>,
}

/// Why weights' input contract cannot be read.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ContractError {
    /// The JSON under a metadata key does not parse.
    #[error("weights metadata {key:?} does not parse: {reason}")]
    Unreadable {
        /// The metadata key.
        key: &'static str,
        /// The parser's message.
        reason: String,
    },
    /// The weights were trained with an input option this build no longer
    /// serves.
    #[error("the weights were trained with {option}, which this build no longer serves")]
    RemovedOption {
        /// The `train_config` option.
        option: &'static str,
    },
    /// The framing needs a calibration with the camera height, and it has
    /// none.
    #[error("these weights read keypoints scaled to the floor: the calibration must give the camera's height above the floor")]
    CameraHeightRequired,
    /// The calibration does not rectify.
    #[error(transparent)]
    Level(#[from] LevelError),
}

/// One calibrated view, as the contract needs it: the direction of up in
/// camera coordinates, pinhole intrinsics in pixels of the image the
/// keypoints are in, the lens (if any) and the camera's height above the
/// floor (if known). The lens is either model
/// ([`blapose_core::lens::LensModel`]): a served calibration's is OpenCV's,
/// a Human3.6M camera's its own.
#[derive(Debug, Clone, PartialEq)]
pub struct ViewCalibration {
    /// World up in camera coordinates (any non-zero length).
    pub up: [f64; 3],
    /// `[fx, fy]`, pixels.
    pub focal: [f64; 2],
    /// `[cx, cy]`, pixels.
    pub principal: [f64; 2],
    /// Image width and height, pixels.
    pub image_size: (u32, u32),
    /// The camera's height above the floor, metres.
    pub camera_height: Option<f32>,
    /// The lens distortion undone before rectifying.
    pub lens: Option<LensDistortion>,
}

impl ViewCalibration {
    /// A Human3.6M-convention camera (world `z` up, the floor at `z = 0`),
    /// without its lens: its keypoints are taken as already undistorted
    /// (the dataset undoes Human3.6M's own lens model first).
    pub fn from_camera(cam: &Camera) -> Self {
        Self {
            up: cam.rotation.map(|row| row[2]),
            focal: cam.focal,
            principal: cam.principal,
            image_size: (cam.width, cam.height),
            camera_height: Some(cam.center[2] as f32),
            lens: None,
        }
    }

    /// [`Self::from_camera`] with the camera's own lens (Human3.6M's
    /// model): its keypoints are those of the raw, distorted picture.
    pub fn from_camera_through_lens(cam: &Camera) -> Self {
        Self {
            lens: Some(cam.lens()),
            ..Self::from_camera(cam)
        }
    }

    /// Frames of this view's picture (`17 * 2` normalized screen
    /// coordinates each) made into those of the distortion-free camera with
    /// the same intrinsics, in place, pixel by pixel
    /// ([`LensDistortion::undistort_pixel`]): what a client does before it
    /// sends undistorted keypoints, and so what the evaluation does to
    /// Human3.6M's detections. Unchanged without a lens.
    /// [`ModelInput::camera`] instead undoes the lens on each viewing ray,
    /// as the server does with a calibration's lens (the two orders agree
    /// to float rounding; each keeps its own numbers).
    pub fn undistort_frames(&self, frames: &mut [f32]) {
        use blapose_core::camera::{denormalize_screen, normalize_screen};
        let Some(lens) = &self.lens else {
            return;
        };
        let (width, height) = self.image_size;
        for xy in frames.chunks_exact_mut(2) {
            let px = denormalize_screen([xy[0], xy[1]], width, height);
            let u = lens.undistort_pixel(
                self.focal,
                self.principal,
                [f64::from(px[0]), f64::from(px[1])],
            );
            let n = normalize_screen([u[0] as f32, u[1] as f32], width, height);
            xy.copy_from_slice(&n);
        }
    }
}

/// The camera a model reads one view through: the view's level twin,
/// with the lens and the floor scaling the contract asks for.
#[derive(Debug, Clone, PartialEq)]
pub struct InputCamera {
    level: LevelCamera,
}

impl InputCamera {
    /// One stream's frames (`17 * 2` values each, normalized screen
    /// coordinates of the view) turned into the model's input, in place.
    pub fn prepare_frames(&self, frames: &mut [f32]) {
        self.level.rectify_frames(frames);
    }

    /// This camera with keypoints seen through `lens`, undone on each
    /// viewing ray before rectifying ([`LevelCamera::with_lens`]).
    pub fn with_lens(self, lens: LensDistortion) -> Self {
        Self {
            level: self.level.with_lens(lens),
        }
    }

    /// The level twin (with lens and floor scaling) behind this camera.
    pub fn level(&self) -> &LevelCamera {
        &self.level
    }
}

impl ModelInput {
    /// The calibration-free contract: screen coordinates, any camera.
    pub const fn screen() -> Self {
        Self {
            framing: Framing::Screen,
            trained_cameras: None,
        }
    }

    /// Plain rectified keypoints from any camera that rectifies (what
    /// camera-aware weights that record no contract are taken to read).
    pub const fn level() -> Self {
        Self {
            framing: Framing::Level,
            trained_cameras: None,
        }
    }

    /// The contract recorded in a weights file's metadata (`get` looks a
    /// key up): its [`KEY_MODEL_INPUT`] when present, else read from its
    /// `train_config` ([`ModelInput::from_train_config`]); `None` when it
    /// records neither.
    pub fn from_metadata<'a>(
        get: impl Fn(&str) -> Option<&'a String>,
    ) -> Result<Option<Self>, ContractError> {
        if let Some(json) = get(KEY_MODEL_INPUT) {
            return serde_json::from_str(json)
                .map(Some)
                .map_err(|e| ContractError::Unreadable {
                    key: KEY_MODEL_INPUT,
                    reason: e.to_string(),
                });
        }
        get(KEY_TRAIN_CONFIG)
            .map(|json| Self::from_train_config(json))
            .transpose()
    }

    /// The contract of weights that predate [`KEY_MODEL_INPUT`], from
    /// their `train_config` JSON: `rectify`, `floor_scaled` and
    /// `wide_cameras` (options a file predates read as off). Weights
    /// trained with `height_normalized` are refused: no shipped model
    /// used it, and it is no longer served.
    pub fn from_train_config(json: &str) -> Result<Self, ContractError> {
        let config: serde_json::Value =
            serde_json::from_str(json).map_err(|e| ContractError::Unreadable {
                key: KEY_TRAIN_CONFIG,
                reason: e.to_string(),
            })?;
        let flag = |name: &str| config.get(name).and_then(|v| v.as_bool()).unwrap_or(false);
        if flag("height_normalized") {
            return Err(ContractError::RemovedOption {
                option: "height_normalized",
            });
        }
        let wide = config
            .get("wide_cameras")
            .and_then(|v| v.as_f64())
            .unwrap_or(0.0);
        Ok(Self::from_training(
            flag("rectify"),
            flag("floor_scaled"),
            wide > 0.0,
        ))
    }

    /// The contract of a training run: rectified or not, scaled to the
    /// floor or not, through the wide cameras
    /// ([`blapose_core::level::WIDE_CAMERA_ENVELOPE`]) or Human3.6M's.
    pub fn from_training(rectify: bool, floor_scaled: bool, wide_cameras: bool) -> Self {
        let framing = match (rectify, floor_scaled) {
            (false, _) => Framing::Screen,
            (true, false) => Framing::Level,
            (true, true) => Framing::LevelFloorScaled,
        };
        Self {
            framing,
            trained_cameras: wide_cameras.then_some(blapose_core::level::WIDE_CAMERA_ENVELOPE),
        }
    }

    /// As the JSON stored under [`KEY_MODEL_INPUT`].
    pub fn to_json(&self) -> String {
        serde_json::to_string(self).expect("a ModelInput always serializes")
    }

    /// The camera this model reads `view` through (`None` for
    /// [`Framing::Screen`], which reads keypoints as the camera gave
    /// them). Refused when the framing needs the camera height and the
    /// view has none, or when the calibration does not rectify.
    pub fn camera(&self, view: &ViewCalibration) -> Result<Option<InputCamera>, ContractError> {
        if !self.framing.needs_calibration() {
            return Ok(None);
        }
        let (width, height) = view.image_size;
        let level = LevelCamera::from_pixels(view.up, view.focal, view.principal, width, height)?;
        let level = match self.framing {
            Framing::LevelFloorScaled => level.scaled_to_floor(
                view.camera_height
                    .ok_or(ContractError::CameraHeightRequired)?,
            ),
            _ => level,
        };
        let camera = InputCamera { level };
        Ok(Some(match view.lens {
            Some(lens) => camera.with_lens(lens),
            None => camera,
        }))
    }

    /// Whether `view` lies inside the cameras the weights were trained
    /// through (always, when they name none). Needs the camera height
    /// when they name an envelope.
    pub fn admits(&self, view: &ViewCalibration) -> Result<(), OutsideEnvelope> {
        let Some(envelope) = self.trained_cameras else {
            return Ok(());
        };
        envelope.check(
            view.camera_height.map_or(0.0, f64::from),
            view.up,
            view.focal[0],
            view.image_size.0,
        )
    }
}

/// [`CameraEnvelope`] as JSON (`{"height_m": [lo, hi], "pitch_deg": ...,
/// "hfov_deg": ...}`): blapose-core has no serde.
mod envelope_json {
    use super::CameraEnvelope;
    use serde::{Deserialize, Deserializer, Serialize, Serializer};

    #[derive(Serialize, Deserialize)]
    struct Envelope {
        height_m: [f64; 2],
        pitch_deg: [f64; 2],
        hfov_deg: [f64; 2],
    }

    pub fn serialize<S: Serializer>(
        value: &Option<CameraEnvelope>,
        s: S,
    ) -> Result<S::Ok, S::Error> {
        value
            .map(|e| Envelope {
                height_m: e.height_m,
                pitch_deg: e.pitch_deg,
                hfov_deg: e.hfov_deg,
            })
            .serialize(s)
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(
        d: D,
    ) -> Result<Option<CameraEnvelope>, D::Error> {
        Ok(Option::<Envelope>::deserialize(d)?.map(|e| CameraEnvelope {
            height_m: e.height_m,
            pitch_deg: e.pitch_deg,
            hfov_deg: e.hfov_deg,
        }))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use blapose_core::level::WIDE_CAMERA_ENVELOPE;

    fn view(camera_height: Option<f32>) -> ViewCalibration {
        ViewCalibration {
            up: [0.0, -0.98, 0.2],
            focal: [1000.0, 1000.0],
            principal: [640.0, 360.0],
            image_size: (1280, 720),
            camera_height,
            lens: None,
        }
    }

    #[test]
    fn older_train_configs_read_into_the_contract() {
        let screen = ModelInput::from_train_config(r#"{"kind":"gru"}"#).unwrap();
        assert_eq!(screen, ModelInput::screen());
        let wide = ModelInput::from_train_config(
            r#"{"rectify":true,"floor_scaled":true,"wide_cameras":0.5}"#,
        )
        .unwrap();
        assert_eq!(wide.framing, Framing::LevelFloorScaled);
        assert_eq!(wide.trained_cameras, Some(WIDE_CAMERA_ENVELOPE));
        assert_eq!(
            ModelInput::from_train_config(r#"{"rectify":true,"height_normalized":true}"#),
            Err(ContractError::RemovedOption {
                option: "height_normalized"
            })
        );
        assert!(matches!(
            ModelInput::from_train_config("{"),
            Err(ContractError::Unreadable { .. })
        ));
    }

    #[test]
    fn the_recorded_contract_wins_and_round_trips() {
        let contract = ModelInput::from_training(true, true, true);
        let mut extra = std::collections::BTreeMap::new();
        extra.insert(KEY_TRAIN_CONFIG.to_string(), r#"{"rectify":false}"#.into());
        assert_eq!(
            ModelInput::from_metadata(|k| extra.get(k)).unwrap(),
            Some(ModelInput::screen())
        );
        extra.insert(KEY_MODEL_INPUT.to_string(), contract.to_json());
        assert_eq!(
            ModelInput::from_metadata(|k| extra.get(k)).unwrap(),
            Some(contract)
        );
        assert_eq!(ModelInput::from_metadata(|_| None).unwrap(), None);
    }

    #[test]
    fn the_recipe_rectifies_scales_and_checks_as_the_framing_says() {
        let mut frames: Vec<f32> = (0..34).map(|i| (i as f32 - 17.0) / 40.0).collect();
        let raw = frames.clone();
        assert!(ModelInput::screen().camera(&view(None)).unwrap().is_none());
        let level = ModelInput::level().camera(&view(None)).unwrap().unwrap();
        level.prepare_frames(&mut frames);
        assert_ne!(frames, raw);
        let floor = ModelInput::from_training(true, true, false);
        assert_eq!(
            floor.camera(&view(None)),
            Err(ContractError::CameraHeightRequired)
        );
        let mut scaled = raw.clone();
        floor
            .camera(&view(Some(2.0)))
            .unwrap()
            .unwrap()
            .prepare_frames(&mut scaled);
        assert_ne!(scaled, frames);
        let wide = ModelInput::from_training(true, false, true);
        assert!(wide.admits(&view(Some(1.5))).is_ok());
        assert!(wide.admits(&view(Some(9.0))).is_err());
        assert!(ModelInput::level().admits(&view(Some(9.0))).is_ok());
    }
}

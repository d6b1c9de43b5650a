//! Keypoints as a level camera would see them ("rectified" keypoints).
//!
//! The one cue to a person's absolute size in a single view is where the
//! feet meet the floor: the further below the horizon, the nearer the
//! person. Where the horizon lies in the picture depends on the camera's
//! tilt and principal point, which a network fed raw keypoints is never
//! told (Human3.6M's four cameras differ by 10.7-16 degrees of tilt, and a
//! model trained over all of them learns an average geometry). Rectifying
//! turns each keypoint's viewing ray into the frame of a *level* camera at
//! the same place and heading (world vertical up, the optical axis turned
//! to the horizontal), so the horizon is always the line `v = 0`. What is
//! left unknown is the camera's height.
//!
//! All a rectification needs is the camera's intrinsics and the direction
//! of world "up" in camera coordinates (`x` right, `y` down, `z` forward):
//! for a calibrated camera with world-to-camera rotation `R` and world `z`
//! up that is `R`'s third column; a phone gives it as minus its gravity
//! vector. The trainer builds a [`LevelCamera`] from each Human3.6M camera
//! ([`LevelCamera::from_camera`]), the server from a session's calibration
//! ([`LevelCamera::new`]); both then share one [`LevelCamera::rectify`].
//!
//! Input and output are normalized screen coordinates
//! ([`crate::camera::normalize_screen`]), the output scaled like them
//! (`x * f * 2 / width`), so for a level camera with a centred principal
//! point it is the identity. Keypoints are taken as undistorted pixels
//! unless the camera carries its lens distortion
//! ([`LevelCamera::with_lens`], [`crate::lens`]), which is then undone
//! first: the camera-aware models were trained through distortion-free
//! cameras, and at Human3.6M's `k1 = -0.2` the lens moves points near the
//! image edge by a few percent.
//!
//! The checks a calibration's values must pass ([`check_calibration`],
//! [`check_image_size`], [`calibration_image_size`]) and the accepted
//! camera heights ([`MIN_CAMERA_HEIGHT`] to [`MAX_CAMERA_HEIGHT`]) live here
//! too, once: the server refuses what they refuse, and the client library
//! runs the same checks before it sends a calibration.

use crate::camera::Camera;
use crate::layouts::Coordinates;
use crate::lens::LensDistortion;
use crate::pose::Keypoints2d;
use crate::skeleton::NUM_JOINTS;

/// Camera height (metres above the floor) that height-normalized models'
/// estimates refer to: about the mean of Human3.6M's training cameras
/// (1.46-1.63 m). A rectified picture from a camera `k` times higher is
/// exactly the picture of the scene `1/k` times the size from this height
/// (similar triangles about the camera centre), so such a model predicts
/// lengths as if seen from here and [`height_scale`] brings them back.
pub const REFERENCE_CAMERA_HEIGHT: f64 = 1.56;

/// What a height-normalized estimate is multiplied by for a camera
/// `camera_height` metres above the floor.
pub fn height_scale(camera_height: f64) -> f64 {
    camera_height / REFERENCE_CAMERA_HEIGHT
}

/// Smallest forward component of a ray before it is treated as grazing.
const MIN_FORWARD: f64 = 1e-3;

/// Steepest accepted optical axis, in degrees above or below the horizon.
/// Past it the level twin's heading is ill-defined (straight down it is
/// undefined) and people fill little of a level camera's view.
pub const MAX_TILT_DEG: f64 = 60.0;

/// Lowest camera height (metres above the floor) a calibration may give.
pub const MIN_CAMERA_HEIGHT: f32 = 0.3;
/// Highest camera height (metres above the floor) a calibration may give.
pub const MAX_CAMERA_HEIGHT: f32 = 10.0;

/// Whether `height` metres is a camera height a calibration may give
/// ([`MIN_CAMERA_HEIGHT`] to [`MAX_CAMERA_HEIGHT`]; never NaN). The wire's
/// 0 ("not given") is the caller's to handle.
pub fn is_camera_height(height: f32) -> bool {
    (MIN_CAMERA_HEIGHT..=MAX_CAMERA_HEIGHT).contains(&height)
}

/// The calibrations a camera-aware model family was trained on: the camera
/// height above the floor, the optical axis' angle to the horizon (pitch,
/// negative looking down) and the horizontal field of view. Rectification
/// removes tilt and roll from the picture but not what they do to framing,
/// and the rectified coordinates scale with the focal length, so a
/// calibration outside the range asks the model about pictures it never
/// saw; the server refuses it ([`CameraEnvelope::check`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CameraEnvelope {
    /// Camera height above the floor, metres.
    pub height_m: [f64; 2],
    /// Optical axis above (+) or below (-) the horizon, degrees.
    pub pitch_deg: [f64; 2],
    /// Horizontal field of view, degrees.
    pub hfov_deg: [f64; 2],
}

/// Where the wide-camera models are trained (`blapose train
/// --wide-cameras`) and the many-bodies benchmark draws its cameras: where a
/// user might put a phone or a webcam.
pub const WIDE_CAMERA_ENVELOPE: CameraEnvelope = CameraEnvelope {
    height_m: [0.5, 3.0],
    pitch_deg: [-35.0, 15.0],
    hfov_deg: [40.0, 100.0],
};

/// A calibration outside a family's [`CameraEnvelope`].
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{field} gives a {quantity} of {value:.2} {unit}; the camera-aware models were trained for {lo} to {hi} {unit}")]
pub struct OutsideEnvelope {
    /// The calibration value at fault (wire spelling).
    pub field: &'static str,
    /// What it gives.
    pub quantity: &'static str,
    /// Its value.
    pub value: f64,
    /// Smallest trained value.
    pub lo: f64,
    /// Largest trained value.
    pub hi: f64,
    /// The unit.
    pub unit: &'static str,
}

/// The optical axis' angle above the horizon (degrees; negative looks
/// down) of a camera with world `up` in camera coordinates (`z` forward).
pub fn pitch_deg(up: [f64; 3]) -> f64 {
    let norm = dot(&up, &up).sqrt();
    (up[2] / norm).clamp(-1.0, 1.0).asin().to_degrees()
}

/// The horizontal field of view (degrees) of a focal length of `focal_x`
/// pixels across an image `width` pixels wide.
pub fn hfov_deg(focal_x: f64, width: u32) -> f64 {
    2.0 * (f64::from(width) / 2.0 / focal_x).atan().to_degrees()
}

impl CameraEnvelope {
    /// Check a calibration (already through [`check_calibration`]): the
    /// camera `height_m` above the floor, world `up` in camera coordinates,
    /// the focal length `focal_x` in pixels of an image `width` wide.
    pub fn check(
        &self,
        height_m: f64,
        up: [f64; 3],
        focal_x: f64,
        width: u32,
    ) -> Result<(), OutsideEnvelope> {
        let within = |field, quantity, value: f64, [lo, hi]: [f64; 2], unit| {
            if (lo..=hi).contains(&value) {
                Ok(())
            } else {
                Err(OutsideEnvelope {
                    field,
                    quantity,
                    value,
                    lo,
                    hi,
                    unit,
                })
            }
        };
        within(
            "camera.height",
            "camera height",
            height_m,
            self.height_m,
            "m",
        )?;
        within(
            "camera.up",
            "pitch",
            pitch_deg(up),
            self.pitch_deg,
            "degrees",
        )?;
        within(
            "camera.focal_x",
            "horizontal field of view",
            hfov_deg(focal_x, width),
            self.hfov_deg,
            "degrees",
        )
    }
}

/// A calibration value that no camera can have. The checks behind it
/// ([`check_calibration`], [`check_image_size`],
/// [`calibration_image_size`]) are the protocol's, shared by the server
/// (which also needs a [`LevelCamera`], so it refuses [`LevelError::TooSteep`]
/// too) and the client library (which checks a calibration before sending
/// it, leaving the tilt to the server). Each names its value in its own
/// words; this error carries what they need.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CalibrationError {
    /// A value is NaN or infinite.
    #[error("{field} is not finite")]
    NonFinite {
        /// Which value: `up`, `focal` or `principal`.
        field: &'static str,
    },
    /// The up direction has (almost) no length.
    #[error("the up direction {up:?} has no length")]
    ZeroUp {
        /// The direction given.
        up: [f64; 3],
    },
    /// A focal length is not positive.
    #[error("focal lengths must be positive, got {focal:?}")]
    InvalidFocal {
        /// The focal lengths given.
        focal: [f64; 2],
    },
    /// The principal point lies beyond any image (more than
    /// [`MAX_PRINCIPAL_ABS`] from the origin): rectifying through it
    /// leaves the finite numbers.
    #[error("the principal point {principal:?} is beyond any image (at most {MAX_PRINCIPAL_ABS} from the origin)")]
    PrincipalOutOfRange {
        /// The principal point given.
        principal: [f64; 2],
    },
    /// The image size has a zero side.
    #[error("image size must be positive, got {width}x{height}")]
    InvalidImageSize {
        /// Width in pixels.
        width: u32,
        /// Height in pixels.
        height: u32,
    },
    /// Normalized keypoints, but no image size to relate them to the
    /// calibration's pixels.
    #[error("an image size is required with normalized keypoints (the calibration is in pixels)")]
    ImageSizeMissing,
    /// The calibration's image size differs from the pixel keypoints'.
    #[error("the calibration's image size {camera_width}x{camera_height} differs from the keypoints' {width}x{height}")]
    ImageSizeMismatch {
        /// The calibration's width.
        camera_width: u32,
        /// The calibration's height.
        camera_height: u32,
        /// The keypoints' width.
        width: u32,
        /// The keypoints' height.
        height: u32,
    },
}

/// Why a calibration cannot be rectified.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum LevelError {
    /// A value no camera can have.
    #[error(transparent)]
    Calibration(#[from] CalibrationError),
    /// The optical axis is too close to vertical.
    #[error("the optical axis is {tilt_deg:.1} degrees from the horizon; at most {MAX_TILT_DEG} is supported")]
    TooSteep {
        /// Angle between the optical axis and the horizontal plane.
        tilt_deg: f64,
    },
}

/// Check a calibration's values, in pixels or normalized units alike:
/// everything finite (`up`, then `focal`, then `principal`), focal lengths
/// positive, `up` of non-zero length. The tilt is not checked.
pub fn check_calibration(
    up: [f64; 3],
    focal: [f64; 2],
    principal: [f64; 2],
) -> Result<(), CalibrationError> {
    finite("up", &up)?;
    finite("focal", &focal)?;
    finite("principal", &principal)?;
    if !(focal[0] > 0.0 && focal[1] > 0.0) {
        return Err(CalibrationError::InvalidFocal { focal });
    }
    if dot(&up, &up).sqrt() <= MIN_UP_NORM {
        return Err(CalibrationError::ZeroUp { up });
    }
    if principal.iter().any(|p| p.abs() > MAX_PRINCIPAL_ABS) {
        return Err(CalibrationError::PrincipalOutOfRange { principal });
    }
    Ok(())
}

/// Largest magnitude of a principal point coordinate (pixels or normalized
/// units): the bound the protocol puts on keypoint values.
pub const MAX_PRINCIPAL_ABS: f64 = 1e6;

/// Check a calibration's image size: both sides positive.
pub fn check_image_size(width: u32, height: u32) -> Result<(), CalibrationError> {
    if width == 0 || height == 0 {
        Err(CalibrationError::InvalidImageSize { width, height })
    } else {
        Ok(())
    }
}

/// The image size a calibration's pixels refer to, for keypoints in
/// `coordinates`: `given` by the calibration, required with normalized
/// keypoints; with pixel keypoints the keypoints' image, which a `given`
/// size must equal. (Not checked for zero sides: see [`check_image_size`].)
pub fn calibration_image_size(
    coordinates: Coordinates,
    given: Option<(u32, u32)>,
) -> Result<(u32, u32), CalibrationError> {
    match (coordinates, given) {
        (Coordinates::Normalized, None) => Err(CalibrationError::ImageSizeMissing),
        (Coordinates::Normalized, Some(size)) => Ok(size),
        (Coordinates::Pixels { width, height }, None) => Ok((width, height)),
        (Coordinates::Pixels { width, height }, Some((cw, ch))) => {
            if (cw, ch) == (width, height) {
                Ok((width, height))
            } else {
                Err(CalibrationError::ImageSizeMismatch {
                    camera_width: cw,
                    camera_height: ch,
                    width,
                    height,
                })
            }
        }
    }
}

/// Length of an up direction below which it is taken as having none.
const MIN_UP_NORM: f64 = 1e-9;

fn dot(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn cross(a: &[f64; 3], b: &[f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

fn finite(field: &'static str, values: &[f64]) -> Result<(), CalibrationError> {
    if values.iter().all(|v| v.is_finite()) {
        Ok(())
    } else {
        Err(CalibrationError::NonFinite { field })
    }
}

/// One frame of rectified keypoints from a camera `camera_height` metres
/// above the floor, scaled by that height over
/// [`REFERENCE_CAMERA_HEIGHT`] and divided by the lowest joint's drop below
/// the horizon (at least [`MIN_FLOOR_DROP`]); see
/// [`LevelCamera::scaled_to_floor`].
pub fn scale_to_floor(kp: &Keypoints2d, camera_height: f32) -> Keypoints2d {
    let drop = kp.iter().map(|p| p[1]).fold(f32::MIN, f32::max);
    let scale = camera_height / REFERENCE_CAMERA_HEIGHT as f32 / drop.max(MIN_FLOOR_DROP as f32);
    kp.map(|p| [p[0] * scale, p[1] * scale])
}

/// The level twin of one camera, built once per camera: its right, down and
/// forward axes in the camera's own frame (so a keypoint's ray needs three
/// dot products and no rotation) and the intrinsics in normalized units.
#[derive(Debug, Clone, PartialEq)]
pub struct LevelCamera {
    /// Right, down and forward of the level frame, camera coordinates.
    axes: [[f64; 3]; 3],
    /// `[fx, fy]` in normalized units (`f * 2 / width`).
    focal: [f64; 2],
    /// `[cx, cy]` in normalized screen coordinates.
    principal: [f64; 2],
    /// The camera height (metres) when each frame is scaled to the floor
    /// ([`LevelCamera::scaled_to_floor`]).
    floor_scaled: Option<f32>,
    /// The lens distortion undone before rectifying, if any
    /// ([`LevelCamera::with_lens`]).
    lens: Option<LensDistortion>,
}

/// Smallest drop of the lowest joint below the horizon that floor scaling
/// divides by (normalized units): a person whose feet are on the horizon
/// (a camera at foot height, or one very far) shows no distance.
pub const MIN_FLOOR_DROP: f64 = 0.02;

impl LevelCamera {
    /// The level twin of a camera with world `up` given in camera
    /// coordinates (any non-zero length) and intrinsics in normalized
    /// units: `focal` is `f * 2 / width`, `principal` the principal point
    /// in normalized screen coordinates.
    pub fn new(up: [f64; 3], focal: [f64; 2], principal: [f64; 2]) -> Result<Self, LevelError> {
        check_calibration(up, focal, principal)?;
        let norm = dot(&up, &up).sqrt();
        let up = up.map(|v| v / norm);
        // The optical axis (camera z) with its vertical part removed.
        let horizontal = [-up[0] * up[2], -up[1] * up[2], 1.0 - up[2] * up[2]];
        let tilt_deg = up[2].clamp(-1.0, 1.0).asin().to_degrees().abs();
        if tilt_deg > MAX_TILT_DEG {
            return Err(LevelError::TooSteep { tilt_deg });
        }
        let h = dot(&horizontal, &horizontal).sqrt();
        let forward = horizontal.map(|v| v / h);
        let right = cross(&forward, &up);
        let down = up.map(|v| -v);
        Ok(Self {
            axes: [right, down, forward],
            focal,
            principal,
            floor_scaled: None,
            lens: None,
        })
    }

    /// This camera with keypoints seen through `lens`: each is undistorted
    /// before it is rectified.
    pub fn with_lens(mut self, lens: LensDistortion) -> Self {
        self.lens = Some(lens);
        self
    }

    /// This camera, `camera_height` metres above the floor, with its
    /// keypoints further scaled frame by frame by `camera_height /
    /// REFERENCE_CAMERA_HEIGHT` over the lowest joint's drop below the
    /// horizon. For a person standing on the floor that drop is `f (h -
    /// z_floor) / Z` (camera height `h`, depth `Z`), so the scaled picture
    /// shows the body at a fixed metric scale whatever the distance, the
    /// lens and the camera height: a bone of length `L` spans about `L /
    /// 1.56` and a model reads sizes from keypoint spreads directly
    /// instead of dividing one small image quantity by another. Drops
    /// below [`MIN_FLOOR_DROP`] are taken as it.
    pub fn scaled_to_floor(mut self, camera_height: f32) -> Self {
        self.floor_scaled = Some(camera_height);
        self
    }

    /// The camera height [`LevelCamera::scaled_to_floor`] scales with, if
    /// it applies ([`scale_to_floor`] after rectifying).
    pub fn floor_scale_height(&self) -> Option<f32> {
        self.floor_scaled
    }

    /// [`LevelCamera::new`] with intrinsics in pixels of a `width` x
    /// `height` image (what a calibration tool reports).
    pub fn from_pixels(
        up: [f64; 3],
        focal: [f64; 2],
        principal: [f64; 2],
        width: u32,
        height: u32,
    ) -> Result<Self, LevelError> {
        check_image_size(width, height)?;
        let (w, h) = (f64::from(width), f64::from(height));
        Self::new(
            up,
            [focal[0] / w * 2.0, focal[1] / w * 2.0],
            [principal[0] / w * 2.0 - 1.0, principal[1] / w * 2.0 - h / w],
        )
    }

    /// The level twin of a calibrated camera whose world `z` is up (the
    /// Human3.6M convention).
    pub fn from_camera(cam: &Camera) -> Result<Self, LevelError> {
        let up = cam.rotation.map(|row| row[2]);
        Self::from_pixels(up, cam.focal, cam.principal, cam.width, cam.height)
    }

    /// One frame of normalized screen keypoints seen through the camera,
    /// as its level twin would see them (see the module docs), scaled to
    /// the floor when [`LevelCamera::scaled_to_floor`] asked for it.
    pub fn rectify(&self, kp: &Keypoints2d) -> Keypoints2d {
        let [right, down, forward] = &self.axes;
        let level = kp.map(|p| {
            let seen = [
                (f64::from(p[0]) - self.principal[0]) / self.focal[0],
                (f64::from(p[1]) - self.principal[1]) / self.focal[1],
            ];
            let [x, y] = match &self.lens {
                Some(lens) => lens.undistort(seen),
                None => seen,
            };
            let ray = [x, y, 1.0];
            let z = dot(&ray, forward).max(MIN_FORWARD);
            [
                (dot(&ray, right) / z * self.focal[0]) as f32,
                (dot(&ray, down) / z * self.focal[1]) as f32,
            ]
        });
        match self.floor_scaled {
            Some(h) => scale_to_floor(&level, h),
            None => level,
        }
    }

    /// [`LevelCamera::rectify`] in place over whole frames of `17 * 2`
    /// values each (a stream, or one frame).
    pub fn rectify_frames(&self, frames: &mut [f32]) {
        for frame in frames.chunks_exact_mut(2 * NUM_JOINTS) {
            let kp: Keypoints2d = std::array::from_fn(|j| [frame[2 * j], frame[2 * j + 1]]);
            for (out, value) in frame
                .iter_mut()
                .zip(self.rectify(&kp).into_iter().flatten())
            {
                *out = value;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::{denormalize_screen, normalize_screen};

    #[test]
    fn floor_scaling_shows_the_body_at_one_metric_scale_whatever_the_distance() {
        // A flat figure facing a level camera h up: feet on the floor,
        // joints at heights z and sideways offsets x, all at depth d.
        let figure = |h: f32, d: f32, size: f32| -> Keypoints2d {
            std::array::from_fn(|j| {
                let z = size * (0.1 + 0.1 * j as f32);
                let x = size * 0.05 * (j as f32 - 8.0);
                [x / d, (h - z) / d]
            })
        };
        let r = REFERENCE_CAMERA_HEIGHT as f32;
        let near = scale_to_floor(&figure(1.5, 3.0, 1.0), 1.5);
        let far = scale_to_floor(&figure(1.5, 9.0, 1.0), 1.5);
        // Twice the person from twice the height: twice the picture.
        let double = scale_to_floor(&figure(3.0, 5.0, 2.0), 3.0);
        for j in 0..NUM_JOINTS {
            for a in 0..2 {
                assert!((near[j][a] - far[j][a]).abs() < 1e-5);
                assert!((double[j][a] - 2.0 * near[j][a]).abs() < 1e-5);
            }
        }
        // A 1 m rise spans h / (h - 0.1) / 1.56: metric, at the reference
        // height's scale.
        assert!((near[0][1] - near[10][1] - 1.5 / 1.4 / r).abs() < 1e-5);
        // Feet on the horizon are not divided by zero.
        let flat = scale_to_floor(&[[0.1, 0.0]; NUM_JOINTS], 1.5);
        assert!(flat.iter().flatten().all(|v| v.is_finite()));
        // Through a level camera: the same as rectifying, then scaling.
        let cam = LevelCamera::new([0.0, -1.0, 0.0], [2.0, 2.0], [0.0, 0.0]).unwrap();
        let kp = figure(1.5, 4.0, 1.0);
        assert_eq!(
            cam.clone().scaled_to_floor(1.5).rectify(&kp),
            scale_to_floor(&cam.rectify(&kp), 1.5)
        );
    }

    #[test]
    fn the_envelope_names_the_value_outside_it() {
        let e = WIDE_CAMERA_ENVELOPE;
        // Level camera, 60 degrees across 1000 px, 1.2 m up.
        let f = 500.0 / 30f64.to_radians().tan();
        assert!((hfov_deg(f, 1000) - 60.0).abs() < 1e-9);
        e.check(1.2, [0.0, -1.0, 0.0], f, 1000).unwrap();
        let err = e.check(3.5, [0.0, -1.0, 0.0], f, 1000).unwrap_err();
        assert_eq!((err.field, err.value), ("camera.height", 3.5));
        // Looking 45 degrees down: up has a forward part of -sin 45.
        let s = 45f64.to_radians().sin();
        let down45 = [0.0, -s, -s];
        assert!((pitch_deg(down45) + 45.0).abs() < 1e-9);
        let err = e.check(1.2, down45, f, 1000).unwrap_err();
        assert_eq!(err.field, "camera.up");
        assert!(err.to_string().contains("pitch of -45.00 degrees"), "{err}");
        // A 120-degree lens.
        let wide = 500.0 / 60f64.to_radians().tan();
        let err = e.check(1.2, [0.0, -1.0, 0.0], wide, 1000).unwrap_err();
        assert_eq!(err.field, "camera.focal_x");
        assert!((err.value - 120.0).abs() < 1e-9);
    }

    fn camera(tilt: f64, principal: [f64; 2]) -> Camera {
        // Looking along world +y, tilted down by `tilt` radians.
        let (c, s) = (tilt.cos(), tilt.sin());
        Camera {
            id: "test".into(),
            rotation: [[1.0, 0.0, 0.0], [0.0, -s, -c], [0.0, c, -s]],
            center: [0.0, -5.0, 1.6],
            focal: [1145.0, 1145.0],
            principal,
            radial: [0.0; 3],
            tangential: [0.0; 2],
            width: 1000,
            height: 1000,
        }
    }

    fn frame_of(cam: &Camera, world: [[f64; 3]; 2]) -> Keypoints2d {
        let mut kp = [[0.0f32; 2]; 17];
        for (j, p) in world.iter().enumerate() {
            kp[j] = normalize_screen(
                cam.project_world_to_pixels(*p).map(|v| v as f32),
                cam.width,
                cam.height,
            );
        }
        kp
    }

    fn level(cam: &Camera) -> LevelCamera {
        LevelCamera::from_camera(cam).unwrap()
    }

    #[test]
    fn a_level_centred_camera_is_left_as_it_is() {
        let cam = camera(0.0, [500.0, 500.0]);
        let kp = frame_of(&cam, [[0.3, 0.0, 0.4], [-0.2, 1.0, 1.9]]);
        let out = level(&cam).rectify(&kp);
        for j in 0..2 {
            for k in 0..2 {
                assert!((out[j][k] - kp[j][k]).abs() < 1e-4, "{out:?} {kp:?}");
            }
        }
    }

    #[test]
    fn tilt_and_principal_point_no_longer_move_the_picture() {
        // The same two world points seen by a level camera and by tilted
        // ones with other principal points rectify to the same place; the
        // point at the camera's height lands on the horizon.
        let points = [[0.3, 0.5, 0.0], [-0.1, 0.2, 1.6]];
        let level_cam = camera(0.0, [500.0, 500.0]);
        let want = level(&level_cam).rectify(&frame_of(&level_cam, points));
        for (tilt, principal) in [(0.19, [512.0, 515.0]), (0.28, [490.0, 501.0])] {
            let cam = camera(tilt, principal);
            let raw = frame_of(&cam, points);
            let got = level(&cam).rectify(&raw);
            assert!(
                (raw[0][1] - want[0][1]).abs() > 0.05,
                "tilt moves the raw picture"
            );
            for j in 0..2 {
                for k in 0..2 {
                    assert!((got[j][k] - want[j][k]).abs() < 1e-4, "{got:?} {want:?}");
                }
            }
            assert!(got[1][1].abs() < 1e-4, "horizon at v = 0: {}", got[1][1]);
            let mut stream: Vec<f32> = raw.iter().chain(raw.iter()).flatten().copied().collect();
            level(&cam).rectify_frames(&mut stream);
            assert_eq!(stream[34..36], [got[0][0], got[0][1]]);
        }
    }

    #[test]
    fn a_distorted_picture_rectifies_like_the_pinhole_one() {
        let cam = camera(0.25, [505.0, 498.0]);
        let lens = LensDistortion::from_coefficients(&[-0.3, 0.1, 0.001, -0.0008, -0.01])
            .unwrap()
            .unwrap();
        // Feet near the bottom corner, where the lens moves them most.
        let points = [[2.0, 0.5, 0.0], [-0.2, 0.3, 1.7]];
        let pinhole = frame_of(&cam, points);
        let through_lens = pinhole.map(|p| {
            let px = denormalize_screen(p, cam.width, cam.height).map(f64::from);
            let ideal = [
                (px[0] - cam.principal[0]) / cam.focal[0],
                (px[1] - cam.principal[1]) / cam.focal[1],
            ];
            let d = lens.distort(ideal);
            normalize_screen(
                [
                    (d[0] * cam.focal[0] + cam.principal[0]) as f32,
                    (d[1] * cam.focal[1] + cam.principal[1]) as f32,
                ],
                cam.width,
                cam.height,
            )
        });
        assert!(
            (through_lens[0][0] - pinhole[0][0]).abs() > 0.01,
            "the lens moves the feet"
        );
        let want = level(&cam).rectify(&pinhole);
        let got = level(&cam).with_lens(lens).rectify(&through_lens);
        for j in 0..2 {
            for k in 0..2 {
                assert!((got[j][k] - want[j][k]).abs() < 1e-4, "{got:?} {want:?}");
            }
        }
    }

    #[test]
    fn roll_about_the_optical_axis_is_undone() {
        // The same camera rolled by 20 degrees about its optical axis: the
        // up direction tells the rectification which way is up.
        let cam = camera(0.2, [500.0, 500.0]);
        let points = [[0.4, 0.3, 0.1], [-0.3, 0.6, 1.2]];
        let want = level(&cam).rectify(&frame_of(&cam, points));
        let (c, s) = (20f64.to_radians().cos(), 20f64.to_radians().sin());
        let roll = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]];
        let rotation: [[f64; 3]; 3] = std::array::from_fn(|i| {
            std::array::from_fn(|j| (0..3).map(|k| roll[i][k] * cam.rotation[k][j]).sum())
        });
        let rolled = Camera {
            rotation,
            principal: [500.0, 500.0],
            ..cam.clone()
        };
        let got = level(&rolled).rectify(&frame_of(&rolled, points));
        for j in 0..2 {
            for k in 0..2 {
                assert!((got[j][k] - want[j][k]).abs() < 1e-4, "{got:?} {want:?}");
            }
        }
    }

    #[test]
    fn bad_calibrations_are_named() {
        let ok = ([0.0, -1.0, 0.0], [1.0, 1.0], [0.0, 0.0]);
        assert!(LevelCamera::new(ok.0, ok.1, ok.2).is_ok());
        assert_eq!(
            LevelCamera::new([0.0, f64::NAN, 0.0], ok.1, ok.2),
            Err(CalibrationError::NonFinite { field: "up" }.into())
        );
        assert!(matches!(
            LevelCamera::new([0.0; 3], ok.1, ok.2),
            Err(LevelError::Calibration(CalibrationError::ZeroUp { .. }))
        ));
        assert!(matches!(
            LevelCamera::new(ok.0, [0.0, 1.0], ok.2),
            Err(LevelError::Calibration(
                CalibrationError::InvalidFocal { .. }
            ))
        ));
        // Looking 70 degrees down.
        let steep = [0.0, -20f64.to_radians().sin(), -70f64.to_radians().sin()];
        assert!(matches!(
            LevelCamera::new(steep, ok.1, ok.2),
            Err(LevelError::TooSteep { tilt_deg }) if (tilt_deg - 70.0).abs() < 0.5
        ));
        assert!(matches!(
            LevelCamera::from_pixels(ok.0, [1000.0; 2], [500.0; 2], 0, 10),
            Err(LevelError::Calibration(
                CalibrationError::InvalidImageSize { .. }
            ))
        ));
    }

    #[test]
    fn camera_heights_are_the_protocol_limits() {
        for ok in [MIN_CAMERA_HEIGHT, 1.56, MAX_CAMERA_HEIGHT] {
            assert!(is_camera_height(ok), "{ok}");
        }
        for bad in [0.0, 0.29, 10.01, -1.4, f32::NAN, f32::INFINITY] {
            assert!(!is_camera_height(bad), "{bad}");
        }
    }

    #[test]
    fn the_image_size_must_fit_the_keypoints() {
        let pixels = Coordinates::Pixels {
            width: 1000,
            height: 1002,
        };
        assert_eq!(calibration_image_size(pixels, None), Ok((1000, 1002)));
        assert_eq!(
            calibration_image_size(pixels, Some((1000, 1002))),
            Ok((1000, 1002))
        );
        assert_eq!(
            calibration_image_size(pixels, Some((1002, 1000))),
            Err(CalibrationError::ImageSizeMismatch {
                camera_width: 1002,
                camera_height: 1000,
                width: 1000,
                height: 1002
            })
        );
        assert_eq!(
            calibration_image_size(Coordinates::Normalized, Some((640, 480))),
            Ok((640, 480))
        );
        assert_eq!(
            calibration_image_size(Coordinates::Normalized, None),
            Err(CalibrationError::ImageSizeMissing)
        );
        assert_eq!(check_image_size(640, 480), Ok(()));
        assert!(check_image_size(0, 480).is_err());
    }
}

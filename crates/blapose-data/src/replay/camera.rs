//! A camera's calibration, as a replay file stores it and a request sends it.
//!
//! The file format and the client's requests carry the same calibration, so
//! it is one type, here below both; its value checks are the server's own
//! ([`blapose_core::level`], [`blapose_core::lens`]), so a calibration that
//! passes here is not refused for its values there. The wire conversion is
//! the client's.

use std::fmt;

use blapose_core::camera::Camera;
use blapose_core::layouts::Coordinates;
use blapose_core::lens::{LensDistortion, LensError};
use blapose_core::level::{self, CalibrationError, MAX_CAMERA_HEIGHT, MIN_CAMERA_HEIGHT};

/// A camera's calibration, for the server's camera-aware models.
///
/// A session (or offline request) that sends one is served by the
/// camera-aware models: the server turns its keypoints into what a level
/// camera at the same place would see before the model reads them. With
/// `distortion` the server first undoes the lens (keypoints detected in the
/// raw image); without it keypoints are taken as undistorted pixels.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CameraCalibration {
    /// Direction of world "up" (against gravity) in camera coordinates
    /// (x right, y down, z along the optical axis), any non-zero length:
    /// for world-to-camera rotation `R` and world z up, `R`'s third column.
    pub up: [f32; 3],
    /// `[fx, fy]` focal lengths in pixels, both > 0.
    pub focal: [f32; 2],
    /// `[cx, cy]` principal point in pixels.
    pub principal: [f32; 2],
    /// `(width, height)` of the image these pixel values refer to. Required
    /// with normalized keypoints; with pixel keypoints `None` means the
    /// input format's size, and a size given must equal it.
    pub image_size: Option<(u32, u32)>,
    /// The camera's height above the floor in metres, [`MIN_CAMERA_HEIGHT`]
    /// to [`MAX_CAMERA_HEIGHT`]; `None` = not given (0 on the wire). A
    /// rectified picture does not show it (seen from a camera k times
    /// higher, a scene looks like one k times smaller): the shipped
    /// camera-aware models scale each frame to the floor with it and
    /// refuse a calibration without it. Other models ignore it.
    pub height: Option<f32>,
    /// The lens's distortion in OpenCV's model and order, `[k1, k2, p1,
    /// p2, k3]` (what `cv2.calibrateCamera` reports; k3 = 0 for a
    /// four-coefficient calibration), for keypoints detected in the raw
    /// image; `None`: the keypoints are undistorted pixels.
    pub distortion: Option<[f32; 5]>,
}

/// Why a [`CameraCalibration`] cannot be used.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum CameraError {
    /// A value is NaN or infinite.
    #[error("{field} is not finite")]
    NonFinite {
        /// Which field: `up`, `focal`, `principal` or `height`.
        field: &'static str,
    },
    /// The up direction has no length.
    #[error("up {0:?} has no length (it must be a direction)")]
    ZeroUp([f32; 3]),
    /// A focal length is not positive.
    #[error("focal lengths must be > 0, got {0:?}")]
    Focal([f32; 2]),
    /// The principal point lies beyond any image.
    #[error("principal point {0:?} is beyond any image (at most {max} from the origin)", max = blapose_core::level::MAX_PRINCIPAL_ABS)]
    Principal([f32; 2]),
    /// The height is outside [`MIN_CAMERA_HEIGHT`]..=[`MAX_CAMERA_HEIGHT`].
    #[error("height {0} m is not a camera height of {MIN_CAMERA_HEIGHT} to {MAX_CAMERA_HEIGHT} m (leave it out when unknown)")]
    Height(f32),
    /// The image size has a zero side.
    #[error("image_size must be positive, got {width}x{height}")]
    ImageSize {
        /// Width in pixels.
        width: u32,
        /// Height in pixels.
        height: u32,
    },
    /// Normalized keypoints, but no image size to relate them to pixels.
    #[error("image_size is required with normalized keypoints (the calibration is in pixels)")]
    ImageSizeMissing,
    /// The distortion is not a usable lens model.
    #[error("distortion: {0}")]
    Distortion(LensError),
    /// The calibration's image size differs from the pixel keypoints'.
    #[error("image_size {camera_width}x{camera_height} differs from the keypoints' image size {width}x{height}")]
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

impl CameraError {
    /// The calibration field at fault: `up`, `focal`, `principal`,
    /// `image_size`, `height` or `distortion`.
    pub const fn field(&self) -> &'static str {
        match self {
            CameraError::NonFinite { field } => field,
            CameraError::ZeroUp(_) => "up",
            CameraError::Principal(_) => "principal",
            CameraError::Focal(_) => "focal",
            CameraError::Height(_) => "height",
            CameraError::Distortion(_) => "distortion",
            CameraError::ImageSize { .. }
            | CameraError::ImageSizeMissing
            | CameraError::ImageSizeMismatch { .. } => "image_size",
        }
    }

    /// What a failed shared check ([`blapose_core::level`]) means for
    /// `calibration`, in this crate's words.
    fn from_check(error: CalibrationError, calibration: &CameraCalibration) -> Self {
        match error {
            CalibrationError::NonFinite { field } => CameraError::NonFinite { field },
            CalibrationError::ZeroUp { .. } => CameraError::ZeroUp(calibration.up),
            CalibrationError::InvalidFocal { .. } => CameraError::Focal(calibration.focal),
            CalibrationError::PrincipalOutOfRange { .. } => {
                CameraError::Principal(calibration.principal)
            }
            CalibrationError::InvalidImageSize { width, height } => {
                CameraError::ImageSize { width, height }
            }
            CalibrationError::ImageSizeMissing => CameraError::ImageSizeMissing,
            CalibrationError::ImageSizeMismatch {
                camera_width,
                camera_height,
                width,
                height,
            } => CameraError::ImageSizeMismatch {
                camera_width,
                camera_height,
                width,
                height,
            },
        }
    }
}

impl CameraCalibration {
    /// The calibration of `camera`: `up` is the third column of its
    /// world-to-camera rotation, the image size its resolution and the
    /// height its centre's z. This assumes world z up with the floor at
    /// z = 0 (as in Human3.6M and the CMU examples); for another world
    /// frame, set `up` and `height` yourself. Values are rounded to `f32`;
    /// the distortion is dropped (Human3.6M's lens model is not OpenCV's).
    pub fn from_camera(camera: &Camera) -> Self {
        let r = &camera.rotation;
        CameraCalibration {
            up: [r[0][2], r[1][2], r[2][2]].map(|v| v as f32),
            focal: camera.focal.map(|v| v as f32),
            principal: camera.principal.map(|v| v as f32),
            image_size: Some((camera.width, camera.height)),
            height: Some(camera.center[2] as f32),
            distortion: None,
        }
    }

    /// Check the values the protocol requires, with the server's own checks
    /// ([`blapose_core::level`]): everything finite, focal lengths > 0, `up`
    /// of non-zero length, a given image size positive, a given height
    /// within [`MIN_CAMERA_HEIGHT`]..=[`MAX_CAMERA_HEIGHT`]. (The server also
    /// refuses an optical axis more than
    /// [`MAX_TILT_DEG`](blapose_core::level::MAX_TILT_DEG) degrees off the
    /// horizon; that is left to it, so a file's calibration can be loaded
    /// and replayed without it.)
    pub fn validate(&self) -> Result<(), CameraError> {
        let error = |e| CameraError::from_check(e, self);
        level::check_calibration(
            self.up.map(f64::from),
            self.focal.map(f64::from),
            self.principal.map(f64::from),
        )
        .map_err(error)?;
        if let Some((width, height)) = self.image_size {
            level::check_image_size(width, height).map_err(error)?;
        }
        if let Some(height) = self.height {
            if !height.is_finite() {
                return Err(CameraError::NonFinite { field: "height" });
            }
            if !level::is_camera_height(height) {
                return Err(CameraError::Height(height));
            }
        }
        LensDistortion::checked(
            self.distortion.as_ref().map_or(&[][..], |d| &d[..]),
            self.focal.map(f64::from),
            self.principal.map(f64::from),
            self.image_size,
        )
        .map_err(CameraError::Distortion)?;
        Ok(())
    }

    /// [`validate`](Self::validate), and check that the image size fits
    /// keypoints in `coordinates`: required for normalized ones, equal to
    /// theirs (or absent) for pixels.
    pub fn validate_for(&self, coordinates: Coordinates) -> Result<(), CameraError> {
        self.validate()?;
        level::calibration_image_size(coordinates, self.image_size)
            .map(|_| ())
            .map_err(|e| CameraError::from_check(e, self))
    }
}

impl fmt::Display for CameraCalibration {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "up [{:.3}, {:.3}, {:.3}], focal [{}, {}] px, principal [{}, {}] px",
            self.up[0],
            self.up[1],
            self.up[2],
            self.focal[0],
            self.focal[1],
            self.principal[0],
            self.principal[1]
        )?;
        if let Some((w, h)) = self.image_size {
            write!(f, ", image {w}x{h}")?;
        }
        if let Some(height) = self.height {
            write!(f, ", height {height} m")?;
        }
        if let Some(d) = self.distortion {
            write!(f, ", distortion {d:?}")?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn calibration() -> CameraCalibration {
        CameraCalibration {
            up: [0.01, -0.98, 0.2],
            focal: [1145.5, 1146.25],
            principal: [512.5, 515.0],
            image_size: Some((1000, 1002)),
            height: Some(1.75),
            distortion: None,
        }
    }

    #[test]
    fn camera_height_is_checked_and_named() {
        let c = calibration();
        for ok in [
            None,
            Some(MIN_CAMERA_HEIGHT),
            Some(1.4),
            Some(MAX_CAMERA_HEIGHT),
        ] {
            CameraCalibration { height: ok, ..c }
                .validate()
                .unwrap_or_else(|e| panic!("{ok:?}: {e}"));
        }
        for bad in [
            f32::NAN,
            f32::INFINITY,
            f32::NEG_INFINITY,
            0.1,
            50.0,
            0.0,
            -1.4,
            0.29,
            10.01,
        ] {
            let cal = CameraCalibration {
                height: Some(bad),
                ..c
            };
            let err = cal.validate().unwrap_err();
            assert_eq!(err.field(), "height", "{bad}: {err}");
            assert!(err.to_string().contains("height"), "{err}");
            if bad.is_finite() {
                assert_eq!(err, CameraError::Height(bad));
            } else {
                assert_eq!(err, CameraError::NonFinite { field: "height" });
            }
            // validate_for checks it too.
            assert_eq!(cal.validate_for(Coordinates::Normalized).unwrap_err(), err);
        }
    }

    #[test]
    fn camera_display_shows_the_height_when_given() {
        let c = calibration();
        let text = c.to_string();
        assert!(text.ends_with(", image 1000x1002, height 1.75 m"), "{text}");
        let text = CameraCalibration { height: None, ..c }.to_string();
        assert!(!text.contains("height"), "{text}");
        assert!(text.ends_with(", image 1000x1002"), "{text}");
    }

    #[test]
    fn camera_values_are_checked_and_the_field_named() {
        let c = calibration();
        c.validate().unwrap();
        let cases = [
            (
                CameraCalibration {
                    focal: [0.0, 1000.0],
                    ..c
                },
                "focal",
            ),
            (
                CameraCalibration {
                    focal: [1000.0, -3.0],
                    ..c
                },
                "focal",
            ),
            (
                CameraCalibration {
                    focal: [f32::NAN, 1000.0],
                    ..c
                },
                "focal",
            ),
            (
                CameraCalibration {
                    up: [0.0, f32::INFINITY, 0.0],
                    ..c
                },
                "up",
            ),
            (CameraCalibration { up: [0.0; 3], ..c }, "up"),
            (
                CameraCalibration {
                    principal: [500.0, f32::NEG_INFINITY],
                    ..c
                },
                "principal",
            ),
            (
                CameraCalibration {
                    image_size: Some((0, 1000)),
                    ..c
                },
                "image_size",
            ),
        ];
        for (bad, field) in cases {
            let err = bad.validate().unwrap_err();
            assert_eq!(err.field(), field, "{bad:?}: {err}");
            assert!(err.to_string().contains(field), "{err}");
        }
        // The image size against the keypoints' coordinates.
        c.validate_for(Coordinates::Pixels {
            width: 1000,
            height: 1002,
        })
        .unwrap();
        c.validate_for(Coordinates::Normalized).unwrap();
        assert!(matches!(
            c.validate_for(Coordinates::Pixels {
                width: 1002,
                height: 1000
            }),
            Err(CameraError::ImageSizeMismatch { .. })
        ));
        let no_size = CameraCalibration {
            image_size: None,
            ..c
        };
        no_size
            .validate_for(Coordinates::Pixels {
                width: 640,
                height: 480,
            })
            .unwrap();
        assert_eq!(
            no_size.validate_for(Coordinates::Normalized),
            Err(CameraError::ImageSizeMissing)
        );
    }

    #[test]
    fn calibration_from_a_camera_takes_the_third_column_as_up() {
        // Looking along world +y, tilted 10 degrees down: R is not
        // symmetric, so a row would give a different vector.
        let (s, c) = 10f64.to_radians().sin_cos();
        let forward = [0.0, c, -s];
        let right = [1.0, 0.0, 0.0];
        let down = [0.0, -s, -c];
        let camera = Camera {
            id: "t".into(),
            rotation: [right, down, forward],
            center: [0.0, -5.0, 1.4],
            focal: [1150.0, 1149.0],
            principal: [500.0, 499.0],
            radial: [0.0; 3],
            tangential: [0.0; 2],
            width: 1000,
            height: 998,
        };
        camera.validate().unwrap();
        let cal = CameraCalibration::from_camera(&camera);
        // World up (0, 0, 1) as a direction in camera coordinates.
        let a = camera.world_to_camera([0.3, 0.2, 1.0]);
        let b = camera.world_to_camera([0.3, 0.2, 2.0]);
        for k in 0..3 {
            assert!(
                (f64::from(cal.up[k]) - (b[k] - a[k])).abs() < 1e-6,
                "{:?} vs {:?}",
                cal.up,
                [b[0] - a[0], b[1] - a[1], b[2] - a[2]]
            );
        }
        assert!(cal.up[1] < 0.0, "up points to smaller image y");
        assert_eq!(cal.focal, [1150.0, 1149.0]);
        assert_eq!(cal.principal, [500.0, 499.0]);
        assert_eq!(cal.image_size, Some((1000, 998)));
        // World z up with the floor at z = 0: the centre's z.
        assert_eq!(cal.height, Some(1.4));
        let high = Camera {
            center: [0.0, -5.0, 3.25],
            ..camera.clone()
        };
        assert_eq!(CameraCalibration::from_camera(&high).height, Some(3.25));
        cal.validate().unwrap();
    }
}

//! Lens distortion of a user's calibrated camera, so keypoints detected in
//! the raw (distorted) image can be served as they are.
//!
//! The camera-aware models read geometry: where the feet fall below the
//! horizon and how far apart joints are. They were trained through
//! distortion-free cameras, and a wide lens bends exactly the image edges
//! where feet often are. A calibration may therefore carry the camera's
//! distortion coefficients in OpenCV's order and model (what
//! `cv2.calibrateCamera` and most calibration tools report), and every
//! keypoint is undistorted before it is rectified
//! ([`crate::level::LevelCamera::with_lens`]).
//!
//! The model, on a point `(x, y)` of the ideal image plane (pixel minus
//! principal point, over the focal length), `r2 = x^2 + y^2`:
//!
//! ```text
//! radial = 1 + k1 r2 + k2 r2^2 + k3 r2^3
//! x_d = x radial + 2 p1 x y + p2 (r2 + 2 x^2)
//! y_d = y radial + p1 (r2 + 2 y^2) + 2 p2 x y
//! ```
//!
//! (Human3.6M's own cameras use another tangential form; their model is
//! [`crate::camera::Intrinsics`].) Undistortion inverts it by fixed-point
//! iteration, which converges for lenses a calibration tool accepts; a
//! calibration whose model does not invert over its own image is refused
//! ([`LensDistortion::check_invertible`]).

/// Fixed-point iterations of [`LensDistortion::undistort`].
const ITERATIONS: usize = 30;

/// Largest round-trip error (in units of the focal length) accepted at the
/// image border by [`LensDistortion::check_invertible`]: 1e-6 of the focal
/// length is a thousandth of a pixel at any realistic focal length.
const MAX_ROUND_TRIP: f64 = 1e-6;

/// Why distortion coefficients are refused.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum LensError {
    /// Not 0, 4 or 5 coefficients.
    #[error("{0} distortion coefficients; give 4 (k1, k2, p1, p2) or 5 (k1, k2, p1, p2, k3) in OpenCV's order, or none for undistorted keypoints")]
    Count(usize),
    /// A coefficient is NaN or infinite.
    #[error("the distortion coefficients are not all finite")]
    NonFinite,
    /// The model folds over within the image: no unique undistortion.
    #[error("this distortion does not invert within the image (at pixel {pixel:?}); is it the OpenCV model in OpenCV's order (k1, k2, p1, p2, k3)?")]
    NotInvertible {
        /// The image point where it fails, pixels.
        pixel: [f64; 2],
    },
}

/// A camera's lens distortion in OpenCV's model (see the module docs).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LensDistortion {
    /// Radial `[k1, k2, k3]`.
    pub radial: [f64; 3],
    /// Tangential `[p1, p2]`.
    pub tangential: [f64; 2],
}

impl LensDistortion {
    /// From OpenCV-ordered coefficients `k1, k2, p1, p2[, k3]`; `None` for
    /// an empty list (keypoints already undistorted).
    pub fn from_coefficients(c: &[f64]) -> Result<Option<Self>, LensError> {
        let (radial, tangential) = match *c {
            [] => return Ok(None),
            [k1, k2, p1, p2] => ([k1, k2, 0.0], [p1, p2]),
            [k1, k2, p1, p2, k3] => ([k1, k2, k3], [p1, p2]),
            _ => return Err(LensError::Count(c.len())),
        };
        if !c.iter().all(|v| v.is_finite()) {
            return Err(LensError::NonFinite);
        }
        Ok(Some(Self { radial, tangential }))
    }

    /// A calibration's lens (`f32` coefficients, as sent), checked as the
    /// server checks it: [`Self::from_coefficients`], then, when the image
    /// it refers to is known, [`Self::check_invertible`] with its pixel
    /// intrinsics.
    pub fn checked(
        coefficients: &[f32],
        focal: [f64; 2],
        principal: [f64; 2],
        image_size: Option<(u32, u32)>,
    ) -> Result<Option<Self>, LensError> {
        let wide: Vec<f64> = coefficients.iter().map(|&v| f64::from(v)).collect();
        let lens = Self::from_coefficients(&wide)?;
        if let (Some(lens), Some((width, height))) = (&lens, image_size) {
            lens.check_invertible(focal, principal, width, height)?;
        }
        Ok(lens)
    }

    /// Where the lens shows the ideal point `[x, y]` (focal-length units).
    pub fn distort(&self, [x, y]: [f64; 2]) -> [f64; 2] {
        let [k1, k2, k3] = self.radial;
        let [p1, p2] = self.tangential;
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
        [
            x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
            y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y,
        ]
    }

    /// The ideal point the lens shows at `[xd, yd]` (focal-length units).
    /// Far outside the image, where the model may not invert, a point
    /// whose iteration leaves the finite numbers is returned as it is
    /// rather than as NaN (a stray detection must not poison a session).
    pub fn undistort(&self, [xd, yd]: [f64; 2]) -> [f64; 2] {
        let [k1, k2, k3] = self.radial;
        let [p1, p2] = self.tangential;
        let (mut x, mut y) = (xd, yd);
        for _ in 0..ITERATIONS {
            let r2 = x * x + y * y;
            let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
            let dx = 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x);
            let dy = p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y;
            x = (xd - dx) / radial;
            y = (yd - dy) / radial;
        }
        if x.is_finite() && y.is_finite() {
            [x, y]
        } else {
            [xd, yd]
        }
    }

    /// Check that undistortion recovers points over the whole image of a
    /// camera with these pixel intrinsics (its border, every 1/8 of each
    /// side, and its centre lines), so every keypoint in the picture has
    /// one answer.
    pub fn check_invertible(
        &self,
        focal: [f64; 2],
        principal: [f64; 2],
        width: u32,
        height: u32,
    ) -> Result<(), LensError> {
        let (w, h) = (f64::from(width), f64::from(height));
        let steps = (0..=8).map(|i| f64::from(i) / 8.0);
        let points = steps.clone().flat_map(|a| {
            steps
                .clone()
                .filter(move |&b| a == 0.0 || a == 1.0 || b == 0.0 || b == 1.0 || b == 0.5)
                .map(move |b| [a * w, b * h])
        });
        for pixel in points {
            let seen = [
                (pixel[0] - principal[0]) / focal[0],
                (pixel[1] - principal[1]) / focal[1],
            ];
            let back = self.distort(self.undistort(seen));
            let miss = (back[0] - seen[0]).hypot(back[1] - seen[1]);
            if miss.is_nan() || miss > MAX_ROUND_TRIP {
                return Err(LensError::NotInvertible { pixel });
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A typical wide phone lens (OpenCV calibration of a 1920x1080 camera).
    fn wide() -> LensDistortion {
        LensDistortion::from_coefficients(&[-0.28, 0.09, 0.0008, -0.0005, -0.012])
            .unwrap()
            .unwrap()
    }

    #[test]
    fn undistort_inverts_distort_over_the_image() {
        let lens = wide();
        for x in [-0.9, -0.5, 0.0, 0.3, 0.8] {
            for y in [-0.5, -0.2, 0.0, 0.4, 0.5] {
                let d = lens.distort([x, y]);
                let u = lens.undistort(d);
                assert!(
                    (u[0] - x).abs() < 1e-9 && (u[1] - y).abs() < 1e-9,
                    "{x},{y}: {u:?}"
                );
            }
        }
        // The lens moves the corners by a lot: this is not the identity.
        let d = lens.distort([0.9, 0.5]);
        assert!((d[0] - 0.9).abs() > 0.1);
        assert!(lens
            .check_invertible([1000.0, 1000.0], [960.0, 540.0], 1920, 1080)
            .is_ok());
        // A stray point far outside the picture stays finite.
        for far in [[40.0, -25.0], [1e6, 1e6], [-3e3, 0.5], [1e160, 1e160]] {
            let u = lens.undistort(far);
            assert!(u[0].is_finite() && u[1].is_finite(), "{far:?}: {u:?}");
        }
    }

    #[test]
    fn the_tangential_terms_follow_opencv() {
        // Values from OpenCV's formula evaluated by hand for (0.2, -0.1):
        // r2 = 0.05; radial = 1 + 0.1 * 0.05 = 1.005
        // x_d = 0.2 * 1.005 + 2 * 0.01 * 0.2 * -0.1 + 0.02 * (0.05 + 0.08) = 0.2032
        // y_d = -0.1 * 1.005 + 0.01 * (0.05 + 0.02) + 2 * 0.02 * 0.2 * -0.1 = -0.1006
        let lens = LensDistortion::from_coefficients(&[0.1, 0.0, 0.01, 0.02])
            .unwrap()
            .unwrap();
        let d = lens.distort([0.2, -0.1]);
        assert!(
            (d[0] - 0.2032).abs() < 1e-12 && (d[1] + 0.1006).abs() < 1e-12,
            "{d:?}"
        );
    }

    #[test]
    fn bad_coefficients_are_typed_errors() {
        assert_eq!(LensDistortion::from_coefficients(&[]), Ok(None));
        assert_eq!(
            LensDistortion::from_coefficients(&[0.1, 0.2, 0.3]),
            Err(LensError::Count(3))
        );
        assert_eq!(
            LensDistortion::from_coefficients(&[0.1, f64::NAN, 0.0, 0.0]),
            Err(LensError::NonFinite)
        );
        // Strong barrel distortion folds over at the corners of a wide view.
        let folded = LensDistortion::from_coefficients(&[-0.9, 0.0, 0.0, 0.0])
            .unwrap()
            .unwrap();
        assert!(matches!(
            folded.check_invertible([500.0, 500.0], [960.0, 540.0], 1920, 1080),
            Err(LensError::NotInvertible { .. })
        ));
    }
}

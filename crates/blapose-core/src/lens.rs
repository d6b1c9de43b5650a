//! Lens distortion: one type for the two distortion models blapose meets,
//! so every keypoint seen through a real lens is undone by one function.
//!
//! Why one type: the camera-aware models read geometry (where the feet
//! fall below the horizon, how far apart joints are) and were trained
//! through distortion-free cameras, while keypoints come from distorted
//! pictures: a user's calibrated camera, whose coefficients come in
//! OpenCV's model and order (what `cv2.calibrateCamera` and most
//! calibration tools report), and Human3.6M's cameras, whose published
//! calibration uses another tangential form. Both share the radial part and
//! the coefficients `k1, k2, k3, p1, p2`; [`LensModel`] names the tangential
//! form, and [`LensDistortion`] distorts and undistorts with either.
//!
//! On a point `(x, y)` of the ideal image plane (pixel minus principal
//! point, over the focal length), `r2 = x^2 + y^2`,
//! `radial = 1 + k1 r2 + k2 r2^2 + k3 r2^3`:
//!
//! ```text
//! OpenCV:     x_d = x radial + 2 p1 x y + p2 (r2 + 2 x^2)
//!             y_d = y radial + p1 (r2 + 2 y^2) + 2 p2 x y
//! Human3.6M:  x_d = x (radial + p1 x + p2 y) + p1 r2
//!             y_d = y (radial + p1 x + p2 y) + p2 r2
//! ```
//!
//! (Human3.6M's projection itself, generic over `f32` for the training hot
//! path, is [`crate::camera::Intrinsics::project`].) Undistortion inverts
//! the model by fixed-point iteration, which converges for lenses a
//! calibration tool accepts; a calibration whose model does not invert over
//! its own image is refused ([`LensDistortion::check_invertible`]). A
//! served calibration's lens is undone on each viewing ray
//! ([`crate::level::LevelCamera::with_lens`]); a picture's keypoints can
//! also be undone pixel by pixel ([`LensDistortion::undistort_pixel`]).

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

/// Which tangential form a lens's coefficients are in (module docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum LensModel {
    /// OpenCV's (and most calibration tools'): what a served calibration
    /// sends.
    OpenCv,
    /// Human3.6M's published camera model ([`crate::camera::Camera`]).
    Human36m,
}

impl LensModel {
    /// Fixed-point iterations of [`LensDistortion::undistort`]: each
    /// model keeps the count its numbers were first computed with.
    const fn iterations(self) -> usize {
        match self {
            Self::OpenCv => 30,
            Self::Human36m => 20,
        }
    }
}

/// A camera's lens distortion in one of the [`LensModel`]s.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LensDistortion {
    /// The tangential form the coefficients are in.
    pub model: LensModel,
    /// Radial `[k1, k2, k3]`.
    pub radial: [f64; 3],
    /// Tangential `[p1, p2]`.
    pub tangential: [f64; 2],
}

impl LensDistortion {
    /// A Human3.6M lens from its calibration's `k` and `p`.
    pub const fn human36m(radial: [f64; 3], tangential: [f64; 2]) -> Self {
        Self {
            model: LensModel::Human36m,
            radial,
            tangential,
        }
    }

    /// An OpenCV lens from OpenCV-ordered coefficients `k1, k2, p1,
    /// p2[, k3]`; `None` for an empty list (keypoints already undistorted).
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
        Ok(Some(Self {
            model: LensModel::OpenCv,
            radial,
            tangential,
        }))
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

    /// `1 + k1 r2 + k2 r2^2 + k3 r2^3`.
    #[inline(always)]
    fn radial_factor(&self, r2: f64) -> f64 {
        let [k1, k2, k3] = self.radial;
        1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    }

    /// The model at `(x, y)` as `(s, dx, dy)`: the lens shows the point at
    /// `(x s + dx, y s + dy)` (the form [`Self::undistort`] iterates on).
    #[inline(always)]
    fn terms(&self, x: f64, y: f64) -> (f64, f64, f64) {
        let [p1, p2] = self.tangential;
        let r2 = x * x + y * y;
        let radial = self.radial_factor(r2);
        match self.model {
            LensModel::OpenCv => (
                radial,
                2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
                p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y,
            ),
            LensModel::Human36m => (radial + p1 * x + p2 * y, p1 * r2, p2 * r2),
        }
    }

    /// Where the lens shows the ideal point `[x, y]` (focal-length units).
    pub fn distort(&self, [x, y]: [f64; 2]) -> [f64; 2] {
        let [p1, p2] = self.tangential;
        let r2 = x * x + y * y;
        let radial = self.radial_factor(r2);
        match self.model {
            LensModel::OpenCv => [
                x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
                y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y,
            ],
            LensModel::Human36m => {
                let s = radial + p1 * x + p2 * y;
                [x * s + p1 * r2, y * s + p2 * r2]
            }
        }
    }

    /// The ideal point the lens shows at `[xd, yd]` (focal-length units).
    /// Far outside the image, where the model may not invert, a point
    /// whose iteration leaves the finite numbers is returned as it is
    /// rather than as NaN (a stray detection must not poison a session).
    pub fn undistort(&self, [xd, yd]: [f64; 2]) -> [f64; 2] {
        let (mut x, mut y) = (xd, yd);
        for _ in 0..self.model.iterations() {
            let (s, dx, dy) = self.terms(x, y);
            x = (xd - dx) / s;
            y = (yd - dy) / s;
        }
        if x.is_finite() && y.is_finite() {
            [x, y]
        } else {
            [xd, yd]
        }
    }

    /// [`Self::undistort`] on a pixel of a camera with pixel intrinsics
    /// `focal` and `principal`: where a distortion-free camera with the
    /// same intrinsics shows the point.
    pub fn undistort_pixel(
        &self,
        focal: [f64; 2],
        principal: [f64; 2],
        pixel: [f64; 2],
    ) -> [f64; 2] {
        let seen = [
            (pixel[0] - principal[0]) / focal[0],
            (pixel[1] - principal[1]) / focal[1],
        ];
        let [x, y] = self.undistort(seen);
        [focal[0] * x + principal[0], focal[1] * y + principal[1]]
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

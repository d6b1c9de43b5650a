//! The export frames: which way is up in the files.
//!
//! blapose's poses are in whatever frame the lifter produced, most often the
//! camera's (x right, y down, z forward), where "up" is not an axis. Animation
//! tools expect Y up and biomechanics tools Z up, so every export rotates the
//! poses (no translation, no scaling beyond units) into a frame built from
//! the world's up direction given in the poses' coordinates (a replay file's
//! `camera_up`, or `-y` for camera axes, the same default as the HTML report):
//!
//! - **Y-up frame (BVH)**: `Y` = up; `Z` = the poses' `-z` axis made level
//!   (for camera coordinates: towards the camera), or their `-y` axis when up
//!   is within 45 degrees of `±z` (poses already Z-up); `X = Y × Z` (for
//!   camera coordinates: the image's right). A person facing the camera faces
//!   `+Z`, their left is `+X`.
//! - **Z-up frame (C3D, TRC)**: `(X, -Z, Y)` of the Y-up frame, the same
//!   rotation Blender applies when it imports a Y-up BVH (forward `-Z`, up
//!   `Y`). Poses that are already Z-up come out unchanged.

use crate::error::ExportError;
use crate::rot::{cross, dot, mul_vec, scale, sub, unit, Mat3, Vec3};

/// The rotation from the poses' coordinates to the export frames.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Axes {
    up: Vec3,
    /// Rows: the Y-up frame's X, Y and Z axes in the poses' coordinates.
    y_up: Mat3,
}

impl Default for Axes {
    /// Camera axes: up is `-y`.
    fn default() -> Self {
        Axes::from_up([0.0, -1.0, 0.0]).expect("valid up")
    }
}

impl Axes {
    /// The frames for a world whose up direction is `up` in the poses'
    /// coordinates (any non-zero length).
    pub fn from_up(up: [f64; 3]) -> Result<Axes, ExportError> {
        if !up.iter().all(|v| v.is_finite()) {
            return Err(ExportError::Up(up));
        }
        let y = unit(up, 1e-12).ok_or(ExportError::Up(up))?;
        let back: Vec3 = if y[2].abs() > std::f64::consts::FRAC_1_SQRT_2 {
            [0.0, -1.0, 0.0]
        } else {
            [0.0, 0.0, -1.0]
        };
        let z = unit(sub(back, scale(y, dot(back, y))), 1e-9).ok_or(ExportError::Up(up))?;
        let x = cross(y, z);
        Ok(Axes {
            up,
            y_up: [x, y, z],
        })
    }

    /// The up direction these frames were built from (as given).
    pub fn up(&self) -> [f64; 3] {
        self.up
    }

    /// Rows: the Y-up (BVH) frame's axes in the poses' coordinates.
    pub fn y_up_matrix(&self) -> Mat3 {
        self.y_up
    }

    /// Rows: the Z-up (C3D, TRC) frame's axes in the poses' coordinates.
    pub fn z_up_matrix(&self) -> Mat3 {
        let [x, y, z] = self.y_up;
        [x, scale(z, -1.0), y]
    }

    /// A point of the poses' coordinates in the Y-up frame.
    pub fn to_y_up(&self, p: Vec3) -> Vec3 {
        mul_vec(&self.y_up, p)
    }

    /// A point of the poses' coordinates in the Z-up frame.
    pub fn to_z_up(&self, p: Vec3) -> Vec3 {
        mul_vec(&self.z_up_matrix(), p)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rot::{mul, norm, transpose, IDENTITY};

    fn is_rotation(m: &Mat3) -> bool {
        let p = mul(m, &transpose(m));
        let det = dot(m[0], cross(m[1], m[2]));
        (0..3).all(|r| (0..3).all(|c| (p[r][c] - IDENTITY[r][c]).abs() < 1e-12))
            && (det - 1.0).abs() < 1e-12
    }

    #[test]
    fn camera_axes_flip_y_and_z() {
        let a = Axes::default();
        assert_eq!(a.to_y_up([1.0, 2.0, 3.0]), [1.0, -2.0, -3.0]);
        assert_eq!(a.to_z_up([1.0, 2.0, 3.0]), [1.0, 3.0, -2.0]);
    }

    #[test]
    fn z_up_poses_come_out_unchanged_in_the_z_up_frame() {
        let a = Axes::from_up([0.0, 0.0, 2.0]).unwrap();
        let p = [0.3, -0.2, 1.1];
        assert!(norm(sub(a.to_z_up(p), p)) < 1e-15);
        assert!(norm(sub(a.to_y_up(p), [0.3, 1.1, 0.2])) < 1e-15);
    }

    #[test]
    fn tilted_camera_up_becomes_exactly_up() {
        let up = [0.0, -0.9966696, -0.0815457];
        let a = Axes::from_up(up).unwrap();
        assert!(is_rotation(&a.y_up_matrix()) && is_rotation(&a.z_up_matrix()));
        let u = unit(up, 0.0).unwrap();
        assert!(norm(sub(a.to_y_up(u), [0.0, 1.0, 0.0])) < 1e-12);
        assert!(norm(sub(a.to_z_up(u), [0.0, 0.0, 1.0])) < 1e-12);
        for up in [[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.3, 0.3, 0.9]] {
            let a = Axes::from_up(up).unwrap();
            assert!(is_rotation(&a.y_up_matrix()), "{up:?}");
        }
    }

    #[test]
    fn bad_up_is_refused() {
        assert!(Axes::from_up([0.0; 3]).is_err());
        assert!(Axes::from_up([f64::NAN, 1.0, 0.0]).is_err());
    }
}

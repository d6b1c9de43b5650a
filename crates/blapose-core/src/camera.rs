//! The Human3.6M camera model, normalized screen coordinates and the
//! horizontal flip.
//!
//! Extrinsics map world to camera space as `X_c = R (X_w - center)`.
//! Projection is the Human3.6M / VideoPose3D lens model, exactly as
//! `../shared/data/README.md` states it:
//!
//! ```text
//! x = X_c[:2] / X_c[2];  r2 = |x|^2
//! radial = 1 + k1 r2 + k2 r2^2 + k3 r2^3;  tan = p1 x0 + p2 x1
//! x_d = x (radial + tan) + p r2;  pixel = f * x_d + c
//! ```
//!
//! The lens part of that model is [`crate::lens::LensDistortion`] in
//! [`crate::lens::LensModel::Human36m`] ([`Camera::lens`]), which also
//! undoes it. (VideoPose3D additionally clamps `x` to `[-1, 1]`; the README's model does
//! not, and neither do we. Inside the Human3.6M field of view the two agree.)
//! Points must lie in front of the camera (`z > 0`); for `z <= 0` the model is
//! meaningless and the result may be non-finite.
//!
//! The networks consume *normalized screen coordinates*
//! ([`normalize_screen`]): `x/w*2 - 1`, `y/w*2 - h/w`, so the image width maps
//! to `[-1, 1]` and the aspect ratio is kept. Because that map is affine, the
//! focal length and principal point can be rewritten in normalized units
//! ([`Camera::normalized_intrinsics`]) and projection then emits normalized
//! coordinates directly, with no per-point pixel round trip: this is the
//! training pipeline's hot path ([`Intrinsics::project_points`]).
//!
//! Horizontal flip: mirroring the image (`u -> w - u`, i.e. normalized
//! `x -> -x`) is the same as mirroring camera space (`X -> -X`) with the
//! principal point mirrored and `p1` negated (the tangential term is odd in
//! `x`). [`Camera::flipped`] builds that camera; with
//! [`crate::pose::flip_pose`] and [`crate::pose::flip_keypoints_pixels`] the
//! three stay consistent (tested below).

use std::ops::{Add, Div, Mul, Sub};

use crate::lens::LensDistortion;
use crate::pose::{Keypoints2d, Pose};

/// Why a camera or a projection request is invalid.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CameraError {
    /// A calibration value is NaN or infinite.
    #[error("camera {camera}: {field} is not finite")]
    NonFinite {
        /// Camera id.
        camera: String,
        /// Which field.
        field: &'static str,
    },
    /// Width or height is zero.
    #[error("camera {camera}: invalid resolution {width}x{height}")]
    InvalidResolution {
        /// Camera id.
        camera: String,
        /// Image width.
        width: u32,
        /// Image height.
        height: u32,
    },
    /// A focal length is not positive.
    #[error("camera {camera}: focal lengths must be positive, got {focal:?}")]
    InvalidFocal {
        /// Camera id.
        camera: String,
        /// The focal lengths.
        focal: [f64; 2],
    },
    /// `R` is not orthonormal.
    #[error("camera {camera}: R is not a rotation (max |R R^T - I| = {deviation:e})")]
    NotARotation {
        /// Camera id.
        camera: String,
        /// Largest deviation of `R R^T` from the identity.
        deviation: f64,
    },
    /// Batched input and output buffers differ in length.
    #[error("{input} input points but room for {output} outputs")]
    LengthMismatch {
        /// Input length.
        input: usize,
        /// Output length.
        output: usize,
    },
}

/// The arithmetic the lens model needs, so one implementation serves the
/// accurate `f64` pixel path and the fast `f32` normalized path.
pub trait Scalar:
    Copy + Add<Output = Self> + Sub<Output = Self> + Mul<Output = Self> + Div<Output = Self> + From<f32>
{
}
impl Scalar for f32 {}
impl Scalar for f64 {}

/// Lens intrinsics, in pixels ([`Camera::pixel_intrinsics`]) or normalized
/// screen units ([`Camera::normalized_intrinsics`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Intrinsics<T> {
    /// `[fx, fy]`.
    pub focal: [T; 2],
    /// `[cx, cy]`.
    pub principal: [T; 2],
    /// Radial distortion `[k1, k2, k3]`.
    pub radial: [T; 3],
    /// Tangential distortion `[p1, p2]`.
    pub tangential: [T; 2],
}

/// Intrinsics whose projection emits normalized screen coordinates.
pub type NormalizedIntrinsics = Intrinsics<f32>;

impl<T: Scalar> Intrinsics<T> {
    /// Project one camera-space point (`z > 0`) with the Human3.6M lens model.
    #[inline(always)]
    pub fn project(&self, p: [T; 3]) -> [T; 2] {
        let one = T::from(1.0);
        let inv_z = one / p[2];
        let x = p[0] * inv_z;
        let y = p[1] * inv_z;
        let r2 = x * x + y * y;
        let [k1, k2, k3] = self.radial;
        let [p1, p2] = self.tangential;
        let radial = one + r2 * (k1 + r2 * (k2 + r2 * k3));
        let s = radial + p1 * x + p2 * y;
        let xd = x * s + p1 * r2;
        let yd = y * s + p2 * r2;
        [
            self.focal[0] * xd + self.principal[0],
            self.focal[1] * yd + self.principal[1],
        ]
    }

    /// The intrinsics of the image mirrored about the vertical line
    /// `x = axis` (in the same units): principal point mirrored, `p1`
    /// negated. Use with camera-space points whose x is negated.
    pub fn mirrored(&self, axis: T) -> Self {
        let zero = T::from(0.0);
        Self {
            principal: [axis + axis - self.principal[0], self.principal[1]],
            tangential: [zero - self.tangential[0], self.tangential[1]],
            ..*self
        }
    }
}

impl Intrinsics<f64> {
    /// The lens of these intrinsics, in Human3.6M's model.
    pub fn lens(&self) -> LensDistortion {
        LensDistortion::human36m(self.radial, self.tangential)
    }

    /// Undo the lens model on one pixel: where a distortion-free camera
    /// with the same focal length and principal point shows the point
    /// ([`LensDistortion::undistort_pixel`]; exact to well under a
    /// micro-pixel for lenses like Human3.6M's within the image).
    pub fn undistort(&self, pixel: [f64; 2]) -> [f64; 2] {
        self.lens()
            .undistort_pixel(self.focal, self.principal, pixel)
    }
}

impl Intrinsics<f32> {
    /// Project many camera-space points at once into `out` (same length).
    ///
    /// Measured on the development machine (one core of a shared 2-core VM,
    /// `cargo test --release -p blapose-core -- --nocapture
    /// projection_throughput`): 0.7e8 to 1.4e8 points/s on one thread, i.e. a
    /// 243-frame, 17-joint window in about 40 µs.
    pub fn project_points(
        &self,
        cam_points: &[[f32; 3]],
        out: &mut [[f32; 2]],
    ) -> Result<(), CameraError> {
        if cam_points.len() != out.len() {
            return Err(CameraError::LengthMismatch {
                input: cam_points.len(),
                output: out.len(),
            });
        }
        let k = *self;
        for (p, o) in cam_points.iter().zip(out.iter_mut()) {
            *o = k.project(*p);
        }
        Ok(())
    }

    /// Project a camera-space pose.
    pub fn project_pose(&self, cam_pose: &Pose) -> Keypoints2d {
        cam_pose.map(|p| self.project(p))
    }
}

/// A calibrated Human3.6M camera (see the module docs for the model).
#[derive(Debug, Clone, PartialEq)]
pub struct Camera {
    /// Camera id, e.g. `"54138969"`.
    pub id: String,
    /// World-to-camera rotation, row-major.
    pub rotation: [[f64; 3]; 3],
    /// Camera centre in world coordinates (metres).
    pub center: [f64; 3],
    /// `[fx, fy]` in pixels.
    pub focal: [f64; 2],
    /// `[cx, cy]` in pixels.
    pub principal: [f64; 2],
    /// Radial distortion `[k1, k2, k3]`.
    pub radial: [f64; 3],
    /// Tangential distortion `[p1, p2]`.
    pub tangential: [f64; 2],
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
}

impl Camera {
    /// Check that every value is finite, the resolution and focal lengths
    /// are positive and `R` is orthonormal (to 1e-6).
    pub fn validate(&self) -> Result<(), CameraError> {
        let camera = || self.id.clone();
        let fields: [(&'static str, &[f64]); 6] = [
            ("R", self.rotation.as_flattened()),
            ("center", &self.center),
            ("focal", &self.focal),
            ("principal", &self.principal),
            ("k", &self.radial),
            ("p", &self.tangential),
        ];
        for (field, values) in fields {
            if !values.iter().all(|v| v.is_finite()) {
                return Err(CameraError::NonFinite {
                    camera: camera(),
                    field,
                });
            }
        }
        if self.width == 0 || self.height == 0 {
            return Err(CameraError::InvalidResolution {
                camera: camera(),
                width: self.width,
                height: self.height,
            });
        }
        if !(self.focal[0] > 0.0 && self.focal[1] > 0.0) {
            return Err(CameraError::InvalidFocal {
                camera: camera(),
                focal: self.focal,
            });
        }
        let r = nalgebra::Matrix3::from_fn(|i, j| self.rotation[i][j]);
        let deviation = (r * r.transpose() - nalgebra::Matrix3::identity()).amax();
        if deviation > 1e-6 {
            return Err(CameraError::NotARotation {
                camera: camera(),
                deviation,
            });
        }
        Ok(())
    }

    /// `R (p - center)`.
    #[inline]
    pub fn world_to_camera(&self, p: [f64; 3]) -> [f64; 3] {
        let d = [
            p[0] - self.center[0],
            p[1] - self.center[1],
            p[2] - self.center[2],
        ];
        self.rotation
            .map(|row| row[0] * d[0] + row[1] * d[1] + row[2] * d[2])
    }

    /// `R^T p + center` (inverse of [`Camera::world_to_camera`]).
    pub fn camera_to_world(&self, p: [f64; 3]) -> [f64; 3] {
        let r = &self.rotation;
        std::array::from_fn(|i| r[0][i] * p[0] + r[1][i] * p[1] + r[2][i] * p[2] + self.center[i])
    }

    /// A world-space pose in camera coordinates (computed in f64).
    pub fn world_to_camera_pose(&self, pose: &Pose) -> Pose {
        pose.map(|p| self.world_to_camera(p.map(f64::from)).map(|v| v as f32))
    }

    /// Batched [`Camera::world_to_camera`] for `f32` points.
    pub fn world_to_camera_points(
        &self,
        world: &[[f32; 3]],
        out: &mut [[f32; 3]],
    ) -> Result<(), CameraError> {
        if world.len() != out.len() {
            return Err(CameraError::LengthMismatch {
                input: world.len(),
                output: out.len(),
            });
        }
        let r = self.rotation.map(|row| row.map(|v| v as f32));
        let c = self.center.map(|v| v as f32);
        for (p, o) in world.iter().zip(out.iter_mut()) {
            let d = [p[0] - c[0], p[1] - c[1], p[2] - c[2]];
            *o = r.map(|row| row[0] * d[0] + row[1] * d[1] + row[2] * d[2]);
        }
        Ok(())
    }

    /// The camera's lens, in Human3.6M's model.
    pub fn lens(&self) -> LensDistortion {
        self.pixel_intrinsics().lens()
    }

    /// Intrinsics in pixels.
    pub fn pixel_intrinsics(&self) -> Intrinsics<f64> {
        Intrinsics {
            focal: self.focal,
            principal: self.principal,
            radial: self.radial,
            tangential: self.tangential,
        }
    }

    /// Intrinsics in normalized screen units: projecting with them gives
    /// [`normalize_screen`] of the pixel projection.
    pub fn normalized_intrinsics(&self) -> NormalizedIntrinsics {
        let w = self.width as f64;
        let h = self.height as f64;
        Intrinsics {
            focal: [self.focal[0] / w * 2.0, self.focal[1] / w * 2.0].map(|v| v as f32),
            principal: [
                self.principal[0] / w * 2.0 - 1.0,
                self.principal[1] / w * 2.0 - h / w,
            ]
            .map(|v| v as f32),
            radial: self.radial.map(|v| v as f32),
            tangential: self.tangential.map(|v| v as f32),
        }
    }

    /// Project a camera-space point (metres, `z > 0`) to pixels.
    #[inline]
    pub fn project_camera_to_pixels(&self, p: [f64; 3]) -> [f64; 2] {
        self.pixel_intrinsics().project(p)
    }

    /// Project a world-space point to pixels.
    #[inline]
    pub fn project_world_to_pixels(&self, p: [f64; 3]) -> [f64; 2] {
        self.project_camera_to_pixels(self.world_to_camera(p))
    }

    /// Project a world-space pose to pixels (computed in f64).
    pub fn project_world_pose_to_pixels(&self, pose: &Pose) -> Keypoints2d {
        let k = self.pixel_intrinsics();
        pose.map(|p| {
            k.project(self.world_to_camera(p.map(f64::from)))
                .map(|v| v as f32)
        })
    }

    /// Project a world-space pose straight to normalized screen coordinates.
    pub fn project_world_pose_normalized(&self, pose: &Pose) -> Keypoints2d {
        let k = self.normalized_intrinsics();
        self.world_to_camera_pose(pose).map(|p| k.project(p))
    }

    /// The camera that sees the horizontally mirrored image.
    ///
    /// Its rotation's first row is negated (so `world_to_camera` yields the
    /// mirrored camera-space point — `R` becomes a reflection, det -1), the
    /// principal point is mirrored (`cx -> w - cx`) and `p1` is negated.
    /// Projecting a world pose with it equals flipping the original pixels
    /// with [`crate::pose::flip_keypoints_pixels`] up to the left/right
    /// relabelling. Flipping twice gives the original camera.
    pub fn flipped(&self) -> Camera {
        let mut c = self.clone();
        c.rotation[0] = self.rotation[0].map(|v| -v);
        let k = self.pixel_intrinsics().mirrored(self.width as f64 / 2.0);
        c.principal = k.principal;
        c.tangential = k.tangential;
        c
    }
}

/// Pixels to normalized screen coordinates: `[x/w*2 - 1, y/w*2 - h/w]`.
#[inline]
pub fn normalize_screen(px: [f32; 2], width: u32, height: u32) -> [f32; 2] {
    let w = width as f32;
    [px[0] / w * 2.0 - 1.0, px[1] / w * 2.0 - height as f32 / w]
}

/// Inverse of [`normalize_screen`].
#[inline]
pub fn denormalize_screen(n: [f32; 2], width: u32, height: u32) -> [f32; 2] {
    let w = width as f32;
    [(n[0] + 1.0) * w / 2.0, (n[1] + height as f32 / w) * w / 2.0]
}

/// [`normalize_screen`] for every joint of a frame.
pub fn normalize_keypoints(kp: &Keypoints2d, width: u32, height: u32) -> Keypoints2d {
    kp.map(|p| normalize_screen(p, width, height))
}

/// [`denormalize_screen`] for every joint of a frame.
pub fn denormalize_keypoints(kp: &Keypoints2d, width: u32, height: u32) -> Keypoints2d {
    kp.map(|p| denormalize_screen(p, width, height))
}

/// [`normalize_screen`] in place for any number of points.
pub fn normalize_points(points: &mut [[f32; 2]], width: u32, height: u32) {
    for p in points {
        *p = normalize_screen(*p, width, height);
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::pose::{flip_keypoints_pixels, flip_pose};

    /// S9's camera 54138969 from ../shared/data/h36m/cameras.json (the
    /// calibration is a published constant, copied here as a test fixture).
    pub(crate) fn s9_cam() -> Camera {
        Camera {
            id: "54138969".into(),
            rotation: [
                [-0.9033486204435297, 0.4269119782787646, 0.04132109321984796],
                [0.04153061098352977, 0.182951140059007, -0.9822444139329296],
                [
                    -0.4268916470184284,
                    -0.8855930460167476,
                    -0.18299857527497945,
                ],
            ],
            center: [2.04445852504166, 4.935117279847931, 1.48122752752863],
            focal: [1145.04940458804, 1143.78109572365],
            principal: [512.541504956548, 515.4514869776],
            radial: [-0.207098910824901, 0.247775183068982, -0.00307515035078854],
            tangential: [-0.000975698859470499, -0.00142447157470321],
            width: 1000,
            height: 1002,
        }
    }

    #[test]
    fn undistorting_a_projection_gives_the_pinhole_projection() {
        let cam = s9_cam();
        let pinhole = Camera {
            radial: [0.0; 3],
            tangential: [0.0; 2],
            ..cam.clone()
        };
        let k = cam.pixel_intrinsics();
        let mut worst_shift = 0.0f64;
        // Points across the whole image, corners included.
        for x in [-1.6, -0.8, 0.0, 0.5, 1.7] {
            for y in [-1.7, -0.6, 0.1, 0.9, 1.6] {
                let p = [x, y, 4.0];
                let seen = cam.project_camera_to_pixels(p);
                let want = pinhole.project_camera_to_pixels(p);
                let got = k.undistort(seen);
                assert!(
                    (got[0] - want[0]).abs() < 1e-6 && (got[1] - want[1]).abs() < 1e-6,
                    "{p:?}: {got:?} vs {want:?}"
                );
                worst_shift = worst_shift.max((seen[0] - want[0]).hypot(seen[1] - want[1]));
            }
        }
        assert!(
            worst_shift > 10.0,
            "the lens moves corners by pixels: {worst_shift}"
        );
    }

    #[test]
    fn projection_matches_hand_computation() {
        // Independent check: the formula from the data README evaluated in
        // python3 with plain floats for the camera-space point (0.3, -0.2, 4):
        //   x = (0.075, -0.05); r2 = 0.008125; radial = 0.9983336767336777
        //   tan = p1*0.075 + p2*(-0.05) = -1.953835725126919e-06
        //   x_d = x*(radial+tan) + p*r2
        //   pixel = f*x_d + c = (598.2678633828624, 458.34460145227933)
        let px = s9_cam().project_camera_to_pixels([0.3, -0.2, 4.0]);
        let x: [f64; 2] = [0.075, -0.05];
        let r2: f64 = x[0] * x[0] + x[1] * x[1];
        let radial = 1.0 - 0.207098910824901 * r2 + 0.247775183068982 * r2 * r2
            - 0.00307515035078854 * r2 * r2 * r2;
        let tan = -0.000975698859470499 * x[0] - 0.00142447157470321 * x[1];
        let xd0 = x[0] * (radial + tan) - 0.000975698859470499 * r2;
        let xd1 = x[1] * (radial + tan) - 0.00142447157470321 * r2;
        let expect = [
            1145.04940458804 * xd0 + 512.541504956548,
            1143.78109572365 * xd1 + 515.4514869776,
        ];
        assert!(
            (px[0] - expect[0]).abs() < 1e-9 && (px[1] - expect[1]).abs() < 1e-9,
            "{px:?} vs {expect:?}"
        );
        assert!((px[0] - 598.2678633828624).abs() < 1e-9, "{px:?}");
        assert!((px[1] - 458.34460145227933).abs() < 1e-9, "{px:?}");
    }

    #[test]
    fn world_camera_round_trip_and_validation() {
        let cam = s9_cam();
        cam.validate().unwrap();
        let p = [0.4, -1.2, 0.9];
        let back = cam.camera_to_world(cam.world_to_camera(p));
        for i in 0..3 {
            assert!((back[i] - p[i]).abs() < 1e-12);
        }
        let mut bad = cam.clone();
        bad.focal[1] = f64::NAN;
        assert!(matches!(
            bad.validate(),
            Err(CameraError::NonFinite { field: "focal", .. })
        ));
        let mut bad = cam.clone();
        bad.rotation[0][0] *= 1.1;
        assert!(matches!(
            bad.validate(),
            Err(CameraError::NotARotation { .. })
        ));
        let mut bad = cam.clone();
        bad.width = 0;
        assert!(matches!(
            bad.validate(),
            Err(CameraError::InvalidResolution { .. })
        ));
        let mut bad = cam;
        bad.focal[0] = -1.0;
        assert!(matches!(
            bad.validate(),
            Err(CameraError::InvalidFocal { .. })
        ));
    }

    #[test]
    fn normalized_intrinsics_agree_with_pixels() {
        let cam = s9_cam();
        let kn = cam.normalized_intrinsics();
        for p in [[0.3f32, -0.2, 4.0], [-1.0, 0.8, 5.5], [0.0, 0.0, 3.0]] {
            let px = cam.project_camera_to_pixels(p.map(f64::from));
            let n = normalize_screen(px.map(|v| v as f32), cam.width, cam.height);
            let direct = kn.project(p);
            assert!(
                (n[0] - direct[0]).abs() < 1e-5 && (n[1] - direct[1]).abs() < 1e-5,
                "{n:?} {direct:?}"
            );
            let back = denormalize_screen(direct, cam.width, cam.height);
            assert!((back[0] as f64 - px[0]).abs() < 5e-3 && (back[1] as f64 - px[1]).abs() < 5e-3);
        }
        // image corners map to x = -1 / +1; the centre row to y = 0
        assert_eq!(normalize_screen([0.0, 501.0], 1000, 1002), [-1.0, 0.0]);
        assert_eq!(normalize_screen([1000.0, 0.0], 1000, 1002)[0], 1.0);
    }

    #[test]
    fn batched_projection_matches_single() {
        let k = s9_cam().normalized_intrinsics();
        let pts: Vec<[f32; 3]> = (0..100)
            .map(|i| {
                [
                    i as f32 * 0.01 - 0.5,
                    0.3 - i as f32 * 0.005,
                    3.0 + i as f32 * 0.02,
                ]
            })
            .collect();
        let mut out = vec![[0.0; 2]; 100];
        k.project_points(&pts, &mut out).unwrap();
        for (p, o) in pts.iter().zip(&out) {
            assert_eq!(*o, k.project(*p));
        }
        let mut short = vec![[0.0; 2]; 99];
        assert_eq!(
            k.project_points(&pts, &mut short),
            Err(CameraError::LengthMismatch {
                input: 100,
                output: 99
            })
        );
    }

    #[test]
    fn flipped_camera_is_consistent_with_flipped_pose_and_pixels() {
        let cam = s9_cam();
        let flipped = cam.flipped();
        assert_eq!(flipped.flipped(), cam);
        // a world pose in front of the camera
        let pose: Pose = std::array::from_fn(|j| {
            [
                0.1 * (j as f32 % 5.0) - 0.2,
                0.05 * j as f32 - 0.3,
                0.9 + 0.04 * j as f32,
            ]
        });
        let px = cam.project_world_pose_to_pixels(&pose);
        // world pose seen by the flipped camera, left/right relabelled
        let via_camera = flipped.project_world_pose_to_pixels(&pose);
        let mirrored = flip_keypoints_pixels(&px, cam.width);
        for (j, v) in via_camera.iter().enumerate() {
            let m = mirrored[crate::skeleton::flipped_joint(j)];
            assert!(
                (v[0] - m[0]).abs() < 1e-3 && (v[1] - m[1]).abs() < 1e-3,
                "joint {j}"
            );
        }
        // camera-space flip + flipped intrinsics == mirrored pixels
        let cam_pose = cam.world_to_camera_pose(&pose);
        let fk = cam.pixel_intrinsics().mirrored(cam.width as f64 / 2.0);
        let fp = flip_pose(&cam_pose);
        for (q, m) in fp.iter().zip(&mirrored) {
            let p = fk.project(q.map(f64::from));
            assert!((p[0] as f32 - m[0]).abs() < 1e-3 && (p[1] as f32 - m[1]).abs() < 1e-3);
        }
        // and in normalized units the mirror axis is x = 0
        let kn = cam.normalized_intrinsics();
        let n = kn.project(cam_pose[3]);
        let nf = kn.mirrored(0.0).project(fp[6]);
        assert!((n[0] + nf[0]).abs() < 1e-6 && (n[1] - nf[1]).abs() < 1e-6);
    }

    #[test]
    fn projection_throughput() {
        let k = s9_cam().normalized_intrinsics();
        let n = 4_000_000;
        let pts: Vec<[f32; 3]> = (0..n)
            .map(|i| {
                [
                    (i % 1000) as f32 * 1e-3 - 0.5,
                    (i % 777) as f32 * 1e-3 - 0.4,
                    4.0 + (i % 13) as f32 * 0.01,
                ]
            })
            .collect();
        let mut out = vec![[0.0f32; 2]; n];
        let t = std::time::Instant::now();
        k.project_points(&pts, &mut out).unwrap();
        let dt = t.elapsed().as_secs_f64();
        let rate = n as f64 / dt;
        println!(
            "normalized projection: {n} points in {:.1} ms = {:.3e} points/s",
            dt * 1e3,
            rate
        );
        assert!(out.iter().all(|p| p[0].is_finite()));
        // "millions of points per second" even on a loaded debug-ish build
        assert!(rate > 2e6, "projection too slow: {rate:.3e} points/s");
    }
}

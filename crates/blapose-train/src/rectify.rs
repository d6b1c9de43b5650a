//! Keypoints as a level camera would see them (an experiment; `--rectify`).
//!
//! The one cue to a person's absolute size in a single view is where the
//! feet meet the floor: the further below the horizon, the nearer the
//! person. Where the horizon lies in the picture depends on the camera's
//! tilt and principal point, which the network is never told, and
//! Human3.6M's four cameras differ by 10.7-16 degrees of tilt. Rectifying
//! turns each keypoint's viewing ray into the frame of a *level* camera at
//! the same place and heading (world vertical up, the optical axis turned
//! to the horizontal), so the horizon is always the line `v = 0`. What is
//! left unknown is the camera's height.
//!
//! The output is scaled like normalized screen coordinates (`x * f * 2 /
//! width`), so for a level camera with a centred principal point and no
//! lens distortion it is the identity. Lens distortion is ignored (the
//! keypoint's pixel is taken as the undistorted one): at Human3.6M's
//! `k1 = -0.2` that moves points near the image edge by a few percent,
//! the same in training and evaluation. It needs each view's calibration,
//! which the served models do not get, so rectified models are for
//! research only.

use blapose_core::camera::{denormalize_screen, Camera};
use blapose_core::pose::Keypoints2d;
use blapose_core::skeleton::NUM_JOINTS;

/// Smallest forward component of a ray before it is treated as grazing.
const MIN_FORWARD: f64 = 1e-3;

fn dot(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// The level twin of one camera, built once per camera: its right, down
/// and forward axes expressed in the camera's own frame, so a keypoint's
/// ray needs three dot products and no rotation.
#[derive(Debug, Clone)]
pub struct LevelView<'a> {
    cam: &'a Camera,
    /// Right, down and forward of the level frame, camera coordinates.
    axes: [[f64; 3]; 3],
    /// Output scale (`f * 2 / width`), like normalized screen coordinates.
    scale: [f64; 2],
}

impl<'a> LevelView<'a> {
    /// The level twin of `cam` (world `z` is up).
    pub fn new(cam: &'a Camera) -> Self {
        // Optical axis in world: the third row of the world-to-camera rotation.
        let axis = cam.rotation[2];
        let h = (axis[0] * axis[0] + axis[1] * axis[1]).sqrt().max(1e-9);
        let forward = [axis[0] / h, axis[1] / h, 0.0];
        // right = forward x up, with up = (0, 0, 1).
        let right = [forward[1], -forward[0], 0.0];
        let down = [0.0, 0.0, -1.0];
        let in_camera = |v: [f64; 3]| cam.rotation.map(|row| dot(&row, &v));
        Self {
            cam,
            axes: [in_camera(right), in_camera(down), in_camera(forward)],
            scale: [
                cam.focal[0] * 2.0 / f64::from(cam.width),
                cam.focal[1] * 2.0 / f64::from(cam.width),
            ],
        }
    }

    /// One frame of normalized screen keypoints seen through the camera,
    /// as its level twin would see them (see the module docs).
    pub fn rectify(&self, kp: &Keypoints2d) -> Keypoints2d {
        let cam = self.cam;
        let [right, down, forward] = &self.axes;
        kp.map(|p| {
            let px = denormalize_screen(p, cam.width, cam.height);
            let ray = [
                (f64::from(px[0]) - cam.principal[0]) / cam.focal[0],
                (f64::from(px[1]) - cam.principal[1]) / cam.focal[1],
                1.0,
            ];
            let z = dot(&ray, forward).max(MIN_FORWARD);
            [
                (dot(&ray, right) / z * self.scale[0]) as f32,
                (dot(&ray, down) / z * self.scale[1]) as f32,
            ]
        })
    }

    /// [`LevelView::rectify`] for a whole stream (`frames * 34` values).
    pub fn rectify_input(&self, input: &[f32]) -> Vec<f32> {
        input
            .chunks_exact(2 * NUM_JOINTS)
            .flat_map(|frame| {
                let kp: Keypoints2d = std::array::from_fn(|j| [frame[2 * j], frame[2 * j + 1]]);
                self.rectify(&kp).into_iter().flatten()
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use blapose_core::camera::normalize_screen;

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

    #[test]
    fn a_level_centred_camera_is_left_as_it_is() {
        let cam = camera(0.0, [500.0, 500.0]);
        let kp = frame_of(&cam, [[0.3, 0.0, 0.4], [-0.2, 1.0, 1.9]]);
        let out = LevelView::new(&cam).rectify(&kp);
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
        let level = camera(0.0, [500.0, 500.0]);
        let want = LevelView::new(&level).rectify(&frame_of(&level, points));
        for (tilt, principal) in [(0.19, [512.0, 515.0]), (0.28, [490.0, 501.0])] {
            let cam = camera(tilt, principal);
            let raw = frame_of(&cam, points);
            let got = LevelView::new(&cam).rectify(&raw);
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
            let stream: Vec<f32> = raw.iter().chain(raw.iter()).flatten().copied().collect();
            let rectified = LevelView::new(&cam).rectify_input(&stream);
            assert_eq!(rectified.len(), stream.len());
            assert_eq!(rectified[34..36], [got[0][0], got[0][1]]);
        }
    }
}

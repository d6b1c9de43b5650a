//! The wide camera distribution: where a user might put a phone or a
//! webcam, not where Human3.6M put its four cameras. The camera-aware
//! models are trained through it (`train --wide-cameras`,
//! [`crate::synth`]) and the many-bodies benchmark (`blapose-lab bodies`)
//! measures on it.
//!
//! Why its own module: the bounds are one definition, written once
//! ([`wide_cameras`]), shared by training and the benchmark, serialized
//! into every benchmark report and checked by tests, so a number in the
//! model card always says which cameras it was measured on.
//!
//! One draw ([`draw_camera`]), in Human3.6M's world (metres, `z` up, the
//! floor at `z = 0`):
//!
//! - the camera stands at a uniform horizontal *distance* from an aim point
//!   (the person's mean root over the clip), at any azimuth around it
//!   (uniform over the full circle: *any yaw*), at a uniform *height* above
//!   the floor;
//! - it faces the aim point horizontally, turned by a small uniform *aim
//!   offset* (so the person is not always in the middle of the picture),
//!   then tilted by a uniform *pitch* (negative looks down) and rolled by
//!   a uniform *roll* about its optical axis;
//! - the image size is one of [`CameraRange::resolutions`], the horizontal
//!   field of view uniform, pixels square (`fx = fy`), the principal point
//!   within [`CameraRange::principal_jitter`] of the image size from the
//!   centre, no lens distortion.
//!
//! [`draw_camera_seeing`] redraws until every joint of every frame is in
//! front of the camera (at least [`MIN_JOINT_DEPTH`]) and inside the image:
//! the benchmark asks about people the user can see. The rejection makes
//! the accepted distribution narrower than the bounds where they
//! combine badly (a steep downward pitch close to a low camera shows no
//! head); the report records the bounds, and the tests check that every
//! accepted camera lies within them.

use blapose_core::camera::Camera;
use blapose_core::level::WIDE_CAMERA_ENVELOPE;
use blapose_core::Pose;
use rand::Rng;
use serde::Serialize;

use crate::error::TrainError;

/// Nearest a joint may be in front of the camera, metres.
pub const MIN_JOINT_DEPTH: f64 = 0.3;

/// Bounds of the wide cameras (all uniform; angles in degrees).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct CameraRange {
    /// Camera height above the floor, metres.
    pub height_m: [f64; 2],
    /// Horizontal distance from the person's mean root, metres.
    pub distance_m: [f64; 2],
    /// Azimuth of the camera around the person (full circle).
    pub yaw_deg: [f64; 2],
    /// Horizontal turn of the optical axis away from the person.
    pub aim_offset_deg: [f64; 2],
    /// Optical axis above (+) or below (-) the horizon.
    pub pitch_deg: [f64; 2],
    /// Roll about the optical axis.
    pub roll_deg: [f64; 2],
    /// Horizontal field of view.
    pub hfov_deg: [f64; 2],
    /// Largest offset of the principal point from the image centre, as a
    /// fraction of the image width (x) and height (y).
    pub principal_jitter: f64,
    /// Image sizes (width, height), one drawn uniformly.
    pub resolutions: Vec<[u32; 2]>,
}

/// The documented wide distribution:
/// height 0.5-3.0 m, distance 2-10 m, any yaw, pitch -35 to +15 degrees,
/// roll +-5, horizontal field of view 40-100 degrees, principal point
/// within 2 % of the centre, 640x480 to 1920x1080. Height, pitch and field
/// of view are [`WIDE_CAMERA_ENVELOPE`], which the server enforces for
/// models trained here.
pub fn wide_cameras() -> CameraRange {
    let envelope = WIDE_CAMERA_ENVELOPE;
    CameraRange {
        height_m: envelope.height_m,
        distance_m: [2.0, 10.0],
        yaw_deg: [-180.0, 180.0],
        aim_offset_deg: [-10.0, 10.0],
        pitch_deg: envelope.pitch_deg,
        roll_deg: [-5.0, 5.0],
        hfov_deg: envelope.hfov_deg,
        principal_jitter: 0.02,
        resolutions: vec![
            [640, 480],
            [800, 600],
            [1024, 768],
            [1280, 720],
            [1280, 960],
            [1920, 1080],
        ],
    }
}

/// One drawn camera and the values it was drawn with.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct DrawnCamera {
    /// The calibrated camera (world `z` up, no distortion).
    #[serde(skip)]
    pub camera: Camera,
    /// Height above the floor, metres.
    pub height_m: f64,
    /// Horizontal distance to the aim point, metres.
    pub distance_m: f64,
    /// Azimuth of the camera around the aim point.
    pub yaw_deg: f64,
    /// Aim offset.
    pub aim_offset_deg: f64,
    /// Pitch (negative looks down).
    pub pitch_deg: f64,
    /// Roll.
    pub roll_deg: f64,
    /// Horizontal field of view.
    pub hfov_deg: f64,
}

fn uniform<R: Rng + ?Sized>(rng: &mut R, [lo, hi]: [f64; 2]) -> f64 {
    if hi > lo {
        rng.random_range(lo..hi)
    } else {
        lo
    }
}

impl CameraRange {
    /// Check the bounds (ordered, finite, physically possible).
    pub fn validate(&self) -> Result<(), TrainError> {
        let bad = |m: String| Err(TrainError::InvalidArgument(m));
        let ranges = [
            ("height_m", self.height_m),
            ("distance_m", self.distance_m),
            ("yaw_deg", self.yaw_deg),
            ("aim_offset_deg", self.aim_offset_deg),
            ("pitch_deg", self.pitch_deg),
            ("roll_deg", self.roll_deg),
            ("hfov_deg", self.hfov_deg),
        ];
        for (name, [lo, hi]) in ranges {
            if !(lo.is_finite() && hi.is_finite() && lo <= hi) {
                return bad(format!("camera range {name} [{lo}, {hi}] is not ordered"));
            }
        }
        if self.height_m[0] <= 0.0 || self.distance_m[0] <= 0.0 {
            return bad("camera height and distance must be positive".into());
        }
        if self.hfov_deg[0] <= 0.0 || self.hfov_deg[1] >= 180.0 {
            return bad("horizontal field of view must be in (0, 180) degrees".into());
        }
        if self.pitch_deg[0] <= -90.0 || self.pitch_deg[1] >= 90.0 {
            return bad("pitch must be in (-90, 90) degrees".into());
        }
        if !(0.0..0.5).contains(&self.principal_jitter) {
            return bad("principal_jitter must be in [0, 0.5)".into());
        }
        if self.resolutions.is_empty() || self.resolutions.iter().any(|r| r[0] == 0 || r[1] == 0) {
            return bad("need at least one non-empty image size".into());
        }
        Ok(())
    }
}

/// Draw one camera aimed at `aim` (world, metres; only its horizontal
/// position is used) from `range` (see the module docs).
pub fn draw_camera<R: Rng + ?Sized>(
    range: &CameraRange,
    aim: [f32; 3],
    rng: &mut R,
) -> DrawnCamera {
    let height_m = uniform(rng, range.height_m);
    let distance_m = uniform(rng, range.distance_m);
    let yaw_deg = uniform(rng, range.yaw_deg);
    let aim_offset_deg = uniform(rng, range.aim_offset_deg);
    let pitch_deg = uniform(rng, range.pitch_deg);
    let roll_deg = uniform(rng, range.roll_deg);
    let hfov_deg = uniform(rng, range.hfov_deg);
    let [width, height] = range.resolutions[rng.random_range(0..range.resolutions.len())];
    let (w, h) = (f64::from(width), f64::from(height));
    let j = range.principal_jitter;
    let principal = [
        w * (0.5 + uniform(rng, [-j, j])),
        h * (0.5 + uniform(rng, [-j, j])),
    ];
    let f = w / 2.0 / (hfov_deg.to_radians() / 2.0).tan();

    // Camera centre: on a circle around the aim point.
    let psi = yaw_deg.to_radians();
    let center = [
        f64::from(aim[0]) + distance_m * psi.cos(),
        f64::from(aim[1]) + distance_m * psi.sin(),
        height_m,
    ];
    // Level forward: towards the aim point, turned by the aim offset.
    let heading = psi + std::f64::consts::PI + aim_offset_deg.to_radians();
    let level = [heading.cos(), heading.sin(), 0.0];
    let up = [0.0, 0.0, 1.0];
    // right = forward x up (camera x right, y down, z forward).
    let right = [level[1], -level[0], 0.0];
    let (sp, cp) = pitch_deg.to_radians().sin_cos();
    let forward: [f64; 3] = std::array::from_fn(|i| cp * level[i] + sp * up[i]);
    let down: [f64; 3] = std::array::from_fn(|i| sp * level[i] - cp * up[i]);
    let (sr, cr) = roll_deg.to_radians().sin_cos();
    let right_r: [f64; 3] = std::array::from_fn(|i| cr * right[i] + sr * down[i]);
    let down_r: [f64; 3] = std::array::from_fn(|i| -sr * right[i] + cr * down[i]);
    DrawnCamera {
        camera: Camera {
            id: "benchmark".into(),
            rotation: [right_r, down_r, forward],
            center,
            focal: [f, f],
            principal,
            radial: [0.0; 3],
            tangential: [0.0; 2],
            width,
            height,
        },
        height_m,
        distance_m,
        yaw_deg,
        aim_offset_deg,
        pitch_deg,
        roll_deg,
        hfov_deg,
    }
}

/// Whether every joint of every pose (world) is at least
/// [`MIN_JOINT_DEPTH`] in front of `cam` and inside its image.
pub fn sees_everything(cam: &Camera, poses: &[Pose]) -> bool {
    let k = cam.pixel_intrinsics();
    poses.iter().flatten().all(|j| {
        let c = cam.world_to_camera(j.map(f64::from));
        if c[2] < MIN_JOINT_DEPTH {
            return false;
        }
        let [u, v] = k.project(c);
        (0.0..=f64::from(cam.width)).contains(&u) && (0.0..=f64::from(cam.height)).contains(&v)
    })
}

/// The mean root (joint 0) of `poses`: where the cameras aim.
pub fn mean_root(poses: &[Pose]) -> [f32; 3] {
    let n = poses.len().max(1) as f32;
    std::array::from_fn(|c| poses.iter().map(|p| p[0][c]).sum::<f32>() / n)
}

/// [`draw_camera`] aimed at the poses' mean root, redrawn until
/// [`sees_everything`]; an error after `max_tries` draws.
pub fn draw_camera_seeing<R: Rng + ?Sized>(
    range: &CameraRange,
    poses: &[Pose],
    max_tries: usize,
    rng: &mut R,
) -> Result<DrawnCamera, TrainError> {
    if poses.is_empty() {
        return Err(TrainError::InvalidArgument("no poses to frame".into()));
    }
    let aim = mean_root(poses);
    for _ in 0..max_tries {
        let cam = draw_camera(range, aim, rng);
        if sees_everything(&cam.camera, poses) {
            return Ok(cam);
        }
    }
    Err(TrainError::Data(format!(
        "no camera of the range framed the clip in {max_tries} draws"
    )))
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    /// A standing person: pelvis at 0.9 m, head at 1.75, feet at 0.1,
    /// walking 1 m along x over the clip.
    fn clip() -> Vec<Pose> {
        (0..20)
            .map(|t| {
                let x = 3.0 + t as f32 * 0.05;
                std::array::from_fn(|j| {
                    let z = 0.1 + 1.65 * j as f32 / 16.0;
                    let y = 1.0 + if j % 2 == 0 { 0.2 } else { -0.2 };
                    [x, y, z]
                })
            })
            .collect()
    }

    #[test]
    fn every_accepted_camera_respects_every_bound_and_frames_the_person() {
        let range = wide_cameras();
        range.validate().unwrap();
        let poses = clip();
        let aim = mean_root(&poses);
        let mut rng = rand::rngs::StdRng::seed_from_u64(5);
        let in_range = |v: f64, [lo, hi]: [f64; 2]| v >= lo - 1e-9 && v <= hi + 1e-9;
        for _ in 0..300 {
            let d = draw_camera_seeing(&range, &poses, 1000, &mut rng).unwrap();
            let c = &d.camera;
            c.validate().unwrap();
            assert!(sees_everything(c, &poses));
            // Drawn values within the bounds ...
            assert!(in_range(d.height_m, range.height_m));
            assert!(in_range(d.distance_m, range.distance_m));
            assert!(in_range(d.pitch_deg, range.pitch_deg));
            assert!(in_range(d.roll_deg, range.roll_deg));
            assert!(in_range(d.hfov_deg, range.hfov_deg));
            assert!(range.resolutions.contains(&[c.width, c.height]));
            // ... and the camera really has them.
            assert!((c.center[2] - d.height_m).abs() < 1e-9);
            let dist = ((c.center[0] - f64::from(aim[0])).powi(2)
                + (c.center[1] - f64::from(aim[1])).powi(2))
            .sqrt();
            assert!((dist - d.distance_m).abs() < 1e-6);
            // Optical axis (world) = third row of R; its z is sin(pitch).
            let pitch = c.rotation[2][2].asin().to_degrees();
            assert!(
                (pitch - d.pitch_deg).abs() < 1e-6,
                "{pitch} vs {}",
                d.pitch_deg
            );
            // Roll: tan(roll) = right.z / down.z (world z of the
            // camera's right and down axes).
            let roll = (c.rotation[0][2] / c.rotation[1][2]).atan().to_degrees();
            assert!((roll - d.roll_deg).abs() < 1e-6, "{roll} vs {}", d.roll_deg);
            let hfov = 2.0 * (f64::from(c.width) / 2.0 / c.focal[0]).atan();
            assert!((hfov.to_degrees() - d.hfov_deg).abs() < 1e-6);
            assert_eq!(c.focal[0], c.focal[1]);
            let (w, h) = (f64::from(c.width), f64::from(c.height));
            assert!((c.principal[0] / w - 0.5).abs() <= range.principal_jitter + 1e-12);
            assert!((c.principal[1] / h - 0.5).abs() <= range.principal_jitter + 1e-12);
            // A rotation, right-handed.
            let r = &c.rotation;
            let det = r[0][0] * (r[1][1] * r[2][2] - r[1][2] * r[2][1])
                - r[0][1] * (r[1][0] * r[2][2] - r[1][2] * r[2][0])
                + r[0][2] * (r[1][0] * r[2][1] - r[1][1] * r[2][0]);
            assert!((det - 1.0).abs() < 1e-9);
            // Rectifiable, as the calibrated models need.
            blapose_core::level::LevelCamera::from_camera(c).unwrap();
        }
    }

    #[test]
    fn the_camera_faces_the_person_and_sees_up_as_up() {
        let range = CameraRange {
            pitch_deg: [0.0, 0.0],
            roll_deg: [0.0, 0.0],
            aim_offset_deg: [0.0, 0.0],
            ..wide_cameras()
        };
        let mut rng = rand::rngs::StdRng::seed_from_u64(1);
        let aim = [1.0, 2.0, 0.9];
        for _ in 0..50 {
            let d = draw_camera(&range, aim, &mut rng);
            let c = d.camera.world_to_camera([1.0, 2.0, d.height_m]);
            assert!(c[0].abs() < 1e-9 && c[1].abs() < 1e-9, "{c:?}");
            assert!((c[2] - d.distance_m).abs() < 1e-9);
            // A point above is higher in the image (smaller y).
            let above = d.camera.world_to_camera([1.0, 2.0, d.height_m + 1.0]);
            assert!(above[1] < 0.0);
        }
    }

    #[test]
    fn a_person_out_of_reach_is_an_error_and_bad_ranges_are_refused() {
        let range = CameraRange {
            distance_m: [0.01, 0.02],
            ..wide_cameras()
        };
        let mut rng = rand::rngs::StdRng::seed_from_u64(2);
        assert!(draw_camera_seeing(&range, &clip(), 20, &mut rng).is_err());
        assert!(draw_camera_seeing(&wide_cameras(), &[], 20, &mut rng).is_err());
        let bad = CameraRange {
            hfov_deg: [100.0, 40.0],
            ..wide_cameras()
        };
        assert!(bad.validate().is_err());
        let bad = CameraRange {
            resolutions: vec![],
            ..wide_cameras()
        };
        assert!(bad.validate().is_err());
    }
}

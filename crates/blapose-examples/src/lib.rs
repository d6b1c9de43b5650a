//! Licence-clean example sequences built from real CMU motion.
//!
//! The repository may not ship Human3.6M data or anything derived from it,
//! yet a replay example should look like what a real pipeline produces. So
//! an example takes the *motion* of a CMU Graphics Lab clip (free for any
//! use) and builds the rest synthetically:
//!
//! 1. **Skeleton.** Each frame's 16 CMU bone *directions* are kept and the
//!    lengths replaced by [`PERSON_LENGTHS`] times a per-clip stature factor:
//!    Human3.6M-convention lengths of a plausible adult, chosen from typical
//!    human proportions (not measured from any Human3.6M subject). CMU's own
//!    joint centres differ from Human3.6M's (e.g. its forearm ends ~5 cm
//!    earlier), and a model trained on Human3.6M predicts Human3.6M-style
//!    lengths, so the ground truth must use that convention to be fair.
//! 2. **Camera.** A camera of our own ([`camera_for_clip`]): 1000x1000 px,
//!    focal 1150 px, principal point at the image centre, mild barrel
//!    distortion, 1.4 m high, about 5 m from the subject, looking at the
//!    clip's mean pelvis position at 50 degrees off the perpendicular of the
//!    direction of travel, moved back until every joint of every frame lies
//!    40 px inside the image. Its calibration is part of the replay file
//!    (`camera_up`, the third column of its rotation; `camera_focal`;
//!    `camera_principal`; `camera_height`, its centre's z, 1.4 m, since the
//!    CMU floor is at z = 0), so replaying an example uses the server's
//!    camera-aware models; the distortion is not (the protocol takes
//!    keypoints as undistorted pixels, and this lens is mild).
//! 3. **2D keypoints** ("detections"): the ground-truth skeleton projected
//!    with that camera plus Gaussian noise, [`ExampleConfig::noise_px`] per
//!    coordinate, 1.5 times that for wrists and ankles (detectors find
//!    extremities least precisely).
//! 4. **Lifted pose** ("a lifter's output"): the ground truth in camera
//!    coordinates, root-relative, rebuilt with each bone's length off by a
//!    fixed per-bone bias and per-frame jitter, and each direction tilted by a
//!    small random angle: the kind of error real lifters make (inconsistent
//!    bone lengths over time), which the bone-length adjustment can repair.
//!
//! Coordinates: CMU clips are +Z up in metres, the convention of Human3.6M
//! world space, so they are used as world coordinates unchanged; the camera
//! maps them with `X_c = R (X_w - center)` (x right, y down, z forward).
//! `pose_3d` and `gt_3d` are in camera coordinates with the pelvis at the
//! origin, as lifters output them.
//!
//! Everything is drawn from one seeded generator per clip, so the same seed
//! gives the same files.

use blapose_core::bones::{decompose, rebuild, BoneError};
use blapose_core::camera::Camera;
use blapose_core::layouts::{InputFormat, KeypointLayout};
use blapose_core::pose::root_relative;
use blapose_core::skeleton::{NUM_BONES, NUM_JOINTS};
use blapose_core::{BoneLengths, Pose};
use blapose_data::npz::{Array, Npz};
use blapose_data::replay::{CameraCalibration, Sequence, SequenceError};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, Normal};

/// Bone lengths (metres) of the example person in the Human3.6M joint
/// convention, bone order of [`blapose_core::skeleton::BONE_NAMES`]: hip
/// 0.13 (pelvis centre to hip joint), thigh 0.45, calf 0.44, spine 0.23,
/// thorax 0.25, neck 0.11, head 0.12, shoulder 0.15, upper arm 0.28, forearm
/// 0.25 (to the wrist). Chosen from typical adult proportions (stature about
/// 1.75 m); not taken from any Human3.6M subject. Left and right are equal.
pub const PERSON_LENGTHS: BoneLengths = [
    0.13, 0.45, 0.44, // r_hip, r_thigh, r_calf
    0.13, 0.45, 0.44, // l_hip, l_thigh, l_calf
    0.23, 0.25, 0.11, 0.12, // spine, thorax, neck, head
    0.15, 0.28, 0.25, // l_shoulder, l_upper_arm, l_forearm
    0.15, 0.28, 0.25, // r_shoulder, r_upper_arm, r_forearm
];

/// Image width and height of the example camera (pixels).
pub const IMAGE_SIZE: u32 = 1000;
/// Focal length of the example camera (pixels).
pub const FOCAL_PX: f64 = 1150.0;
/// Radial distortion k1, k2, k3 of the example camera (mild barrel).
pub const RADIAL: [f64; 3] = [-0.06, 0.015, 0.0];
/// Tangential distortion p1, p2 of the example camera.
pub const TANGENTIAL: [f64; 2] = [0.0002, -0.0001];
/// Height of the camera centre above the ground (metres).
pub const CAMERA_HEIGHT: f64 = 1.4;
/// Height of the point the camera looks at (metres), about pelvis height.
pub const LOOK_AT_HEIGHT: f64 = 0.95;
/// Angle between the viewing direction and the perpendicular of the clip's
/// direction of travel (degrees): oblique, so walking clips cross less of
/// the image and the camera can stay at a Human3.6M-like distance.
pub const VIEW_OFFSET_DEG: f64 = 50.0;
/// Keypoints stay this far inside the image (pixels).
pub const MARGIN_PX: f64 = 40.0;

/// The CMU clips the shipped examples come from: npz key, example file stem
/// and stature factor of the example person. The factors vary the person
/// between examples (0.96-1.04 times [`PERSON_LENGTHS`]); they are our
/// choice, not measurements.
pub const CLIPS: [(&str, &str, f32); 5] = [
    ("subject02/02_02", "cmu_02_02_walk", 1.00),
    ("subject09/09_01", "cmu_09_01_run", 0.96),
    ("subject13/13_32", "cmu_13_32_jump", 1.04),
    ("subject20/20_06", "cmu_20_06_march", 0.98),
    ("subject21/21_11", "cmu_21_11_highfive", 1.02),
];

/// File stem and stature factor for a clip key (unknown clips: `cmu_<key>`
/// with `/` replaced, stature 1).
pub fn clip_name_and_stature(key: &str) -> (String, f32) {
    CLIPS
        .iter()
        .find(|(k, _, _)| *k == key)
        .map(|(_, name, stature)| (name.to_string(), *stature))
        .unwrap_or_else(|| (format!("cmu_{}", key.replace('/', "_")), 1.0))
}

/// Knobs of the synthesis (defaults are what the shipped examples use).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ExampleConfig {
    /// Base seed; each clip's generator is seeded from it and the clip name.
    pub seed: u64,
    /// Stature factor applied to [`PERSON_LENGTHS`].
    pub stature: f32,
    /// Camera distance from the clip's mean pelvis position (metres), before
    /// moving back to fit the image.
    pub camera_distance: f64,
    /// Standard deviation of the 2D noise (pixels).
    pub noise_px: f32,
    /// Standard deviation of the fixed per-bone relative length bias.
    pub length_bias: f32,
    /// Standard deviation of the per-frame relative length jitter.
    pub length_jitter: f32,
    /// Standard deviation of the per-frame direction tilt (degrees).
    pub direction_noise_deg: f32,
}

impl Default for ExampleConfig {
    fn default() -> Self {
        ExampleConfig {
            seed: 2024,
            stature: 1.0,
            camera_distance: 5.0,
            noise_px: 3.0,
            length_bias: 0.08,
            length_jitter: 0.04,
            direction_noise_deg: 3.0,
        }
    }
}

/// Why an example could not be built.
#[derive(Debug, thiserror::Error)]
pub enum ExampleError {
    /// The clip has no frames.
    #[error("clip {0:?} has no frames")]
    EmptyClip(String),
    /// A clip pose could not be decomposed (zero-length bone, NaN).
    #[error("clip {clip:?}, frame {frame}: {source}")]
    Pose {
        /// The clip.
        clip: String,
        /// The frame.
        frame: usize,
        /// Why.
        #[source]
        source: BoneError,
    },
    /// No camera distance up to 15 m keeps the clip inside the image.
    #[error("clip {0:?} does not fit in the example camera's image")]
    DoesNotFit(String),
    /// The built sequence is invalid (should not happen).
    #[error(transparent)]
    Sequence(#[from] SequenceError),
    /// A distribution parameter is invalid.
    #[error("invalid noise parameter: {0}")]
    Noise(String),
}

/// A generated example: the replay sequence plus what it was made from.
#[derive(Debug, Clone)]
pub struct Example {
    /// The replay sequence (`keypoints_2d`, `pose_3d`, `gt_3d`, ...).
    pub sequence: Sequence,
    /// The example camera.
    pub camera: Camera,
    /// The ground-truth bone lengths.
    pub gt_lengths: BoneLengths,
}

impl Example {
    /// The replay arrays (the calibration `camera_up`, `camera_focal`,
    /// `camera_principal` and `camera_height` among them) plus, for transparency, the rest of
    /// the camera and the true lengths (extra keys are ignored by replay
    /// readers): `camera_R` (3,3), `camera_center` (3,), `camera_k` (3,),
    /// `camera_p` (2,), `gt_bone_lengths` (16,).
    pub fn to_npz(&self) -> Result<Npz, ExampleError> {
        self.sequence.validate()?;
        let mut npz = self.sequence.to_npz()?;
        let c = &self.camera;
        let arr = |shape: Vec<usize>, v: Vec<f32>| {
            Array::new(shape, v).map_err(|e| {
                ExampleError::Sequence(SequenceError::Npz {
                    path: "<example>".into(),
                    error: e,
                })
            })
        };
        let f = |v: &[f64]| v.iter().map(|&x| x as f32).collect::<Vec<_>>();
        npz.insert("camera_R", arr(vec![3, 3], f(c.rotation.as_flattened()))?);
        npz.insert("camera_center", arr(vec![3], f(&c.center))?);
        npz.insert("camera_k", arr(vec![3], f(&c.radial))?);
        npz.insert("camera_p", arr(vec![2], f(&c.tangential))?);
        npz.insert(
            "gt_bone_lengths",
            arr(vec![NUM_BONES], self.gt_lengths.to_vec())?,
        );
        Ok(npz)
    }
}

/// A seed for one clip: the base seed mixed with the clip name (FNV-1a), so
/// a clip's example does not change when other clips are added.
pub fn clip_seed(seed: u64, clip: &str) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325 ^ seed;
    for b in clip.bytes() {
        h ^= u64::from(b);
        h = h.wrapping_mul(0x0100_0000_01b3);
    }
    h
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

fn normalized(v: [f64; 3]) -> [f64; 3] {
    let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    if n > 0.0 {
        v.map(|x| x / n)
    } else {
        v
    }
}

/// A camera at `center` looking at `target` with world +Z up: rows of `R`
/// are the camera's x (right), y (down) and z (forward) axes in world
/// coordinates.
pub fn look_at(id: &str, center: [f64; 3], target: [f64; 3]) -> Camera {
    let forward = normalized(sub(target, center));
    let right = normalized(cross(forward, [0.0, 0.0, 1.0]));
    let down = cross(forward, right);
    let c = f64::from(IMAGE_SIZE) / 2.0;
    Camera {
        id: id.to_string(),
        rotation: [right, down, forward],
        center,
        focal: [FOCAL_PX, FOCAL_PX],
        principal: [c, c],
        radial: RADIAL,
        tangential: TANGENTIAL,
        width: IMAGE_SIZE,
        height: IMAGE_SIZE,
    }
}

fn fits(camera: &Camera, poses: &[Pose]) -> bool {
    let max = f64::from(IMAGE_SIZE) - MARGIN_PX;
    poses.iter().flatten().all(|p| {
        let c = camera.world_to_camera(p.map(f64::from));
        if c[2] < 1.0 {
            return false;
        }
        let px = camera.project_camera_to_pixels(c);
        px.iter()
            .all(|&v| v.is_finite() && (MARGIN_PX..=max).contains(&v))
    })
}

/// The example camera for a clip (see the module docs): looks at the mean
/// pelvis position from `distance` metres, [`VIEW_OFFSET_DEG`] off the perpendicular
/// of the main horizontal direction of travel, backing off in 0.25 m steps
/// until every joint fits.
pub fn camera_for_clip(clip: &str, world: &[Pose], distance: f64) -> Result<Camera, ExampleError> {
    if world.is_empty() {
        return Err(ExampleError::EmptyClip(clip.to_string()));
    }
    let n = world.len() as f64;
    let mean = |k: usize| world.iter().map(|p| f64::from(p[0][k])).sum::<f64>() / n;
    let (mx, my) = (mean(0), mean(1));
    // Main direction of horizontal pelvis motion (2x2 PCA); a clip that
    // stays in place gets the x axis.
    let (mut sxx, mut sxy, mut syy) = (0.0, 0.0, 0.0);
    for p in world {
        let (dx, dy) = (f64::from(p[0][0]) - mx, f64::from(p[0][1]) - my);
        sxx += dx * dx;
        sxy += dx * dy;
        syy += dy * dy;
    }
    let travel = 0.5 * (2.0 * sxy).atan2(sxx - syy);
    let view = travel + std::f64::consts::FRAC_PI_2 + VIEW_OFFSET_DEG.to_radians();
    let target = [mx, my, LOOK_AT_HEIGHT];
    let mut d = distance;
    while d <= 15.0 {
        let center = [mx - d * view.cos(), my - d * view.sin(), CAMERA_HEIGHT];
        let camera = look_at(&format!("example-{clip}"), center, target);
        if fits(&camera, world) {
            return Ok(camera);
        }
        d += 0.25;
    }
    Err(ExampleError::DoesNotFit(clip.to_string()))
}

/// Tilt unit vector `d` by `angle` radians towards a random perpendicular.
fn tilt(d: [f32; 3], angle: f32, rng: &mut StdRng) -> [f32; 3] {
    let d64 = d.map(f64::from);
    loop {
        let r: [f64; 3] = std::array::from_fn(|_| rng.random::<f64>() * 2.0 - 1.0);
        let dot = r[0] * d64[0] + r[1] * d64[1] + r[2] * d64[2];
        let perp = sub(r, d64.map(|x| x * dot));
        let n = (perp[0] * perp[0] + perp[1] * perp[1] + perp[2] * perp[2]).sqrt();
        if n > 1e-3 {
            let (s, c) = f64::from(angle).sin_cos();
            return std::array::from_fn(|k| (c * d64[k] + s * perp[k] / n) as f32);
        }
    }
}

fn normal(std: f32) -> Result<Normal<f32>, ExampleError> {
    Normal::new(0.0, std).map_err(|e| ExampleError::Noise(format!("std {std}: {e}")))
}

/// Build one example from a CMU clip in world coordinates (metres, +Z up).
pub fn make_example(
    clip: &str,
    world: &[Pose],
    config: &ExampleConfig,
) -> Result<Example, ExampleError> {
    if world.is_empty() {
        return Err(ExampleError::EmptyClip(clip.to_string()));
    }
    let mut rng = StdRng::seed_from_u64(clip_seed(config.seed, clip));
    let gt_lengths: BoneLengths = PERSON_LENGTHS.map(|l| l * config.stature);

    // 1. CMU directions, our person's lengths, CMU root trajectory.
    let gt_world = world
        .iter()
        .enumerate()
        .map(|(frame, p)| {
            let (_, dirs) = decompose(p).map_err(|source| ExampleError::Pose {
                clip: clip.to_string(),
                frame,
                source,
            })?;
            Ok(rebuild(p[0], &dirs, &gt_lengths))
        })
        .collect::<Result<Vec<Pose>, ExampleError>>()?;

    // 2. Camera, 3. noisy 2D keypoints.
    let camera = camera_for_clip(clip, &gt_world, config.camera_distance)?;
    let noise = normal(config.noise_px)?;
    let extremities = [3usize, 6, 13, 16]; // ankles and wrists
    let mut keypoints = Vec::with_capacity(gt_world.len() * NUM_JOINTS * 2);
    for pose in &gt_world {
        let px = camera.project_world_pose_to_pixels(pose);
        for (j, p) in px.iter().enumerate() {
            let scale = if extremities.contains(&j) { 1.5 } else { 1.0 };
            keypoints.push(p[0] + scale * noise.sample(&mut rng));
            keypoints.push(p[1] + scale * noise.sample(&mut rng));
        }
    }

    // 4. Ground truth and the "lifted" pose in camera space, root-relative.
    let gt_cam: Vec<Pose> = gt_world
        .iter()
        .map(|p| root_relative(&camera.world_to_camera_pose(p)))
        .collect();
    let bias_dist = normal(config.length_bias)?;
    let jitter_dist = normal(config.length_jitter)?;
    let tilt_dist = normal(config.direction_noise_deg.to_radians())?;
    let bias: [f32; NUM_BONES] = std::array::from_fn(|_| bias_dist.sample(&mut rng));
    let lifted = gt_cam
        .iter()
        .enumerate()
        .map(|(frame, p)| {
            let (_, dirs) = decompose(p).map_err(|source| ExampleError::Pose {
                clip: clip.to_string(),
                frame,
                source,
            })?;
            let dirs = dirs.map(|d| tilt(d, tilt_dist.sample(&mut rng), &mut rng));
            let lengths: BoneLengths = std::array::from_fn(|b| {
                let factor = 1.0 + bias[b] + jitter_dist.sample(&mut rng);
                gt_lengths[b] * factor.max(0.5)
            });
            Ok(rebuild([0.0; 3], &dirs, &lengths))
        })
        .collect::<Result<Vec<Pose>, ExampleError>>()?;

    let sequence = Sequence {
        input_format: InputFormat::pixels(KeypointLayout::H36m17, IMAGE_SIZE, IMAGE_SIZE),
        keypoints_2d: keypoints,
        confidence: Vec::new(),
        pose_3d: lifted,
        gt_3d: Some(gt_cam),
        fps: Some(50.0),
        camera: Some(CameraCalibration::from_camera(&camera)),
        subject: None,
    };
    sequence.validate()?;
    Ok(Example {
        sequence,
        camera,
        gt_lengths,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use blapose_core::bones::bone_lengths;
    use blapose_core::metrics::mpjpe;

    /// A standing figure walking along +x, +Z up, pelvis ~0.95 m high.
    fn walk(frames: usize) -> Vec<Pose> {
        (0..frames)
            .map(|t| {
                let x = 0.02 * t as f32;
                let s = (0.2 * t as f32).sin() * 0.1;
                let mut p: Pose = [
                    [0.0, 0.0, 0.95],
                    [0.0, -0.1, 0.9],
                    [s, -0.1, 0.5],
                    [s, -0.1, 0.1],
                    [0.0, 0.1, 0.9],
                    [-s, 0.1, 0.5],
                    [-s, 0.1, 0.1],
                    [0.0, 0.0, 1.15],
                    [0.0, 0.0, 1.4],
                    [0.02, 0.0, 1.5],
                    [0.0, 0.0, 1.65],
                    [0.0, 0.17, 1.4],
                    [-s, 0.2, 1.12],
                    [-s, 0.2, 0.88],
                    [0.0, -0.17, 1.4],
                    [s, -0.2, 1.12],
                    [s, -0.2, 0.88],
                ];
                for j in p.iter_mut() {
                    j[0] += x;
                }
                p
            })
            .collect()
    }

    #[test]
    fn look_at_camera_is_a_rotation_and_sees_the_target_centred() {
        let cam = look_at("t", [0.0, -5.0, 1.4], [0.0, 0.0, 1.4]);
        cam.validate().unwrap();
        let px = cam.project_world_to_pixels([0.0, 0.0, 1.4]);
        assert!(
            (px[0] - 500.0).abs() < 1e-9 && (px[1] - 500.0).abs() < 1e-9,
            "{px:?}"
        );
        // Up in the world is up in the image (smaller v); +x is to the right.
        assert!(cam.project_world_to_pixels([0.0, 0.0, 2.0])[1] < 500.0);
        assert!(cam.project_world_to_pixels([0.5, 0.0, 1.4])[0] > 500.0);
    }

    #[test]
    fn example_has_true_lengths_noisy_lift_and_fits_the_image() {
        let world = walk(60);
        let ex = make_example("test/walk", &world, &ExampleConfig::default()).unwrap();
        let seq = &ex.sequence;
        assert_eq!(seq.len(), 60);
        let gt = seq.gt_3d.as_ref().unwrap();
        for p in gt {
            let l = bone_lengths(p);
            for b in 0..NUM_BONES {
                assert!(
                    (l[b] - PERSON_LENGTHS[b]).abs() < 1e-5,
                    "bone {b}: {}",
                    l[b]
                );
            }
            assert_eq!(p[0], [0.0; 3]);
        }
        // The lifted pose is wrong, but plausibly so.
        let err = mpjpe(&seq.pose_3d, gt).unwrap();
        assert!(err > 0.01 && err < 0.1, "lifted MPJPE {err} m");
        assert!(seq.keypoints_2d.iter().all(|&v| (0.0..1000.0).contains(&v)));
        // Keypoints are the projection of the ground truth plus a few px of noise.
        let clean = ex.camera.project_world_pose_to_pixels(&rebuild(
            world[10][0],
            &decompose(&world[10]).unwrap().1,
            &ex.gt_lengths,
        ));
        let kp = seq.frame(10).keypoints_2d;
        let mean_err: f32 = kp
            .iter()
            .zip(clean.iter())
            .map(|(a, b)| ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2)).sqrt())
            .sum::<f32>()
            / 17.0;
        assert!(
            mean_err > 1.0 && mean_err < 12.0,
            "mean 2D noise {mean_err} px"
        );
    }

    /// `R`'s third column, the direction of world +Z in camera coordinates.
    fn third_column(r: &[[f64; 3]; 3]) -> [f64; 3] {
        [r[0][2], r[1][2], r[2][2]]
    }

    #[test]
    fn example_carries_its_cameras_calibration() {
        let world = walk(30);
        let ex = make_example("test/walk", &world, &ExampleConfig::default()).unwrap();
        let cal = ex.sequence.camera.expect("an example has a calibration");
        let up = third_column(&ex.camera.rotation);
        // The same as moving a world point straight up, seen by the camera.
        let a = ex.camera.world_to_camera([0.1, 0.2, 1.0]);
        let b = ex.camera.world_to_camera([0.1, 0.2, 2.0]);
        for k in 0..3 {
            assert!((f64::from(cal.up[k]) - up[k]).abs() < 1e-6, "{cal:?}");
            assert!((up[k] - (b[k] - a[k])).abs() < 1e-9);
        }
        assert!(cal.up[1] < -0.9, "a near-level camera: up is mostly -y");
        assert_eq!(cal.focal, [FOCAL_PX as f32; 2]);
        assert_eq!(cal.principal, [IMAGE_SIZE as f32 / 2.0; 2]);
        assert_eq!(cal.image_size, Some((IMAGE_SIZE, IMAGE_SIZE)));
        assert_eq!(cal.height, Some(ex.camera.center[2] as f32));
        assert_eq!(cal.height, Some(CAMERA_HEIGHT as f32));
        // Written with the replay keys, and read back as the same camera.
        let arrays = ex.to_npz().unwrap();
        let back = Sequence::from_npz(&arrays, None).unwrap();
        assert_eq!(back.camera, Some(cal));
        assert_eq!(back, ex.sequence);
    }

    /// The committed examples carry a calibration whose `up` is the third
    /// column of the example camera's rotation (`camera_R`, row-major) and
    /// whose `camera_height` is the camera centre's z (`camera_center`).
    #[test]
    fn committed_examples_carry_their_cameras_calibration() {
        let examples = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../examples");
        for (_, stem, _) in CLIPS {
            let path = examples.join(format!("{stem}.npz"));
            let arrays = blapose_data::read_npz(&path).unwrap();
            let r = arrays.get_shaped("camera_R", &[Some(3), Some(3)]).unwrap();
            let r = r.data();
            let seq = Sequence::load(&path, None).unwrap();
            let cal = seq
                .camera
                .unwrap_or_else(|| panic!("{stem} has no calibration"));
            assert_eq!(cal.up, [r[2], r[5], r[8]], "{stem}");
            assert_ne!(cal.up, [r[6], r[7], r[8]], "{stem}: a row, not the column");
            assert_eq!(cal.focal, [FOCAL_PX as f32; 2], "{stem}");
            assert_eq!(cal.principal, [IMAGE_SIZE as f32 / 2.0; 2], "{stem}");
            assert_eq!(cal.image_size, Some((IMAGE_SIZE, IMAGE_SIZE)), "{stem}");
            // The height is the camera centre's z (floor at z = 0).
            let center = arrays.get_shaped("camera_center", &[Some(3)]).unwrap();
            let height = arrays.scalar("camera_height").unwrap();
            assert_eq!(height, center.data()[2], "{stem}");
            assert_eq!(cal.height, Some(center.data()[2]), "{stem}");
            assert_eq!(cal.height, Some(CAMERA_HEIGHT as f32), "{stem}");
            let norm = cal.up.iter().map(|v| v * v).sum::<f32>().sqrt();
            assert!((norm - 1.0).abs() < 1e-5, "{stem}: |up| = {norm}");
        }
    }

    #[test]
    fn generation_is_deterministic_per_clip() {
        let world = walk(20);
        let c = ExampleConfig::default();
        let a = make_example("x/a", &world, &c).unwrap().sequence;
        let b = make_example("x/a", &world, &c).unwrap().sequence;
        let other = make_example("x/b", &world, &c).unwrap().sequence;
        assert_eq!(a, b);
        assert_ne!(a.keypoints_2d, other.keypoints_2d);
        let arrays = make_example("x/a", &world, &c).unwrap().to_npz().unwrap();
        for key in [
            "keypoints_2d",
            "pose_3d",
            "gt_3d",
            "image_size",
            "layout",
            "camera_R",
            "camera_up",
            "camera_focal",
            "camera_principal",
            "camera_height",
            "gt_bone_lengths",
        ] {
            assert!(arrays.contains(key), "{key}");
        }
    }

    /// The committed examples are what `make-example` builds from the CMU
    /// data (skips when the data is absent).
    #[test]
    fn committed_examples_match_the_generator() {
        let Some(root) =
            blapose_data::test_data_root("cmu/cmu_h36m17.npz", "example regeneration check")
        else {
            return;
        };
        let cmu = blapose_data::read_npz(root.join("cmu/cmu_h36m17.npz")).unwrap();
        let examples = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../examples");
        for (key, stem, _) in CLIPS {
            let (name, stature) = clip_name_and_stature(key);
            assert_eq!(name, stem);
            let config = ExampleConfig {
                stature,
                ..ExampleConfig::default()
            };
            let built = make_example(key, &cmu.poses(key).unwrap(), &config)
                .unwrap()
                .to_npz()
                .unwrap();
            let committed = blapose_data::read_npz(examples.join(format!("{stem}.npz"))).unwrap();
            assert_eq!(
                built.keys().collect::<Vec<_>>(),
                committed.keys().collect::<Vec<_>>(),
                "{stem}"
            );
            for (k, a) in built.iter() {
                let b = committed.get(k).unwrap();
                assert_eq!(a.shape(), b.shape(), "{stem}/{k}");
                let diff = a
                    .data()
                    .iter()
                    .zip(b.data())
                    .map(|(x, y)| (x - y).abs())
                    .fold(0.0f32, f32::max);
                assert!(
                    diff < 1e-3,
                    "{stem}/{k} differs by {diff}: regenerate with make-example"
                );
            }
        }
    }

    #[test]
    fn degenerate_clips_are_errors() {
        assert!(matches!(
            make_example("e", &[], &ExampleConfig::default()),
            Err(ExampleError::EmptyClip(_))
        ));
        let mut world = walk(3);
        world[1][2] = world[1][1];
        let e = make_example("z", &world, &ExampleConfig::default()).unwrap_err();
        assert!(matches!(e, ExampleError::Pose { frame: 1, .. }), "{e}");
    }
}

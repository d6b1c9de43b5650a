//! Motion metrics for `blapose eval-adjust`: how a method's poses move, not
//! only where each one is.
//!
//! Per trial (sequence x camera) a [`Scene`] holds what the ground truth
//! says about place and contact: the pelvis in camera space, each frame's
//! viewing rays (the detections undistorted through the trial's camera),
//! world up in camera space, and when each foot is planted (detected on
//! the ground truth, [`blapose_core::motion::feet`]). A method's poses are
//! then scored ([`score`]) by
//!
//! * `accel_error_mm`: mean |acceleration difference| (mm/frame²,
//!   root-relative, [`blapose_core::metrics::accel_error`]);
//! * `mrpe_mm`: mean root position error of the roots the method placed
//!   ([`place_roots`]: solved from the rays for the method's own poses, so
//!   its lengths set the depth);
//! * `foot_skate_mm`: mean horizontal slide of an ankle between two
//!   frames in which the ground truth has it planted, with the method's
//!   poses at the method's roots (mm per contact frame).

use blapose_core::camera::{denormalize_screen, Camera};
use blapose_core::metrics::{accel_error, mrpe, MM_PER_M};
use blapose_core::motion::feet::{detect_contacts, foot_skate, ContactParams};
use blapose_core::motion::root::{solve_root, Rays, ROOT_JOINT_WEIGHTS};
use blapose_core::motion::{place, CausalMotion, CausalMotionConfig, Viewing};
use blapose_core::skeleton::{NUM_JOINTS, ROOT};
use blapose_core::Pose;
use blapose_data::h36m::H36m;

use crate::error::TrainError;
use crate::lifter::data::LifterSequence;
use crate::synth::FRAME_DIM;

/// Frame rate of the Human3.6M recordings.
pub const H36M_RATE_HZ: f64 = 50.0;

/// What the ground truth says about one trial's place and contacts.
#[derive(Debug, Clone)]
pub struct Scene {
    /// Pelvis in camera space per frame (metres).
    pub root: Vec<[f64; 3]>,
    /// Viewing rays and joint weights per frame (the served
    /// [`ROOT_JOINT_WEIGHTS`]).
    pub rays: Vec<(Rays, [f64; NUM_JOINTS])>,
    /// World up in camera coordinates (unit).
    pub up: [f64; 3],
    /// Ground-truth contacts per foot and frame.
    pub contacts: [Vec<bool>; 2],
}

/// Viewing rays of normalized-screen keypoints through `cam` (its lens
/// undone).
pub fn rays_from_normalized(kp: &[f32], cam: &Camera) -> Rays {
    let k = cam.pixel_intrinsics();
    std::array::from_fn(|j| {
        let px = denormalize_screen([kp[2 * j], kp[2 * j + 1]], cam.width, cam.height);
        let u = k.undistort([px[0] as f64, px[1] as f64]);
        [
            (u[0] - k.principal[0]) / k.focal[0],
            (u[1] - k.principal[1]) / k.focal[1],
        ]
    })
}

impl Scene {
    /// The scene of `seq` (its world poses and camera from `h36m`).
    pub fn build(h36m: &H36m, seq: &LifterSequence) -> Result<Self, TrainError> {
        let t = &seq.trial;
        let missing = |what: &str| {
            TrainError::Data(format!(
                "no {what} for {}/{}/{}",
                t.subject, t.sequence, t.camera
            ))
        };
        let world = h36m
            .sequence(&t.subject, &t.sequence)
            .ok_or_else(|| missing("poses"))?;
        let cam = h36m
            .cameras
            .get(&t.subject, &t.camera)
            .ok_or_else(|| missing("camera"))?;
        let n = seq.frames();
        let placed: Vec<Pose> = world[..n]
            .iter()
            .map(|p| cam.world_to_camera_pose(p))
            .collect();
        let root = placed.iter().map(|p| p[ROOT].map(f64::from)).collect();
        let rays = t
            .input
            .chunks_exact(FRAME_DIM)
            .take(n)
            .map(|kp| (rays_from_normalized(kp, cam), ROOT_JOINT_WEIGHTS))
            .collect();
        // World z is up; its camera-space direction is R's third column.
        let up = std::array::from_fn(|i| cam.rotation[i][2]);
        let contacts = detect_contacts(&placed, up, H36M_RATE_HZ, ContactParams::default());
        Ok(Self {
            root,
            rays,
            up,
            contacts,
        })
    }

    /// The geometry the offline stage places with.
    pub fn viewing(&self) -> Viewing<'_> {
        Viewing {
            rays: &self.rays,
            up: Some(self.up),
        }
    }
}

/// Roots solved frame by frame for `poses` (no smoothing); a frame that
/// cannot be solved repeats the last solved root (the origin before any).
pub fn place_roots(poses: &[Pose], scene: &Scene) -> Vec<[f64; 3]> {
    let mut last = [0.0; 3];
    poses
        .iter()
        .zip(&scene.rays)
        .map(|(p, (r, w))| {
            if let Some(v) = solve_root(r, p, w) {
                last = v;
            }
            last
        })
        .collect()
}

/// Stream `adjusted` (root-relative, `lengths[t]` applied) through the
/// served causal motion stage, as a session with this camera would:
/// smoothed poses and placed roots.
pub fn stream_causal(
    adjusted: &[Pose],
    lengths: &[blapose_core::BoneLengths],
    config: CausalMotionConfig,
    scene: &Scene,
) -> Result<(Vec<Pose>, Vec<[f64; 3]>), TrainError> {
    let mut stage = CausalMotion::new(config);
    let mut poses = Vec::with_capacity(adjusted.len());
    let mut roots = Vec::with_capacity(adjusted.len());
    let mut last = [0.0; 3];
    for ((p, l), (r, w)) in adjusted.iter().zip(lengths).zip(&scene.rays) {
        let out = stage
            .step(p, l, Some((r, w)))
            .map_err(|e| TrainError::Data(format!("motion stage: {e}")))?;
        if let Some(root) = out.root {
            last = root;
        }
        poses.push(out.pose);
        roots.push(last);
    }
    Ok((poses, roots))
}

/// One method's motion metrics on one trial.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MotionScore {
    /// Mean |acceleration difference| (mm/frame²); `None` under 3 frames.
    pub accel_error_mm: Option<f64>,
    /// Mean root position error (mm).
    pub mrpe_mm: f64,
    /// Mean slide per ground-truth contact frame (mm) and how many such
    /// frames; `None` without any.
    pub foot_skate: Option<(f64, usize)>,
}

/// Score `pred` (root-relative) placed at `roots` against the truth.
pub fn score(
    pred: &[Pose],
    roots: &[[f64; 3]],
    gt: &[Pose],
    scene: &Scene,
) -> Result<MotionScore, TrainError> {
    let metric = |e: blapose_core::metrics::MetricError| TrainError::Data(e.to_string());
    let accel_error_mm = if pred.len() >= 3 {
        Some(accel_error(pred, gt).map_err(metric)? * MM_PER_M)
    } else {
        None
    };
    let mrpe_mm = mrpe(roots, &scene.root).map_err(metric)? * MM_PER_M;
    let placed = place(pred, roots);
    let foot_skate = foot_skate(&placed, &scene.contacts, scene.up).map(|(m, n)| (m * MM_PER_M, n));
    Ok(MotionScore {
        accel_error_mm,
        mrpe_mm,
        foot_skate,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rays_of_a_projected_point_point_at_it() {
        let cam = Camera {
            id: "c".into(),
            rotation: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            center: [0.0; 3],
            focal: [1145.0, 1144.0],
            principal: [512.0, 515.0],
            radial: [-0.2, 0.24, -0.002],
            tangential: [-0.0007, -0.0014],
            width: 1000,
            height: 1002,
        };
        let p = [0.4, -0.3, 4.0];
        let n = cam.normalized_intrinsics().project(p.map(|v| v as f32));
        let kp: Vec<f32> = (0..NUM_JOINTS).flat_map(|_| n).collect();
        let r = rays_from_normalized(&kp, &cam)[0];
        assert!(
            (r[0] - 0.1).abs() < 1e-5 && (r[1] + 0.075).abs() < 1e-5,
            "{r:?}"
        );
    }
}

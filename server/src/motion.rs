//! The motion stage: after the lengths are applied, the poses' bone
//! directions smoothed (lengths untouched), the pelvis placed in camera
//! space from the keypoints, and planted feet held (offline). The filters
//! and their chosen settings are `blapose_core::motion`'s, the same code
//! `blapose eval-adjust` scores; this module only turns a request's
//! keypoints and calibration into the viewing rays that code reads, and
//! its output into answer fields.
//!
//! The rays come from the keypoints as validated (normalized screen
//! coordinates, before the model's rectification), through the
//! calibration's intrinsics with its lens undone. Without a
//! calibration the focal length is assumed
//! ([`blapose_core::motion::root::ASSUMED_FOCAL_PER_SIDE`] of the image's
//! larger side, the principal point at the centre) and the answer says so.
//! A joint the client marked missing gets no weight in the root solve.

use blapose_core::bones::BoneError;
use blapose_core::layouts::{Coordinates, InputFormat};
use blapose_core::motion::root::{FloorFrame, Rays, ASSUMED_FOCAL_PER_SIDE, ROOT_JOINT_WEIGHTS};
use blapose_core::motion::{
    offline_motion, place, place_pose, served_causal, served_offline, CausalMotion, Viewing,
    DEFAULT_RATE_HZ,
};
use blapose_core::{BoneLengths, Pose, NUM_JOINTS};
use blapose_model::input::ViewCalibration;
use blapose_proto::v1 as pb;
use tonic::Status;

/// Highest frame rate a motion option may state.
pub const MAX_FRAME_RATE_HZ: f32 = 1000.0;

/// A request's checked motion option: its frame rate, `None` when off; a
/// rate that is not a number in (0, [`MAX_FRAME_RATE_HZ`]] is
/// INVALID_ARGUMENT.
pub fn options(motion: Option<&pb::MotionOptions>) -> Result<Option<f64>, Status> {
    match motion.filter(|m| m.enabled) {
        Some(m) => frame_rate(m.frame_rate_hz).map(Some),
        None => Ok(None),
    }
}

/// A stated frame rate as served: 0 is [`DEFAULT_RATE_HZ`]; anything but a
/// number in (0, [`MAX_FRAME_RATE_HZ`]] is INVALID_ARGUMENT.
pub fn frame_rate(rate: f32) -> Result<f64, Status> {
    if rate == 0.0 {
        return Ok(DEFAULT_RATE_HZ);
    }
    if !(rate.is_finite() && rate > 0.0 && rate <= MAX_FRAME_RATE_HZ) {
        return Err(Status::invalid_argument(format!(
            "motion.frame_rate_hz must be 0 (50 Hz) or in (0, {MAX_FRAME_RATE_HZ}] frames per second, got {rate}"
        )));
    }
    Ok(rate as f64)
}

/// How a request's keypoints become viewing rays.
#[derive(Debug, Clone, Copy)]
pub struct RayCamera {
    /// Focal length and principal point in normalized screen units.
    focal: [f64; 2],
    principal: [f64; 2],
    /// The lens undone (focal-length units).
    lens: Option<blapose_core::lens::LensDistortion>,
    /// Whether the focal length was assumed.
    pub assumed: bool,
}

impl RayCamera {
    /// The camera of a request whose keypoints were read in `spec` (and
    /// validated into normalized screen coordinates), from its calibration
    /// when it sent one.
    pub fn new(spec: &InputFormat, view: Option<&ViewCalibration>) -> Self {
        // u = x / w * 2 - 1, v = y / w * 2 - h / w: the image centre is 0.
        match (view, spec.coordinates) {
            (Some(v), _) => {
                let (w, h) = (v.image_size.0 as f64, v.image_size.1 as f64);
                Self {
                    focal: v.focal.map(|f| f / w * 2.0),
                    principal: [
                        v.principal[0] / w * 2.0 - 1.0,
                        v.principal[1] / w * 2.0 - h / w,
                    ],
                    lens: v.lens,
                    assumed: false,
                }
            }
            (None, Coordinates::Pixels { width, height }) => {
                let f = 2.0 * ASSUMED_FOCAL_PER_SIDE * width.max(height) as f64 / width as f64;
                Self {
                    focal: [f, f],
                    principal: [0.0, 0.0],
                    lens: None,
                    assumed: true,
                }
            }
            (None, Coordinates::Normalized) => Self {
                focal: [2.0 * ASSUMED_FOCAL_PER_SIDE; 2],
                principal: [0.0, 0.0],
                lens: None,
                assumed: true,
            },
        }
    }

    /// The rays of one frame of H36M-17 keypoints (`2 * NUM_JOINTS`
    /// normalized screen coordinates), weight 0 for missing joints.
    pub fn rays(&self, keypoints: &[f32], present: &[bool]) -> (Rays, [f64; NUM_JOINTS]) {
        let rays = std::array::from_fn(|j| {
            let ideal = [
                (keypoints[2 * j] as f64 - self.principal[0]) / self.focal[0],
                (keypoints[2 * j + 1] as f64 - self.principal[1]) / self.focal[1],
            ];
            match &self.lens {
                Some(lens) => lens.undistort(ideal),
                None => ideal,
            }
        });
        let weights = std::array::from_fn(|j| {
            if present[j] {
                ROOT_JOINT_WEIGHTS[j]
            } else {
                0.0
            }
        });
        (rays, weights)
    }
}

/// A session's motion stage settings, fixed at open: its frame rate, how
/// its keypoints become rays, and its floor when the calibration has a
/// camera height.
#[derive(Debug, Clone, Copy)]
pub struct SessionMotion {
    /// Frames per second.
    pub rate_hz: f64,
    rays: RayCamera,
    floor: Option<FloorFrame>,
}

impl SessionMotion {
    /// The settings of a session in `spec` with this calibration.
    pub fn new(rate_hz: f64, spec: &InputFormat, view: Option<&ViewCalibration>) -> Self {
        Self {
            rate_hz,
            rays: RayCamera::new(spec, view),
            floor: floor(view),
        }
    }

    /// A fresh causal stage (the served filters at this rate).
    pub fn stage(&self) -> CausalMotion {
        CausalMotion::new(served_causal(self.rate_hz))
    }

    /// As the session answers it in `SessionOpened.motion`.
    pub fn to_proto(&self) -> pb::MotionOptions {
        pb::MotionOptions {
            enabled: true,
            frame_rate_hz: self.rate_hz as f32,
        }
    }

    /// One streamed frame through the session's `stage`: `adjusted`
    /// (lengths applied) smoothed, its root placed from the frame's
    /// validated keypoints (`input`, normalized, missing joints' pairs
    /// ignored through `present`). Errors leave the stage as it was.
    pub fn frame(
        &self,
        stage: &mut CausalMotion,
        adjusted: &Pose,
        lengths: &BoneLengths,
        input: &[f32],
        present: &[bool],
    ) -> Result<FrameMotion, BoneError> {
        let (rays, weights) = self.rays.rays(input, present);
        let placed = stage.step(adjusted, lengths, Some((&rays, &weights)))?;
        let world = match (placed.root, self.floor) {
            (Some(root), Some(floor)) => {
                let p = place_pose(&placed.pose, &root);
                Some(p.map(|j| floor.to_world(j.map(f64::from)).map(|v| v as f32)))
            }
            _ => None,
        };
        Ok(FrameMotion {
            pose: placed.pose,
            root: placed.root,
            world,
            focal_assumed: self.rays.assumed,
        })
    }
}

/// What the causal stage made of one streamed frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FrameMotion {
    /// The smoothed pose (root-relative as it came).
    pub pose: Pose,
    /// The pelvis in camera space, when it could be placed.
    pub root: Option<[f64; 3]>,
    /// The placed pose in world coordinates (calibrations with a camera
    /// height).
    pub world: Option<Pose>,
    /// Whether the focal length was assumed.
    pub focal_assumed: bool,
}

/// The floor frame of a calibration with a camera height.
fn floor(view: Option<&ViewCalibration>) -> Option<FloorFrame> {
    let v = view?;
    FloorFrame::new(v.up, v.camera_height? as f64).ok()
}

/// What the motion stage adds to a whole sequence's answer.
#[derive(Debug, Clone, PartialEq)]
pub struct SequenceMotion {
    /// The poses after the stage (root-relative as they came).
    pub poses: Vec<Pose>,
    /// Pelvis in camera space per frame; `None` when no frame could be
    /// placed.
    pub roots: Option<Vec<[f64; 3]>>,
    /// Each frame's pose in world coordinates (calibrations with a camera
    /// height).
    pub world: Option<Vec<Pose>>,
    /// Whether the focal length was assumed.
    pub focal_assumed: bool,
}

/// The offline stage on a whole adjusted sequence: `keypoints` and
/// `present` as validated (`frames x 2 * NUM_JOINTS` normalized screen
/// coordinates, `frames x NUM_JOINTS`).
pub fn sequence(
    poses: &[Pose],
    lengths: &[BoneLengths],
    rate_hz: f64,
    spec: &InputFormat,
    view: Option<&ViewCalibration>,
    keypoints: &[f32],
    present: &[bool],
) -> Result<SequenceMotion, Status> {
    let camera = RayCamera::new(spec, view);
    let rays: Vec<_> = keypoints
        .chunks_exact(2 * NUM_JOINTS)
        .zip(present.chunks_exact(NUM_JOINTS))
        .map(|(k, p)| camera.rays(k, p))
        .collect();
    let floor = floor(view);
    // Without a calibration "up" is taken as the image's up (a level
    // camera): only the feet read it.
    let up = view
        .and_then(|v| FloorFrame::new(v.up, 0.0).ok())
        .map_or([0.0, -1.0, 0.0], |f| f.up());
    let viewing = Viewing {
        rays: &rays,
        up: Some(up),
    };
    let (poses, roots) = offline_motion(poses, lengths, &served_offline(rate_hz), Some(viewing))
        .map_err(|e| Status::internal(format!("motion stage failed: {e}")))?;
    let world = match (&roots, floor) {
        (Some(r), Some(f)) => Some(
            place(&poses, r)
                .iter()
                .map(|p| p.map(|j| f.to_world(j.map(f64::from)).map(|v| v as f32)))
                .collect(),
        ),
        _ => None,
    };
    Ok(SequenceMotion {
        poses,
        roots,
        world,
        focal_assumed: camera.assumed,
    })
}

/// The stage's fields of an `AdjustSequenceResponse`.
pub fn fill_response(resp: &mut pb::AdjustSequenceResponse, m: &SequenceMotion) {
    resp.adjusted_poses_3d = m.poses.iter().flatten().flatten().copied().collect();
    resp.root_positions = m
        .roots
        .iter()
        .flatten()
        .flatten()
        .map(|&v| v as f32)
        .collect();
    resp.focal_assumed = m.focal_assumed;
    resp.world_poses_3d = m
        .world
        .iter()
        .flatten()
        .flatten()
        .flatten()
        .copied()
        .collect();
}

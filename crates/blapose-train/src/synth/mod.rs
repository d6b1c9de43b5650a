//! The augmentation pipeline: synthetic 2D sequences with known bone
//! lengths, built from real Human3.6M motion.
//!
//! One sample (the paper's trick, plus a playback-rate augmentation):
//!
//! 1. pick a training sequence (probability proportional to its length);
//! 2. pick a playback stride `r ~ U(stride_min, stride_max)` source frames
//!    per output frame (Human3.6M is 50 Hz; `r in [50/60, 2]` covers 25-60
//!    fps streams) and a random window of `T` output frames; frames between
//!    mocap samples are linearly interpolated (root position and bone
//!    directions, re-normalized);
//! 3. draw bone lengths ([`crate::lengths::LengthSampler`]) and rebuild every
//!    frame with the sequence's directions, the drawn lengths and the
//!    original root trajectory — lifted or lowered per frame, with
//!    `floor_contact`, so that the pose's lowest joint stays as high as in
//!    the original (longer legs would otherwise push the feet through the
//!    floor, and the feet's image height, which tells the distance and so
//!    the scale, would contradict the lengths);
//! 4. pick one of the subject's 4 real cameras, move the whole window by one
//!    random shift `s ~ N(0, shift_std)` (re-drawn, at most
//!    [`MAX_SHIFT_TRIES`] times, while the root comes closer than `min_depth`
//!    or leaves the image; no shift if every draw fails). The paper shifts
//!    in all three camera axes ([`ShiftPlane::Camera`]), which lifts people
//!    off the floor and so hides their distance; [`ShiftPlane::Ground`]
//!    shifts along the world floor only, so the feet's height in the image
//!    still tells the distance, as it does in any fixed-camera scene;
//!    With probability `wide_cameras` the window is instead seen through a
//!    camera drawn from the many-bodies benchmark's wide distribution
//!    ([`crate::camera_range::wide_cameras`]: any height 0.5-3 m, distance,
//!    heading, tilt and field of view a user might set up), framing the
//!    whole window, no shift; its detector noise is a random residual track
//!    (no recorded track belongs to a drawn camera);
//! 5. project with the camera's real intrinsics *and* distortion straight to
//!    normalized screen coordinates;
//! 6. add detector noise ([`crate::noise`]), rescaled to the new depth;
//! 7. flip horizontally with probability `flip_prob` (`x -> -x`, left/right
//!    joints swapped — the noise is flipped with the sample). Lengths are
//!    symmetric, so the target is unchanged.
//!
//! Every random choice comes from an RNG seeded by `(seed, step, index)`
//! ([`sample_rng`]), so a batch is the same whatever the thread count and a
//! resumed run sees exactly the batches it would have seen.

use blapose_core::bones::rebuild;
use blapose_core::camera::NormalizedIntrinsics;
use blapose_core::level::LevelCamera;
use blapose_core::pose::flip_keypoints_normalized;
use blapose_core::skeleton::{NUM_BONES, NUM_JOINTS};
use blapose_core::{BoneDirections, BoneLengths, Keypoints2d, Pose};
use blapose_model::input::InputCamera;
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use rayon::prelude::*;

use crate::camera_range::{draw_camera_seeing, wide_cameras};
use crate::error::TrainError;
use crate::lengths::LengthSampler;
use crate::noise::{apply_residual, residual_at, MetricResidual, NoiseKind, ResidualBank};

mod config;
mod motion;

pub use config::{ShiftPlane, SynthConfig};
pub use motion::{lowest_height, rebuild_on_floor, MotionSequence};

/// Values per input frame.
pub const FRAME_DIM: usize = NUM_JOINTS * 2;
/// How often the 3D shift is re-drawn before giving up on it.
pub const MAX_SHIFT_TRIES: usize = 16;
/// How often a wide camera is re-drawn to frame a window before the sample
/// falls back to a recorded camera.
pub const WIDE_CAMERA_TRIES: usize = 50;

/// Where the synthetic samples come from: the training sequences, the
/// residual bank and the length sampler.
#[derive(Debug, Clone)]
pub struct SynthSource {
    sequences: Vec<MotionSequence>,
    /// Cumulative frame counts for length-weighted sequence choice.
    cumulative: Vec<u64>,
    residuals: ResidualBank,
    sampler: LengthSampler,
    /// Per sequence, the indices of the cameras samples may use (empty:
    /// every camera).
    camera_subset: Vec<Vec<usize>>,
}

/// [`Sample::camera`] of a sample seen through a wide camera.
pub const WIDE_CAMERA: usize = usize::MAX;

/// Where in which sequence a sample plays.
struct Window {
    sequence: usize,
    /// First source frame (fractional).
    start: f32,
    /// Source frames per output frame.
    stride: f32,
}

/// One synthetic sample.
#[derive(Debug, Clone, PartialEq)]
pub struct Sample {
    /// `T * 34` normalized screen coordinates (H36M-17 order, x then y).
    pub input: Vec<f32>,
    /// The lengths the sample was rebuilt with (metres).
    pub target: BoneLengths,
    /// Which sequence it came from.
    pub sequence: usize,
    /// Which of the sequence's cameras ([`WIDE_CAMERA`]: a drawn one).
    pub camera: usize,
    /// Playback stride.
    pub stride: f32,
    /// Whether it was flipped.
    pub flipped: bool,
}

/// A batch: `batch * T * 34` inputs and `batch * 16` targets, row-major.
#[derive(Debug, Clone, PartialEq)]
pub struct Batch {
    /// Samples in the batch.
    pub batch: usize,
    /// Frames per sample.
    pub seq_len: usize,
    /// Inputs.
    pub inputs: Vec<f32>,
    /// Targets.
    pub targets: Vec<f32>,
}

/// Mix `(seed, step, index)` into one RNG seed (splitmix64 finalizer over a
/// simple combination; distinct triples give well-spread seeds).
pub fn mix_seed(seed: u64, step: u64, index: u64) -> u64 {
    let mut z = seed
        .wrapping_mul(0x9E37_79B9_7F4A_7C15)
        .wrapping_add(step.wrapping_mul(0xD1B5_4A32_D192_ED03))
        .wrapping_add(index.wrapping_mul(0x8CB9_2BA7_2F3D_8DD7))
        .wrapping_add(0x632B_E59B_D9B4_E019);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// The RNG of sample `index` of step `step`.
pub fn sample_rng(seed: u64, step: u64, index: u64) -> StdRng {
    StdRng::seed_from_u64(mix_seed(seed, step, index))
}

impl SynthSource {
    /// A source over `sequences` (training subjects only), with a residual
    /// bank aligned to them (`bank.track(seq, cam)`) and a length sampler.
    pub fn new(
        sequences: Vec<MotionSequence>,
        residuals: ResidualBank,
        sampler: LengthSampler,
    ) -> Result<Self, TrainError> {
        if sequences.iter().all(|s| s.len() < 2) {
            return Err(TrainError::Data(
                "no training sequence with at least 2 frames".into(),
            ));
        }
        if let Some(s) = sequences.iter().find(|s| s.cameras.is_empty()) {
            return Err(TrainError::Data(format!(
                "{}/{} has no camera",
                s.subject, s.action
            )));
        }
        let mut acc = 0u64;
        let cumulative = sequences
            .iter()
            .map(|s| {
                acc += if s.len() >= 2 { s.len() as u64 } else { 0 };
                acc
            })
            .collect();
        Ok(Self {
            sequences,
            cumulative,
            residuals,
            sampler,
            camera_subset: Vec::new(),
        })
    }

    /// Draw samples through the cameras named in `ids` only (all when
    /// `ids` is empty). The network sees keypoints, never which camera
    /// took them, so over several cameras it can only learn their average
    /// geometry (height, tilt, principal point); with one, the geometry is
    /// fixed, which shows how much of a body's size the picture holds when
    /// the camera is known. Every sequence must have one of the cameras.
    pub fn with_cameras(mut self, ids: &[String]) -> Result<Self, TrainError> {
        if ids.is_empty() {
            self.camera_subset.clear();
            return Ok(self);
        }
        let mut subset = Vec::with_capacity(self.sequences.len());
        for seq in &self.sequences {
            let allowed: Vec<usize> = (0..seq.cameras.len())
                .filter(|&i| ids.contains(&seq.cameras[i].id))
                .collect();
            if allowed.is_empty() {
                return Err(TrainError::InvalidArgument(format!(
                    "{}/{} has none of the cameras {}",
                    seq.subject,
                    seq.action,
                    ids.join(",")
                )));
            }
            subset.push(allowed);
        }
        self.camera_subset = subset;
        Ok(self)
    }

    /// Check that every camera can be rectified ([`LevelCamera`]), as
    /// `SynthConfig::rectify` needs.
    pub fn check_rectifiable(&self) -> Result<(), TrainError> {
        for seq in &self.sequences {
            for cam in seq.cameras.iter() {
                LevelCamera::from_camera(cam).map_err(|e| {
                    TrainError::Data(format!("{} camera {}: {e}", seq.subject, cam.id))
                })?;
            }
        }
        Ok(())
    }

    /// The sequences.
    pub fn sequences(&self) -> &[MotionSequence] {
        &self.sequences
    }

    /// The residual bank.
    pub fn residuals(&self) -> &ResidualBank {
        &self.residuals
    }

    /// The length sampler.
    pub fn sampler(&self) -> &LengthSampler {
        &self.sampler
    }

    fn pick_sequence<R: Rng + ?Sized>(&self, rng: &mut R) -> usize {
        let total = *self.cumulative.last().unwrap_or(&0);
        let x = rng.random_range(0..total.max(1));
        self.cumulative
            .partition_point(|&c| c <= x)
            .min(self.sequences.len() - 1)
    }

    /// Synthesize one sample with `rng`.
    pub fn sample<R: Rng + ?Sized>(&self, cfg: &SynthConfig, rng: &mut R) -> Sample {
        let t_len = cfg.seq_len;
        let seq_idx = self.pick_sequence(rng);
        let seq = &self.sequences[seq_idx];
        let n = seq.len();

        // Playback stride and window.
        let mut stride = if cfg.stride_max > cfg.stride_min {
            rng.random_range(cfg.stride_min..cfg.stride_max)
        } else {
            cfg.stride_min
        };
        let span_needed = (t_len.saturating_sub(1)) as f32 * stride;
        let span_avail = (n - 1) as f32;
        if span_needed > span_avail {
            stride = span_avail / (t_len.saturating_sub(1)).max(1) as f32;
        }
        let span = (t_len.saturating_sub(1)) as f32 * stride;
        let start = if span_avail > span {
            rng.random_range(0.0..(span_avail - span))
        } else {
            0.0
        };

        let lengths = self.sampler.sample(&seq.lengths, rng);
        // The body is rebuilt with `subject + (drawn - subject)`, which can
        // differ from the drawn lengths in the last bit: the form every
        // shipped model was trained with, kept so that runs reproduce bit
        // for bit. The target is the drawn lengths.
        let shown: BoneLengths =
            std::array::from_fn(|b| seq.lengths[b] + (lengths[b] - seq.lengths[b]));
        // Drawn only when asked, so recorded-camera runs keep their streams.
        if cfg.wide_cameras > 0.0 && rng.random::<f32>() < cfg.wide_cameras {
            let window = Window {
                sequence: seq_idx,
                start,
                stride,
            };
            if let Some(sample) = self.sample_wide(cfg, &window, &lengths, &shown, rng) {
                return sample;
            }
        }
        let cam_idx = match self.camera_subset.get(seq_idx) {
            Some(allowed) => allowed[rng.random_range(0..allowed.len())],
            None => rng.random_range(0..seq.cameras.len()),
        };
        let cam = &seq.cameras[cam_idx];
        let k: NormalizedIntrinsics = cam.normalized_intrinsics();
        let half_h = cam.height as f32 / cam.width as f32;

        // Rebuilt camera-space poses (unshifted), turned about the vertical
        // through the window's first root by a random yaw when asked.
        let pivot = seq.at(start).0;
        let build = |yaw: f32| -> Vec<Pose> {
            (0..t_len)
                .map(|t| {
                    let (root, dirs) = seq.at(start + t as f32 * stride);
                    let (root, dirs) = turn_about_vertical(root, &dirs, pivot, yaw);
                    let world = if cfg.floor_contact {
                        rebuild_on_floor(root, &dirs, &shown, &seq.lengths)
                    } else {
                        rebuild(root, &dirs, &shown)
                    };
                    cam.world_to_camera_pose(&world)
                })
                .collect()
        };
        // One 3D shift for the whole window.
        let in_view = |poses: &[Pose], s: [f32; 3]| {
            poses.iter().all(|p| {
                let r = [p[0][0] + s[0], p[0][1] + s[1], p[0][2] + s[2]];
                if r[2] < cfg.min_depth {
                    return false;
                }
                let q = k.project(r);
                q[0].abs() <= 1.0 && q[1].abs() <= half_h
            })
        };
        let find_shift = |poses: &[Pose], rng: &mut R| {
            if cfg.shift_std > 0.0 {
                for _ in 0..MAX_SHIFT_TRIES {
                    let s = cfg.shift_plane.draw(cam, cfg.shift_std, rng);
                    if in_view(poses, s) {
                        return Some(s);
                    }
                }
            }
            None
        };
        let mut cam_poses;
        let mut shift;
        if cfg.random_yaw {
            let yaw = rng.random_range(-std::f32::consts::PI..std::f32::consts::PI);
            cam_poses = build(yaw);
            shift = find_shift(&cam_poses, rng);
            if shift.is_none() && !in_view(&cam_poses, [0.0; 3]) {
                // Turned out of the picture: keep the recorded heading.
                cam_poses = build(0.0);
                shift = find_shift(&cam_poses, rng);
            }
        } else {
            cam_poses = build(0.0);
            shift = find_shift(&cam_poses, rng);
        }
        let shift = shift.unwrap_or([0.0; 3]);

        let track = match cfg.noise {
            NoiseKind::Residual => self
                .residuals
                .track(seq_idx, cam_idx)
                .filter(|t| !t.is_empty())
                .or_else(|| self.residuals.random_track(rng)),
            _ => None,
        };
        // Always drawn, so the flip probability does not shift later draws.
        let flipped = rng.random::<f32>() < cfg.flip_prob;

        // Every camera was checked by `check_rectifiable`.
        let read_through = cfg.input_camera(cam).ok().flatten();
        let mut input = Vec::with_capacity(t_len * FRAME_DIM);
        for (t, p) in cam_poses.iter().enumerate() {
            let shifted = p.map(|j| [j[0] + shift[0], j[1] + shift[1], j[2] + shift[2]]);
            let kp: Keypoints2d = k.project_pose(&shifted);
            let depth = shifted[0][2];
            let residual = match cfg.noise {
                NoiseKind::None => None,
                NoiseKind::Gaussian => Some(self.residuals.gaussian(rng)),
                // Aligned with the pose when it is the sample's own track
                // (same frames, same stride).
                NoiseKind::Residual => track.map(|tr| {
                    let u = start + t as f32 * stride;
                    residual_at(tr, u.min((tr.len() - 1) as f32))
                }),
            };
            let kp = as_read(kp, residual, depth, k.focal, read_through.as_ref(), flipped);
            input.extend(kp.iter().flatten());
        }
        Sample {
            input,
            target: lengths,
            sequence: seq_idx,
            camera: cam_idx,
            stride,
            flipped,
        }
    }

    /// The sample of `window` seen through a camera of the wide
    /// distribution (see the module docs, step 4); `None` when no drawn
    /// camera frames it.
    fn sample_wide<R: Rng + ?Sized>(
        &self,
        cfg: &SynthConfig,
        window: &Window,
        lengths: &BoneLengths,
        shown: &BoneLengths,
        rng: &mut R,
    ) -> Option<Sample> {
        let seq = &self.sequences[window.sequence];
        let at = |t: usize| window.start + t as f32 * window.stride;
        let world: Vec<Pose> = (0..cfg.seq_len)
            .map(|t| {
                let (root, dirs) = seq.at(at(t));
                if cfg.floor_contact {
                    rebuild_on_floor(root, &dirs, shown, &seq.lengths)
                } else {
                    rebuild(root, &dirs, shown)
                }
            })
            .collect();
        let drawn = draw_camera_seeing(&wide_cameras(), &world, WIDE_CAMERA_TRIES, rng).ok()?;
        let cam = &drawn.camera;
        let k = cam.normalized_intrinsics();
        let track = match cfg.noise {
            NoiseKind::Residual => self.residuals.random_track(rng),
            _ => None,
        };
        let span = cfg.seq_len.saturating_sub(1) as f32 * window.stride;
        let offset = match track {
            Some(tr) if (tr.len() as f32 - 1.0) > span => {
                rng.random_range(0.0..(tr.len() as f32 - 1.0 - span))
            }
            _ => 0.0,
        };
        let flipped = rng.random::<f32>() < cfg.flip_prob;
        // A drawn camera that does not rectify gives no sample.
        let read_through = cfg.input_camera(cam).ok()?;
        let mut input = Vec::with_capacity(cfg.seq_len * FRAME_DIM);
        for (t, p) in world.iter().enumerate() {
            let c = cam.world_to_camera_pose(p);
            let kp: Keypoints2d = k.project_pose(&c);
            let residual = match cfg.noise {
                NoiseKind::None => None,
                NoiseKind::Gaussian => Some(self.residuals.gaussian(rng)),
                NoiseKind::Residual => {
                    track.map(|tr| residual_at(tr, offset + t as f32 * window.stride))
                }
            };
            let kp = as_read(
                kp,
                residual,
                c[0][2],
                k.focal,
                read_through.as_ref(),
                flipped,
            );
            input.extend(kp.iter().flatten());
        }
        Some(Sample {
            input,
            target: *lengths,
            sequence: window.sequence,
            camera: WIDE_CAMERA,
            stride: window.stride,
            flipped,
        })
    }

    /// Synthesize batch `step` (samples `0..batch`, each with
    /// [`sample_rng`]`(seed, step, i)`), in parallel.
    pub fn batch(&self, cfg: &SynthConfig, seed: u64, step: u64, batch: usize) -> Batch {
        let samples: Vec<Sample> = (0..batch)
            .into_par_iter()
            .map(|i| self.sample(cfg, &mut sample_rng(seed, step, i as u64)))
            .collect();
        let mut inputs = Vec::with_capacity(batch * cfg.seq_len * FRAME_DIM);
        let mut targets = Vec::with_capacity(batch * NUM_BONES);
        for s in &samples {
            inputs.extend_from_slice(&s.input);
            targets.extend_from_slice(&s.target);
        }
        Batch {
            batch,
            seq_len: cfg.seq_len,
            inputs,
            targets,
        }
    }
}

/// One projected frame as the network reads it: detector noise (`residual`,
/// metric, at the root's `depth`), then prepared by the contract's camera
/// when given ([`InputCamera::prepare_frames`]), then mirrored when
/// `flipped`.
fn as_read(
    mut kp: Keypoints2d,
    residual: Option<MetricResidual>,
    depth: f32,
    focal: [f32; 2],
    read_through: Option<&InputCamera>,
    flipped: bool,
) -> Keypoints2d {
    if let Some(r) = residual {
        apply_residual(&mut kp, &r, depth, focal);
    }
    if let Some(camera) = read_through {
        camera.prepare_frames(kp.as_flattened_mut());
    }
    if flipped {
        kp = flip_keypoints_normalized(&kp);
    }
    kp
}

/// `root` and `dirs` turned by `yaw` radians about the vertical (world `z`)
/// through `pivot`: the same motion facing another way, so the four
/// cameras see it from any side instead of the recorded ones (heights, and
/// so the floor contact, are unchanged). `yaw = 0` returns them as they are.
pub fn turn_about_vertical(
    root: [f32; 3],
    dirs: &BoneDirections,
    pivot: [f32; 3],
    yaw: f32,
) -> ([f32; 3], BoneDirections) {
    if yaw == 0.0 {
        return (root, *dirs);
    }
    let (s, c) = yaw.sin_cos();
    let turn = |x: f32, y: f32| [c * x - s * y, s * x + c * y];
    let [x, y] = turn(root[0] - pivot[0], root[1] - pivot[1]);
    let root = [pivot[0] + x, pivot[1] + y, root[2]];
    let dirs = dirs.map(|d| {
        let [x, y] = turn(d[0], d[1]);
        [x, y, d[2]]
    });
    (root, dirs)
}

/// Mirror a flat `T * 34` input sequence horizontally (the flip the
/// augmentation applies); applying it twice is the identity.
pub fn flip_input(input: &[f32]) -> Vec<f32> {
    let mut out = Vec::with_capacity(input.len());
    for frame in input.chunks_exact(FRAME_DIM) {
        let kp: Keypoints2d = std::array::from_fn(|j| [frame[2 * j], frame[2 * j + 1]]);
        out.extend(flip_keypoints_normalized(&kp).iter().flatten());
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use blapose_core::camera::Camera;

    fn tilted_camera() -> Camera {
        // Looking along world +y, tilted down by ~0.3 rad about x.
        let (c, s) = (0.3f64.cos(), 0.3f64.sin());
        Camera {
            id: "test".into(),
            rotation: [[1.0, 0.0, 0.0], [0.0, -s, -c], [0.0, c, -s]],
            center: [0.5, -4.0, 1.6],
            focal: [1145.0, 1144.0],
            principal: [512.0, 515.0],
            radial: [0.0; 3],
            tangential: [0.0; 2],
            width: 1000,
            height: 1002,
        }
    }

    /// World-space direction of a camera-space shift.
    fn to_world(cam: &Camera, s: [f32; 3]) -> [f64; 3] {
        let w = cam.camera_to_world(s.map(f64::from));
        std::array::from_fn(|i| w[i] - cam.center[i])
    }

    #[test]
    fn ground_shift_stays_on_the_floor_and_camera_shift_does_not() {
        let cam = tilted_camera();
        let mut rng = StdRng::seed_from_u64(1);
        let mut max_up = 0.0f64;
        let mut max_up_camera = 0.0f64;
        let mut horizontal = 0.0f64;
        for _ in 0..200 {
            let g = to_world(&cam, ShiftPlane::Ground.draw(&cam, 0.5, &mut rng));
            max_up = max_up.max(g[2].abs());
            horizontal = horizontal.max(g[0].abs().max(g[1].abs()));
            let c = to_world(&cam, ShiftPlane::Camera.draw(&cam, 0.5, &mut rng));
            max_up_camera = max_up_camera.max(c[2].abs());
        }
        assert!(max_up < 1e-5, "ground shift moved {max_up} m vertically");
        assert!(horizontal > 0.5, "ground shift too small: {horizontal}");
        assert!(
            max_up_camera > 0.5,
            "camera shift should move vertically too"
        );
    }

    #[test]
    fn floor_contact_keeps_the_lowest_joint_at_its_height() {
        use blapose_core::bones::{bone_lengths, decompose};
        // A standing pose: feet 2 cm above the floor, pelvis at 0.9 m.
        let mut pose = [[0.0f32; 3]; NUM_JOINTS];
        let up = |z: f32, x: f32| [x, 0.1, z];
        for (j, p) in pose.iter_mut().enumerate() {
            *p = up(0.9 + 0.05 * j as f32, 0.01 * j as f32);
        }
        // Right and left legs (H36M: 1-3 right hip/knee/foot, 4-6 left).
        pose[1] = up(0.9, -0.1);
        pose[2] = up(0.46, -0.1);
        pose[3] = up(0.02, -0.1);
        pose[4] = up(0.9, 0.1);
        pose[5] = up(0.47, 0.1);
        pose[6] = up(0.03, 0.1);
        let (original, dirs) = decompose(&pose).unwrap();
        let longer = original.map(|l| l * 1.2);
        let root = pose[0];
        let floating = rebuild(root, &dirs, &longer);
        assert!(lowest_height(&floating) < -0.05, "longer legs sink");
        let grounded = rebuild_on_floor(root, &dirs, &longer, &original);
        assert!((lowest_height(&grounded) - 0.02).abs() < 1e-5);
        assert_eq!(
            bone_lengths(&grounded).map(|l| (l * 1e4).round()),
            longer.map(|l| (l * 1e4).round()),
            "lifting keeps the new lengths"
        );
        // With the original lengths nothing moves.
        let same = rebuild_on_floor(root, &dirs, &original, &original);
        assert_eq!(same, rebuild(root, &dirs, &original));
    }

    #[test]
    fn a_turn_keeps_heights_lengths_and_the_pivot() {
        let dirs: BoneDirections = std::array::from_fn(|b| {
            let a = b as f32 * 0.4;
            [a.cos() * 0.6, a.sin() * 0.6, 0.8]
        });
        let root = [1.0, 2.0, 0.9];
        let pivot = [0.5, 1.5, 0.9];
        let (r, d) = turn_about_vertical(root, &dirs, pivot, 1.0);
        assert_eq!(r[2], root[2]);
        let dist = |p: [f32; 3]| ((p[0] - pivot[0]).powi(2) + (p[1] - pivot[1]).powi(2)).sqrt();
        assert!((dist(r) - dist(root)).abs() < 1e-5);
        for (a, b) in d.iter().zip(&dirs) {
            assert_eq!(a[2], b[2], "heights kept");
            let n = (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt();
            assert!((n - 1.0).abs() < 1e-5, "still unit");
        }
        assert_eq!(turn_about_vertical(root, &dirs, pivot, 0.0), (root, dirs));
        let (p, _) = turn_about_vertical(pivot, &dirs, pivot, 2.0);
        assert!(dist(p) < 1e-6, "the pivot stays");
    }

    #[test]
    fn flag_config_and_display_spellings_agree() {
        use clap::ValueEnum;
        for p in ShiftPlane::value_variants() {
            assert_eq!(p.to_possible_value().unwrap().get_name(), p.name());
            assert_eq!(serde_json::to_value(p).unwrap(), p.name());
            assert_eq!(p.to_string(), p.name());
        }
        assert!(ShiftPlane::from_str("floor", false).is_err());
    }
}

//! Motion: what happens to a sequence of adjusted poses once their lengths
//! are right. The lifter's bone directions shake from frame to frame and
//! its poses have no place in the world; this module smooths directions
//! (then rebuilds with the session's lengths, so lengths stay exact),
//! places the pelvis in camera space from the 2D keypoints ([`root`]) and
//! holds planted feet ([`feet`]).
//!
//! Two settings, one per way of being served:
//!
//! * **causal** ([`CausalMotion`]): streams. The answer to frame `t` reads
//!   no frame after it and adds no latency; the state is per session and
//!   plain numbers ([`CausalMotion::state`]) so session tokens carry it and
//!   a continuation is bit-exact.
//! * **offline** ([`smooth_sequence`]): a whole recording at once
//!   (`AdjustSequence`), zero-phase (forward and backward).
//!
//! The filters themselves live in [`one_euro`], [`kalman`] and
//! [`zero_phase`]; which one is served by default, and with which settings,
//! was chosen on held-out training subjects (`blapose-lab motion`; the
//! table is in docs/research.md).

pub mod feet;
pub mod fir;
pub mod kalman;
pub mod one_euro;
pub mod root;
pub mod zero_phase;

mod causal;
pub use causal::{CausalMotion, MotionState};

use crate::bones::{decompose, rebuild, BoneError};
use crate::pose::{BoneDirections, BoneLengths, Pose};
use crate::skeleton::{NUM_BONES, NUM_JOINTS, ROOT};
use feet::{detect_contacts, plant_feet, ContactParams};
use fir::{FirBank, FirTaps};
use kalman::{KalmanBank, KalmanParams};
use one_euro::{OneEuroBank, OneEuroParams};
use root::{solve_root, Rays};

/// A frame after the motion stage: the root-relative pose and, when the
/// stage could place it, the pelvis in camera space (metres).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Placed {
    /// Root-relative pose (the input's root kept).
    pub pose: Pose,
    /// Pelvis position in camera space.
    pub root: Option<[f64; 3]>,
}

/// Values a pose's directions are filtered as: 16 bones x 3.
pub const DIRECTION_CHANNELS: usize = NUM_BONES * 3;

/// Frame rate the defaults are given at (Human3.6M's).
pub const DEFAULT_RATE_HZ: f64 = 50.0;

/// The causal stage a session gets when it asks for motion at `rate_hz`.
///
/// Chosen on held-out training trials (`blapose-lab motion`, every 8th
/// trial of S1/S5/S6/S7/S8; the table is in docs/research.md) by two rules
/// fixed before looking: for directions, the smoothest candidate (least
/// acceleration error) whose MPJPE is within 1 % of the unfiltered
/// adjustment's; for the root, the least foot skating among the filters
/// whose root error is within 1 % of the best.
pub fn served_causal(rate_hz: f64) -> CausalMotionConfig {
    CausalMotionConfig {
        directions: Some(CausalSmoothing::Kalman(KalmanParams {
            process_noise: 0.3,
            measurement_noise: 4e-4,
        })),
        root: Some(CausalSmoothing::Kalman(KalmanParams {
            process_noise: 0.1,
            measurement_noise: 0.04,
        })),
        rate_hz,
    }
}

/// The offline stage an `AdjustSequence` gets when it asks for motion.
///
/// Chosen like [`served_causal`]: the directions' smoother with the least
/// velocity error among those whose MPJPE is at most the unfiltered
/// Bi-GRU adjustment's; the root smoothed at 1 Hz (0.5 Hz placed it better
/// but cost MPJPE); feet held (a tenth of the skating, 0.3 mm of MPJPE).
pub fn served_offline(rate_hz: f64) -> OfflineMotionConfig {
    OfflineMotionConfig {
        directions: Some(OfflineSmoothing::SavitzkyGolay {
            window_s: 0.7,
            degree: 2,
        }),
        root: Some(OfflineSmoothing::Butterworth {
            order: 4,
            cutoff_hz: 1.0,
        }),
        feet: Some(FeetConfig {
            contact: ContactParams::default(),
            min_frames: 5,
            blend: 5,
        }),
        rate_hz,
    }
}

/// A causal smoother of many channels.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum CausalSmoothing {
    /// One Euro filter (adaptive low-pass).
    OneEuro(OneEuroParams),
    /// Constant-velocity Kalman filter.
    Kalman(KalmanParams),
    /// Learned finite impulse response ([`fir`]; its taps hold for the
    /// frame rate they were fitted at).
    Fir(FirTaps),
}

/// A zero-phase smoother of whole recordings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum OfflineSmoothing {
    /// Butterworth low-pass of `order`, forward and backward.
    Butterworth {
        /// Order of one pass (even).
        order: usize,
        /// Cutoff (Hz).
        cutoff_hz: f64,
    },
    /// Savitzky-Golay polynomial of `degree` over `window_s` seconds.
    SavitzkyGolay {
        /// Window length (seconds; made an odd number of frames).
        window_s: f64,
        /// Polynomial degree.
        degree: usize,
    },
    /// Rauch-Tung-Striebel smoother of the constant-velocity model.
    Rts(KalmanParams),
}

/// One [`CausalSmoothing`] running over a set of channels sampled
/// together (bone directions, a root, 2D keypoints).
#[derive(Debug, Clone, PartialEq)]
pub enum ChannelFilter {
    /// One Euro filters.
    #[doc(hidden)]
    OneEuro(OneEuroBank),
    /// Kalman filters.
    #[doc(hidden)]
    Kalman(KalmanBank),
    /// Learned FIR filters.
    #[doc(hidden)]
    Fir(FirBank),
}

impl ChannelFilter {
    /// Fresh filters at `rate_hz` (they take their channel count from the
    /// first sample).
    pub fn new(smoothing: CausalSmoothing, rate_hz: f64) -> Self {
        match smoothing {
            CausalSmoothing::OneEuro(p) => ChannelFilter::OneEuro(OneEuroBank::new(p, rate_hz)),
            CausalSmoothing::Kalman(p) => ChannelFilter::Kalman(KalmanBank::new(p, rate_hz)),
            CausalSmoothing::Fir(taps) => ChannelFilter::Fir(FirBank::new(taps)),
        }
    }

    /// Filter one sample of every channel in place.
    pub fn step(&mut self, x: &mut [f64]) {
        match self {
            ChannelFilter::OneEuro(b) => b.step(x),
            ChannelFilter::Kalman(b) => b.step(x),
            ChannelFilter::Fir(b) => b.step(x),
        }
    }

    /// The state as numbers.
    pub fn state(&self) -> Vec<f64> {
        match self {
            ChannelFilter::OneEuro(b) => b.state(),
            ChannelFilter::Kalman(b) => b.state(),
            ChannelFilter::Fir(b) => b.state(),
        }
    }

    /// Continue from [`Self::state`]; `None` when it does not fit.
    pub fn with_state(self, state: &[f64]) -> Option<Self> {
        Some(match self {
            ChannelFilter::OneEuro(b) => ChannelFilter::OneEuro(b.with_state(state)?),
            ChannelFilter::Kalman(b) => ChannelFilter::Kalman(b.with_state(state)?),
            ChannelFilter::Fir(b) => ChannelFilter::Fir(b.with_state(state)?),
        })
    }
}

/// What a session's causal motion stage does.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CausalMotionConfig {
    /// Smoothing of the bone directions (`None`: as the lifter gave them).
    pub directions: Option<CausalSmoothing>,
    /// Smoothing of the solved root position (camera space, metres).
    pub root: Option<CausalSmoothing>,
    /// Frames per second of the stream.
    pub rate_hz: f64,
}

/// A unit bone direction in every bone (a pose whose bones all have
/// length), else the bone's direction stays what the filter made of it.
pub(crate) fn normalized(mut dirs: BoneDirections) -> BoneDirections {
    for d in &mut dirs {
        let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        if n > 0.0 && n.is_finite() {
            *d = d.map(|v| v / n);
        }
    }
    dirs
}

/// A pose's bone directions as the [`DIRECTION_CHANNELS`] values the
/// direction filters read; `None` for a pose with a zero-length bone.
pub fn direction_values(pose: &Pose) -> Option<[f64; DIRECTION_CHANNELS]> {
    decompose(pose).ok().map(|(_, d)| directions_as_values(&d))
}

pub(crate) fn directions_as_values(dirs: &BoneDirections) -> [f64; DIRECTION_CHANNELS] {
    std::array::from_fn(|i| dirs[i / 3][i % 3] as f64)
}

pub(crate) fn values_as_directions(v: &[f64; DIRECTION_CHANNELS]) -> BoneDirections {
    std::array::from_fn(|b| std::array::from_fn(|i| v[3 * b + i] as f32))
}

/// Smooth `frames` samples of `channels` values (frame-major) in place,
/// zero-phase.
pub fn smooth_series(values: &mut [f64], channels: usize, method: OfflineSmoothing, rate_hz: f64) {
    if channels == 0 {
        return;
    }
    if let OfflineSmoothing::Rts(p) = method {
        kalman::rts_smooth(values, channels, p, rate_hz);
        return;
    }
    let frames = values.len() / channels;
    let mut series = vec![0.0; frames];
    for c in 0..channels {
        for (t, v) in series.iter_mut().enumerate() {
            *v = values[t * channels + c];
        }
        match method {
            OfflineSmoothing::Butterworth { order, cutoff_hz } => {
                zero_phase::butterworth_filtfilt(&mut series, order, cutoff_hz, rate_hz)
            }
            OfflineSmoothing::SavitzkyGolay { window_s, degree } => {
                let frames = (window_s * rate_hz).round() as usize;
                zero_phase::savitzky_golay(&mut series, frames | 1, degree)
            }
            OfflineSmoothing::Rts(_) => unreachable!("handled above"),
        }
        for (t, v) in series.iter().enumerate() {
            values[t * channels + c] = *v;
        }
    }
}

/// A whole recording's poses with their bone directions smoothed
/// zero-phase and rebuilt with `lengths[t]`, each from its own root.
/// Errors name the first frame whose pose cannot be decomposed.
pub fn smooth_sequence(
    poses: &[Pose],
    lengths: &[BoneLengths],
    method: OfflineSmoothing,
    rate_hz: f64,
) -> Result<Vec<Pose>, BoneError> {
    if poses.len() != lengths.len() {
        return Err(BoneError::SequenceLengthMismatch {
            poses: poses.len(),
            lengths: lengths.len(),
        });
    }
    let mut values = Vec::with_capacity(poses.len() * DIRECTION_CHANNELS);
    for (t, p) in poses.iter().enumerate() {
        let (_, dirs) = decompose(p).map_err(|e| BoneError::InFrame {
            frame: t,
            source: Box::new(e),
        })?;
        values.extend(directions_as_values(&dirs));
    }
    smooth_series(&mut values, DIRECTION_CHANNELS, method, rate_hz);
    Ok(poses
        .iter()
        .zip(lengths)
        .zip(values.chunks_exact(DIRECTION_CHANNELS))
        .map(|((p, l), v)| {
            let v: &[f64; DIRECTION_CHANNELS] = v.try_into().expect("chunk size");
            rebuild(p[ROOT], &normalized(values_as_directions(v)), l)
        })
        .collect())
}

/// A placed pelvis: camera space, metres.
pub type Root = [f64; 3];

/// What the offline motion stage does with a whole recording.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OfflineMotionConfig {
    /// Smoothing of the bone directions.
    pub directions: Option<OfflineSmoothing>,
    /// Smoothing of the solved root trajectory.
    pub root: Option<OfflineSmoothing>,
    /// Hold planted feet (needs placed roots and an up direction).
    pub feet: Option<FeetConfig>,
    /// Frames per second of the recording.
    pub rate_hz: f64,
}

/// Foot planting settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FeetConfig {
    /// When a foot counts as planted.
    pub contact: ContactParams,
    /// Shortest run of planted frames that is held.
    pub min_frames: usize,
    /// Frames over which a hold eases in and out.
    pub blend: usize,
}

/// A recording's geometry, for placing it: each frame's viewing rays and
/// joint weights, and world "up" in camera coordinates when known.
#[derive(Debug, Clone, Copy)]
pub struct Viewing<'a> {
    /// Per frame: rays and joint weights ([`root::solve_root`]).
    pub rays: &'a [(Rays, [f64; NUM_JOINTS])],
    /// Unit up direction in camera space (feet need it).
    pub up: Option<[f64; 3]>,
}

/// The offline motion stage on a whole recording of adjusted
/// (root-relative) poses with `lengths[t]`: directions smoothed, roots
/// solved and smoothed when `viewing` is given, feet held when also asked
/// and up is known. Frames whose root cannot be solved take the nearest
/// solved one (all `None` when no frame can be solved).
pub fn offline_motion(
    poses: &[Pose],
    lengths: &[BoneLengths],
    config: &OfflineMotionConfig,
    viewing: Option<Viewing>,
) -> Result<(Vec<Pose>, Option<Vec<Root>>), BoneError> {
    let mut out = match config.directions {
        Some(method) => smooth_sequence(poses, lengths, method, config.rate_hz)?,
        None => poses.to_vec(),
    };
    let Some(viewing) = viewing else {
        return Ok((out, None));
    };
    let solved: Vec<Option<[f64; 3]>> = out
        .iter()
        .zip(viewing.rays)
        .map(|(p, (r, w))| solve_root(r, p, w))
        .collect();
    let Some(mut roots) = fill_gaps(&solved) else {
        return Ok((out, None));
    };
    if let Some(method) = config.root {
        let mut flat: Vec<f64> = roots.iter().flatten().copied().collect();
        smooth_series(&mut flat, 3, method, config.rate_hz);
        for (r, v) in roots.iter_mut().zip(flat.chunks_exact(3)) {
            *r = [v[0], v[1], v[2]];
        }
    }
    if let (Some(feet), Some(up)) = (config.feet, viewing.up) {
        let mut placed = place(&out, &roots);
        let contacts = detect_contacts(&placed, up, config.rate_hz, feet.contact);
        plant_feet(&mut placed, &contacts, feet.min_frames, feet.blend);
        // Back to each pose's own frame: only the knees and ankles moved.
        for ((o, p), r) in out.iter_mut().zip(&placed).zip(&roots) {
            let own = o[ROOT];
            for j in feet::MOVED_JOINTS {
                o[j] = std::array::from_fn(|i| ((p[j][i] as f64 - r[i]) + own[i] as f64) as f32);
            }
        }
    }
    Ok((out, Some(roots)))
}

/// Every `None` replaced by the nearest `Some` before it, or after it at
/// the start; `None` when there is none at all.
fn fill_gaps(solved: &[Option<[f64; 3]>]) -> Option<Vec<[f64; 3]>> {
    let first = solved.iter().flatten().next().copied()?;
    let mut last = first;
    Some(
        solved
            .iter()
            .map(|s| {
                if let Some(v) = s {
                    last = *v;
                }
                last
            })
            .collect(),
    )
}

/// A pose moved so that its pelvis is at `root`.
pub fn place_pose(pose: &Pose, root: &Root) -> Pose {
    let own = pose[ROOT];
    pose.map(|j| std::array::from_fn(|i| ((j[i] - own[i]) as f64 + root[i]) as f32))
}

/// Poses moved so that each one's pelvis is at its root.
pub fn place(poses: &[Pose], roots: &[Root]) -> Vec<Pose> {
    poses
        .iter()
        .zip(roots)
        .map(|(p, r)| place_pose(p, r))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bones::bone_lengths;

    fn pose(t: usize, jitter: f32) -> Pose {
        let s = if t.is_multiple_of(2) { jitter } else { -jitter };
        std::array::from_fn(|j| {
            let j = j as f32;
            [
                0.1 * j + s,
                0.05 * (j % 3.0) + 0.01 * t as f32,
                0.02 * j * j,
            ]
        })
    }

    const CONFIG: CausalMotionConfig = CausalMotionConfig {
        directions: Some(CausalSmoothing::Kalman(KalmanParams {
            process_noise: 1.0,
            measurement_noise: 1e-3,
        })),
        root: Some(CausalSmoothing::OneEuro(OneEuroParams {
            min_cutoff_hz: 1.0,
            beta: 0.1,
            derivative_cutoff_hz: 1.0,
        })),
        rate_hz: 50.0,
    };

    #[test]
    fn lengths_stay_exact_and_a_continuation_is_bit_exact() {
        let lengths = bone_lengths(&pose(0, 0.0));
        let mut a = CausalMotion::new(CONFIG);
        for t in 0..30 {
            let out = a.smooth_pose(&pose(t, 0.01), &lengths).unwrap();
            for (x, y) in bone_lengths(&out).iter().zip(&lengths) {
                assert!((x - y).abs() < 1e-5);
            }
            a.smooth_root([0.1 * t as f64, 0.0, 4.0]);
        }
        let mut b = CausalMotion::restore(CONFIG, &a.state()).unwrap();
        for t in 30..60 {
            let p = pose(t, 0.01);
            assert_eq!(a.smooth_pose(&p, &lengths), b.smooth_pose(&p, &lengths));
            let r = [0.1 * t as f64, 0.0, 4.0];
            assert_eq!(a.smooth_root(r), b.smooth_root(r));
        }
        let off = CausalMotionConfig {
            root: None,
            ..CONFIG
        };
        assert!(CausalMotion::restore(off, &a.state()).is_none());
    }

    #[test]
    fn offline_smoothing_keeps_lengths() {
        let poses: Vec<Pose> = (0..50).map(|t| pose(t, 0.01)).collect();
        let lengths = vec![bone_lengths(&pose(0, 0.0)); 50];
        let method = OfflineSmoothing::Butterworth {
            order: 4,
            cutoff_hz: 3.0,
        };
        let out = smooth_sequence(&poses, &lengths, method, 50.0).unwrap();
        for (p, l) in out.iter().zip(&lengths) {
            for (x, y) in bone_lengths(p).iter().zip(l) {
                assert!((x - y).abs() < 1e-5);
            }
        }
    }
}

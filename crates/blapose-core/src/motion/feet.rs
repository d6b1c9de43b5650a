//! Feet on the floor: when a foot is planted (slow and low), how far a
//! planted foot slides (foot skating, the measure animators see), and
//! holding a planted foot still by re-aiming the leg (two-bone inverse
//! kinematics, bone lengths unchanged).
//!
//! Poses here are placed (root included) in a space that does not move
//! with the person: camera space of a static camera, or world coordinates.
//! "Up" is a unit vector in that space; heights are measured along it from
//! the lowest the foot gets in the recording, so no floor calibration is
//! needed.

use crate::pose::Pose;

/// The ankles (the skeleton's lowest joints): right, left.
pub const ANKLES: [usize; 2] = [3, 6];
/// Hip and knee above each ankle of [`ANKLES`].
const LEGS: [[usize; 3]; 2] = [[1, 2, 3], [4, 5, 6]];
/// The joints [`plant_feet`] moves: knees and ankles.
pub const MOVED_JOINTS: [usize; 4] = [2, 3, 5, 6];

/// When a foot counts as planted.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ContactParams {
    /// Fastest a planted ankle moves (m/s).
    pub max_speed_m_s: f64,
    /// Highest a planted ankle is above the lowest it gets (m).
    pub max_height_m: f64,
}

impl Default for ContactParams {
    fn default() -> Self {
        Self {
            max_speed_m_s: 0.3,
            max_height_m: 0.08,
        }
    }
}

fn sub(a: [f32; 3], b: [f32; 3]) -> [f64; 3] {
    std::array::from_fn(|i| a[i] as f64 - b[i] as f64)
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn norm(a: [f64; 3]) -> f64 {
    dot(a, a).sqrt()
}

/// Which frames each foot is planted in: `[foot][frame]`, foot order of
/// [`ANKLES`]. A frame's speed is its displacement from the previous
/// frame (the first frame takes the second's).
pub fn detect_contacts(
    poses: &[Pose],
    up: [f64; 3],
    rate_hz: f64,
    params: ContactParams,
) -> [Vec<bool>; 2] {
    ANKLES.map(|ankle| {
        let heights: Vec<f64> = poses
            .iter()
            .map(|p| dot(p[ankle].map(f64::from), up))
            .collect();
        let lowest = heights.iter().copied().fold(f64::INFINITY, f64::min);
        (0..poses.len())
            .map(|t| {
                let (a, b) = match t {
                    0 if poses.len() > 1 => (1, 0),
                    0 => return heights[0] - lowest <= params.max_height_m,
                    _ => (t, t - 1),
                };
                let speed = norm(sub(poses[a][ankle], poses[b][ankle])) * rate_hz;
                speed <= params.max_speed_m_s && heights[t] - lowest <= params.max_height_m
            })
            .collect()
    })
}

/// Foot skating: the mean horizontal distance (perpendicular to `up`) an
/// ankle moves between two consecutive frames in which it is planted
/// (`contacts` from [`detect_contacts`], usually on the ground truth), in
/// metres per contact frame; `None` without such a pair.
pub fn foot_skate(poses: &[Pose], contacts: &[Vec<bool>; 2], up: [f64; 3]) -> Option<(f64, usize)> {
    let mut sum = 0.0;
    let mut n = 0;
    for (foot, &ankle) in ANKLES.iter().enumerate() {
        for t in 1..poses.len() {
            if contacts[foot][t] && contacts[foot][t - 1] {
                let d = sub(poses[t][ankle], poses[t - 1][ankle]);
                let along = dot(d, up);
                let horizontal: [f64; 3] = std::array::from_fn(|i| d[i] - along * up[i]);
                sum += norm(horizontal);
                n += 1;
            }
        }
    }
    (n > 0).then(|| (sum / n as f64, n))
}

/// Move `pose`'s ankle of `leg` to `target` by turning thigh and calf
/// (lengths unchanged; the knee stays in the plane it bent in). A target
/// out of reach is approached along the same line.
fn reach(pose: &mut Pose, leg: [usize; 3], target: [f64; 3]) {
    let [hip, knee, ankle] = leg;
    let h = pose[hip].map(f64::from);
    let thigh = norm(sub(pose[knee], pose[hip]));
    let calf = norm(sub(pose[ankle], pose[knee]));
    let to_target: [f64; 3] = std::array::from_fn(|i| target[i] - h[i]);
    let dist = norm(to_target);
    if dist < 1e-9 || thigh < 1e-9 || calf < 1e-9 {
        return;
    }
    let dir = to_target.map(|v| v / dist);
    let d = dist.clamp((thigh - calf).abs() + 1e-6, thigh + calf - 1e-6);
    let along = (thigh * thigh - calf * calf + d * d) / (2.0 * d);
    let across = (thigh * thigh - along * along).max(0.0).sqrt();
    // The knee bends towards where it was (the pole).
    let k = sub(pose[knee], pose[hip]);
    let kd = dot(k, dir);
    let mut pole: [f64; 3] = std::array::from_fn(|i| k[i] - kd * dir[i]);
    let pn = norm(pole);
    if pn < 1e-9 {
        return;
    }
    pole = pole.map(|v| v / pn);
    let new_knee: [f64; 3] = std::array::from_fn(|i| h[i] + along * dir[i] + across * pole[i]);
    let new_ankle: [f64; 3] = std::array::from_fn(|i| h[i] + d * dir[i]);
    pose[knee] = new_knee.map(|v| v as f32);
    pose[ankle] = new_ankle.map(|v| v as f32);
}

/// Hold each planted foot still: every run of at least `min_frames`
/// planted frames of a foot gets one ankle position (the run's mean), and
/// the leg is re-aimed to it in every frame of the run; over `blend`
/// frames on either side the target eases from the foot's own position to
/// the run's. Offline: a run's target reads its last frame.
pub fn plant_feet(poses: &mut [Pose], contacts: &[Vec<bool>; 2], min_frames: usize, blend: usize) {
    let n = poses.len();
    for (foot, leg) in LEGS.iter().enumerate() {
        let ankle = leg[2];
        let mut t = 0;
        while t < n {
            if !contacts[foot][t] {
                t += 1;
                continue;
            }
            let start = t;
            while t < n && contacts[foot][t] {
                t += 1;
            }
            let end = t;
            if end - start < min_frames.max(1) {
                continue;
            }
            let mut target = [0.0f64; 3];
            for p in &poses[start..end] {
                for i in 0..3 {
                    target[i] += p[ankle][i] as f64 / (end - start) as f64;
                }
            }
            let lo = start.saturating_sub(blend);
            let hi = (end + blend).min(n);
            for (s, pose) in poses.iter_mut().enumerate().take(hi).skip(lo) {
                let weight = if s < start {
                    (s + 1 - lo) as f64 / (blend + 1) as f64
                } else if s >= end {
                    (hi - s) as f64 / (blend + 1) as f64
                } else {
                    1.0
                };
                let own = pose[ankle].map(f64::from);
                let goal: [f64; 3] =
                    std::array::from_fn(|i| own[i] + weight * (target[i] - own[i]));
                reach(pose, *leg, goal);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bones::bone_lengths;

    /// A standing pose (y down, z forward camera space, up = -y), pelvis
    /// at `x` along the walk.
    fn standing(x: f32) -> Pose {
        let mut p = [[0.0f32; 3]; 17];
        p[0] = [x, 0.0, 4.0];
        p[1] = [x - 0.1, 0.0, 4.0];
        p[2] = [x - 0.1, 0.45, 4.05];
        p[3] = [x - 0.1, 0.9, 4.0];
        p[4] = [x + 0.1, 0.0, 4.0];
        p[5] = [x + 0.1, 0.45, 4.05];
        p[6] = [x + 0.1, 0.9, 4.0];
        for (j, q) in p.iter_mut().enumerate().skip(7) {
            *q = [x, -0.05 * j as f32, 4.0];
        }
        p
    }

    #[test]
    fn planted_feet_stop_sliding_and_keep_their_lengths() {
        let up = [0.0, -1.0, 0.0];
        // The body drifts 2 mm per frame while both feet should be planted.
        let mut poses: Vec<Pose> = (0..40).map(|t| standing(0.002 * t as f32)).collect();
        let contacts = detect_contacts(&poses, up, 50.0, ContactParams::default());
        assert!(contacts.iter().all(|c| c.iter().all(|&v| v)));
        let (before, _) = foot_skate(&poses, &contacts, up).unwrap();
        assert!((before - 0.002).abs() < 1e-6);
        let lengths = bone_lengths(&poses[10]);
        plant_feet(&mut poses, &contacts, 3, 4);
        let (after, _) = foot_skate(&poses, &contacts, up).unwrap();
        assert!(after < 1e-5, "skate after planting {after}");
        for (a, b) in bone_lengths(&poses[10]).iter().zip(&lengths) {
            assert!((a - b).abs() < 1e-5);
        }
    }

    #[test]
    fn a_swinging_foot_is_not_planted() {
        let mut poses: Vec<Pose> = (0..10).map(|_| standing(0.0)).collect();
        for (t, p) in poses.iter_mut().enumerate() {
            p[3][2] += 0.05 * t as f32; // 2.5 m/s forward
            p[3][1] -= 0.2; // and lifted
        }
        let c = detect_contacts(&poses, [0.0, -1.0, 0.0], 50.0, ContactParams::default());
        assert!(c[0].iter().all(|&v| !v));
        assert!(c[1].iter().all(|&v| v));
    }
}

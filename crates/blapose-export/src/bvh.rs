//! BVH (Biovision Hierarchy) for animation tools: Blender, MotionBuilder,
//! Maya, game engines.
//!
//! Positions alone do not fix a skeleton's rotations: a bone can spin about
//! its own axis without moving a joint. A BVH needs that twist, so each
//! joint's rotation is solved here from its bone's direction plus a twist
//! taken from the joints around it (see [`crate::rig::Aim`]): the hip line
//! turns the pelvis, the shoulder line the thorax, the knee and elbow planes
//! the thighs and upper arms (held while the limb is straight, where the
//! plane is undefined), and everything else follows its parent with the
//! smallest rotation, from a neutral direction whose opposite a body cannot
//! reach. So the twist moves continuously and never flips half a turn
//! between frames; Euler angles are then picked nearest the previous
//! frame's. [`BvhReport::max_step_deg`] measures it.
//!
//! The file: `HIERARCHY` with the rig of [`crate::rig`] (offsets = the
//! motion's bone lengths in the T-pose rest pose, metres, Y up), then
//! `MOTION`, one line per frame: the pelvis's position (metres, Y-up frame)
//! and every joint's rotation (degrees) in its channel order. Forward
//! kinematics of a frame gives back its 17 joints to about 1e-7 m (six
//! decimals are written).

use std::io::Write;

use crate::motion::Motion;
use crate::rig::{end_site, offsets, Aim, Line, BEND_RAMP_DEG, RIG};
use crate::rot::{
    add, angle_between, axis_angle, channel_names, cross, dot, from_cols, from_euler, mul, mul_vec,
    norm, perp, sub, swing, to_euler, transpose, unit, Mat3, Vec3, IDENTITY,
};
use crate::text::push_fixed;

const N: usize = RIG.len();

/// What writing a BVH measured.
#[derive(Debug, Clone, PartialEq)]
pub struct BvhReport {
    /// Frames written.
    pub frames: usize,
    /// The largest change of any joint's rotation (relative to its parent;
    /// the pelvis's relative to the world) between two consecutive frames,
    /// degrees.
    pub max_step_deg: f64,
    /// The joint it happened at.
    pub max_step_joint: &'static str,
    /// The later of the two frames.
    pub max_step_frame: usize,
    /// The largest distance between a joint as the written channels
    /// (rounded as written) place it and the motion's position, metres.
    pub max_fk_error_m: f64,
}

/// Solves the rig's rotations frame after frame. It carries what a frame
/// needs from the ones before: the pelvis's last rotation (a fallback for a
/// degenerate pose) and the twist each knee and elbow plane holds.
#[derive(Debug, Clone)]
pub struct Solver {
    prev_root: Mat3,
    held: [f64; N],
}

impl Solver {
    /// A solver for `motion`, its held twists started where a backward pass
    /// over the whole motion ends (the first clear knee and elbow planes).
    pub fn new(motion: &Motion) -> Solver {
        let mut back = Solver::fresh();
        for t in (0..motion.len()).rev() {
            back.frame(&motion.y_up(t));
        }
        Solver {
            prev_root: IDENTITY,
            held: back.held,
        }
    }

    fn fresh() -> Solver {
        Solver {
            prev_root: IDENTITY,
            held: [0.0; N],
        }
    }

    /// Each rig joint's world rotation for the next frame (positions in the
    /// Y-up frame, metres).
    pub fn frame(&mut self, p: &[Vec3; 17]) -> [Mat3; N] {
        let mut w = [IDENTITY; N];
        for (r, joint) in RIG.iter().enumerate() {
            let base = joint.parent.map_or(self.prev_root, |q| w[q]);
            let dir = joint.aim.and_then(|c| unit(sub(p[c], p[joint.at]), 1e-9));
            w[r] = match (joint.kind, dir) {
                (Aim::Leaf { .. }, _) | (_, None) => base,
                (Aim::Frame(line), Some(d)) => frame(p, line, joint.rest_dir, d)
                    .unwrap_or_else(|| aim(&base, joint.rest_dir, d)),
                (Aim::Swing, Some(d)) => aim(&base, joint.rest_dir, d),
                (
                    Aim::Bend {
                        far,
                        rest_bend,
                        fold,
                    },
                    Some(d),
                ) => {
                    let neutral = swing(joint.rest_dir, joint.neutral, [0.0, 1.0, 0.0]);
                    let s = aim(&mul(&base, &neutral), joint.rest_dir, d);
                    let child = joint.aim.expect("bend joints aim");
                    let v = sub(p[far], p[child]);
                    let vp = perp(v, d);
                    let bend = norm(vp).atan2(dot(v, d)).to_degrees();
                    let (lo, hi) = BEND_RAMP_DEG;
                    let weight = smoothstep((bend - lo) / (hi - lo));
                    if let (Some(f), true) = (unit(vp, 1e-12), weight > 0.0) {
                        let r0 = mul_vec(&s, rest_bend);
                        let theta = dot(d, cross(r0, f)).atan2(dot(r0, f));
                        let period = if fold {
                            std::f64::consts::PI
                        } else {
                            std::f64::consts::TAU
                        };
                        let delta = theta - self.held[r];
                        self.held[r] += weight * (delta - period * (delta / period).round());
                    }
                    mul(&axis_angle(d, self.held[r]), &s)
                }
            };
        }
        self.prev_root = w[0];
        w
    }
}

fn smoothstep(x: f64) -> f64 {
    let x = x.clamp(0.0, 1.0);
    x * x * (3.0 - 2.0 * x)
}

/// The smallest rotation after `base` that takes the rest direction to `d`.
fn aim(base: &Mat3, rest_dir: Vec3, d: Vec3) -> Mat3 {
    let from = mul_vec(base, rest_dir);
    let fallback = mul_vec(base, [0.0, 0.0, 1.0]);
    mul(&swing(from, d, fallback), base)
}

/// The absolute frame whose rest `+Y` (the bone) goes to `d` and rest `+X`
/// to the body line made perpendicular to `d`; `None` when the line is
/// parallel to the bone.
fn frame(p: &[Vec3; 17], line: Line, rest_dir: Vec3, d: Vec3) -> Option<Mat3> {
    let hips = sub(p[4], p[1]);
    let shoulders = sub(p[11], p[14]);
    let x_ref = match line {
        Line::Hips => hips,
        Line::Shoulders => shoulders,
        Line::HipsAndShoulders => add(unit(hips, 1e-12)?, unit(shoulders, 1e-12)?),
    };
    let x = unit(perp(x_ref, d), 1e-6 * norm(x_ref).max(1e-12))?;
    let rest_x = [1.0, 0.0, 0.0];
    let rest = from_cols(rest_dir, rest_x, cross(rest_dir, rest_x));
    Some(mul(&from_cols(d, x, cross(d, x)), &transpose(&rest)))
}

/// Local rotations (relative to the parent; the root's to the world).
fn locals(w: &[Mat3; N]) -> [Mat3; N] {
    std::array::from_fn(|r| match RIG[r].parent {
        None => w[r],
        Some(q) => mul(&transpose(&w[q]), &w[r]),
    })
}

fn round6(v: f64) -> f64 {
    (v * 1e6).round() / 1e6
}

/// Write `motion` as BVH to `out`; see the module docs for the layout.
pub fn write_bvh<W: Write>(motion: &Motion, out: W) -> Result<BvhReport, crate::ExportError> {
    let mut out = std::io::BufWriter::with_capacity(1 << 16, out);
    let lengths = motion.lengths();
    out.write_all(hierarchy(motion).as_bytes())?;
    let offs = offsets(lengths);

    let mut solver = Solver::new(motion);
    let mut prev_local = [IDENTITY; N];
    let mut prev_euler = [[0.0; 3]; N];
    let mut report = BvhReport {
        frames: motion.len(),
        max_step_deg: 0.0,
        max_step_joint: RIG[0].name,
        max_step_frame: 0,
        max_fk_error_m: 0.0,
    };
    let mut line = String::with_capacity(1024);
    for t in 0..motion.len() {
        let p = motion.y_up(t);
        let w = solver.frame(&p);
        let local = locals(&w);
        line.clear();
        let root = p[0].map(round6);
        for (k, v) in root.iter().enumerate() {
            if k > 0 {
                line.push(' ');
            }
            push_fixed(&mut line, *v, 6);
        }
        let mut written = [IDENTITY; N];
        for r in 0..N {
            let order = RIG[r].order;
            let e = to_euler(order, &local[r], prev_euler[r]);
            prev_euler[r] = e;
            let deg = e.map(|a| round6(a.to_degrees()));
            for v in deg {
                line.push(' ');
                push_fixed(&mut line, v, 6);
            }
            written[r] = from_euler(order, deg.map(f64::to_radians));
            if t > 0 {
                let step = angle_between(&prev_local[r], &local[r]).to_degrees();
                if step > report.max_step_deg {
                    report.max_step_deg = step;
                    report.max_step_joint = RIG[r].name;
                    report.max_step_frame = t;
                }
            }
        }
        prev_local = local;
        line.push('\n');
        out.write_all(line.as_bytes())?;
        report.max_fk_error_m = report
            .max_fk_error_m
            .max(fk_error(&written, &offs, root, &p));
    }
    out.flush()?;
    Ok(report)
}

/// Forward kinematics of the written channels against the positions.
fn fk_error(local: &[Mat3; N], offs: &[Vec3; N], root: Vec3, p: &[Vec3; 17]) -> f64 {
    let mut world = [IDENTITY; N];
    let mut pos = [[0.0; 3]; N];
    let mut err: f64 = 0.0;
    for r in 0..N {
        match RIG[r].parent {
            None => {
                world[r] = local[r];
                pos[r] = root;
            }
            Some(q) => {
                world[r] = mul(&world[q], &local[r]);
                pos[r] = add(pos[q], mul_vec(&world[q], offs[r]));
            }
        }
        err = err.max(norm(sub(pos[r], p[RIG[r].at])));
    }
    err
}

/// The `HIERARCHY` section and the `MOTION` header.
fn hierarchy(motion: &Motion) -> String {
    let lengths = motion.lengths();
    let offs = offsets(lengths);
    let mut s = String::from("HIERARCHY\n");
    let mut depth = 0usize;
    let mut open: Vec<usize> = Vec::new();
    for r in 0..N {
        while let Some(&top) = open.last() {
            if Some(top) == RIG[r].parent {
                break;
            }
            open.pop();
            depth -= 1;
            s.push_str(&format!("{}}}\n", "\t".repeat(depth)));
        }
        let tab = "\t".repeat(depth);
        let kind = if RIG[r].parent.is_none() {
            "ROOT"
        } else {
            "JOINT"
        };
        let o = offs[r];
        s.push_str(&format!("{tab}{kind} {}\n{tab}{{\n", RIG[r].name));
        s.push_str(&format!(
            "{tab}\tOFFSET {:.6} {:.6} {:.6}\n",
            o[0], o[1], o[2]
        ));
        let rot = channel_names(RIG[r].order);
        if RIG[r].parent.is_none() {
            s.push_str(&format!(
                "{tab}\tCHANNELS 6 Xposition Yposition Zposition {rot}\n"
            ));
        } else {
            s.push_str(&format!("{tab}\tCHANNELS 3 {rot}\n"));
        }
        if let Some(e) = end_site(r, lengths) {
            s.push_str(&format!(
                "{tab}\tEnd Site\n{tab}\t{{\n{tab}\t\tOFFSET {:.6} {:.6} {:.6}\n{tab}\t}}\n",
                e[0], e[1], e[2]
            ));
        }
        open.push(r);
        depth += 1;
    }
    while open.pop().is_some() {
        depth -= 1;
        s.push_str(&format!("{}}}\n", "\t".repeat(depth)));
    }
    s.push_str(&format!(
        "MOTION\nFrames: {}\nFrame Time: {:.9}\n",
        motion.len(),
        1.0 / motion.fps()
    ));
    s
}

#[cfg(test)]
mod tests;

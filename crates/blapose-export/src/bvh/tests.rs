use super::*;
use crate::rot::{about, from_euler, Order};
use blapose_core::skeleton::JOINT_NAMES;
use blapose_core::{BoneLengths, Pose};

/// A BVH as a reader sees it.
struct Parsed {
    names: Vec<String>,
    parents: Vec<Option<usize>>,
    offsets: Vec<Vec3>,
    /// Per joint: (first channel index, position channels?, rotation order).
    channels: Vec<(usize, bool, Order)>,
    frames: Vec<Vec<f64>>,
    frame_time: f64,
}

fn parse(text: &str) -> Parsed {
    let mut p = Parsed {
        names: vec![],
        parents: vec![],
        offsets: vec![],
        channels: vec![],
        frames: vec![],
        frame_time: 0.0,
    };
    let mut stack: Vec<Option<usize>> = vec![];
    let mut in_end = false;
    let mut next_channel = 0;
    let mut lines = text.lines();
    for line in lines.by_ref() {
        let w: Vec<&str> = line.split_whitespace().collect();
        match w.first().copied() {
            Some("ROOT") | Some("JOINT") => {
                p.names.push(w[1].to_string());
                p.parents.push(stack.iter().rev().flatten().next().copied());
            }
            Some("End") => in_end = true,
            Some("{") => stack.push(if in_end {
                None
            } else {
                Some(p.names.len() - 1)
            }),
            Some("}") if stack.pop() == Some(None) => in_end = false,
            Some("OFFSET") if !in_end => p
                .offsets
                .push([w[1], w[2], w[3]].map(|v| v.parse().unwrap())),
            Some("CHANNELS") => {
                let n: usize = w[1].parse().unwrap();
                let rot: Vec<usize> = w[2..]
                    .iter()
                    .filter(|c| c.ends_with("rotation"))
                    .map(|c| (c.as_bytes()[0] - b'X') as usize)
                    .collect();
                p.channels
                    .push((next_channel, n == 6, [rot[0], rot[1], rot[2]]));
                next_channel += n;
            }
            Some("MOTION") => break,
            _ => {}
        }
    }
    for line in lines {
        if let Some(t) = line.strip_prefix("Frame Time:") {
            p.frame_time = t.trim().parse().unwrap();
        } else if !line.starts_with("Frames:") {
            let v: Vec<f64> = line
                .split_whitespace()
                .map(|x| x.parse().unwrap())
                .collect();
            assert_eq!(v.len(), next_channel);
            p.frames.push(v);
        }
    }
    p
}

/// Forward kinematics: each joint's world position and local rotation.
fn fk(p: &Parsed, frame: usize) -> (Vec<Vec3>, Vec<Mat3>) {
    let v = &p.frames[frame];
    let n = p.names.len();
    let (mut pos, mut world, mut local) = (vec![[0.0; 3]; n], vec![IDENTITY; n], vec![IDENTITY; n]);
    for j in 0..n {
        let (c, has_pos, order) = p.channels[j];
        let r0 = if has_pos { c + 3 } else { c };
        local[j] = from_euler(order, [v[r0], v[r0 + 1], v[r0 + 2]].map(f64::to_radians));
        match p.parents[j] {
            None => {
                pos[j] = add(p.offsets[j], [v[c], v[c + 1], v[c + 2]]);
                world[j] = local[j];
            }
            Some(q) => {
                pos[j] = add(pos[q], mul_vec(&world[q], p.offsets[j]));
                world[j] = mul(&world[q], &local[j]);
            }
        }
    }
    (pos, local)
}

fn example(name: &str) -> (Vec<Pose>, [f64; 3]) {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../examples")
        .join(name);
    let npz = blapose_data::npz::read_npz(path).unwrap();
    let up = npz.get("camera_up").unwrap().data();
    (
        npz.poses("pose_3d").unwrap(),
        [up[0] as f64, up[1] as f64, up[2] as f64],
    )
}

/// Write, read back, and check every joint by name; returns the report.
fn round_trip(motion: &Motion, tol: f64) -> BvhReport {
    let mut out = Vec::new();
    let report = write_bvh(motion, &mut out).unwrap();
    let parsed = parse(std::str::from_utf8(&out).unwrap());
    assert_eq!(parsed.frames.len(), motion.len());
    assert!((parsed.frame_time - 1.0 / motion.fps()).abs() < 1e-9);
    let mut worst: f64 = 0.0;
    for t in 0..motion.len() {
        let (pos, _) = fk(&parsed, t);
        let want = motion.y_up(t);
        for (j, name) in JOINT_NAMES.iter().enumerate() {
            let k = parsed.names.iter().position(|n| n == name).unwrap();
            worst = worst.max(norm(sub(pos[k], want[j])));
        }
    }
    assert!(worst < tol, "worst joint error {worst} m");
    assert!(report.max_fk_error_m < tol, "{report:?}");
    report
}

#[test]
fn hierarchy_has_the_joints_the_lengths_and_end_sites() {
    let (poses, _) = example("cmu_02_02_walk.npz");
    let lengths: BoneLengths = blapose_core::bones::bone_lengths(&poses[0]);
    let m = Motion::new(&poses[..2], &lengths, 50.0).unwrap();
    let mut out = Vec::new();
    write_bvh(&m, &mut out).unwrap();
    let text = String::from_utf8(out).unwrap();
    assert!(text.starts_with(
        "HIERARCHY\nROOT pelvis\n{\n\tOFFSET 0.000000 0.000000 0.000000\n\tCHANNELS 6 Xposition"
    ));
    assert_eq!(text.matches("End Site").count(), 5);
    assert_eq!(text.matches("JOINT ").count(), 20);
    assert!(text.contains("MOTION\nFrames: 2\nFrame Time: 0.020000000\n"));
    assert_eq!(text.matches('{').count(), text.matches('}').count());
    let parsed = parse(&text);
    // Rest pose: each bone's parent-to-child distance is its length.
    let mut rest = vec![[0.0; 3]; parsed.names.len()];
    for j in 0..parsed.names.len() {
        rest[j] = match parsed.parents[j] {
            None => parsed.offsets[j],
            Some(q) => add(rest[q], parsed.offsets[j]),
        };
    }
    for (b, length) in lengths.iter().enumerate() {
        let at = |joint: usize| {
            parsed
                .names
                .iter()
                .position(|n| n == JOINT_NAMES[joint])
                .unwrap()
        };
        let (c, p) = (at(b + 1), at(blapose_core::skeleton::bone_parent(b)));
        let d = norm(sub(rest[c], rest[p]));
        assert!(
            (d - *length as f64).abs() < 1e-6,
            "bone {b}: {d} vs {length}"
        );
    }
}

#[test]
fn every_example_comes_back_within_a_micrometre_without_flips() {
    for name in [
        "cmu_02_02_walk.npz",
        "cmu_09_01_run.npz",
        "cmu_13_32_jump.npz",
        "cmu_20_06_march.npz",
        "cmu_21_11_highfive.npz",
    ] {
        let (poses, up) = example(name);
        // The lifted poses, re-posed with their mean lengths: realistic,
        // noisy directions (3 degrees per bone per frame).
        let mut mean = [0.0f32; 16];
        for p in &poses {
            let l = blapose_core::bones::bone_lengths(p);
            (0..16).for_each(|b| mean[b] += l[b] / poses.len() as f32);
        }
        let m = Motion::new(&poses, &mean, 50.0)
            .unwrap()
            .with_up(up)
            .unwrap();
        let report = round_trip(&m, 2e-6);
        println!("{name}: {report:?}");
        assert!(report.max_step_deg < 30.0, "{name}: {report:?}");
    }
}

#[test]
fn any_pose_comes_back_even_contorted_ones() {
    // Pseudo-random joints: not a body, but forward kinematics is exact
    // whatever the twist.
    let mut x = 0.5f64;
    let mut rnd = || {
        x = (x * 3.9 * (1.0 - x)).clamp(0.01, 0.99);
        (x - 0.5) as f32
    };
    let poses: Vec<Pose> = (0..40)
        .map(|_| std::array::from_fn(|_| [rnd(), rnd(), rnd()]))
        .collect();
    let lengths: BoneLengths = std::array::from_fn(|b| 0.1 + 0.02 * b as f32);
    round_trip(&Motion::new(&poses, &lengths, 30.0).unwrap(), 2e-6);
}

/// The rest pose itself, in the poses' coordinates (camera axes: y down, z
/// towards the scene, so the Y-up frame is (x, -y, -z)).
fn t_pose(lengths: &BoneLengths) -> Pose {
    crate::rig::rest_positions(lengths).map(|p| [p[0] as f32, -p[1] as f32, -p[2] as f32])
}

#[test]
fn the_rest_pose_has_zero_rotations() {
    let lengths: BoneLengths = std::array::from_fn(|b| 0.1 + 0.02 * b as f32);
    let m = Motion::new(&[t_pose(&lengths)], &lengths, 50.0).unwrap();
    let mut out = Vec::new();
    write_bvh(&m, &mut out).unwrap();
    let parsed = parse(std::str::from_utf8(&out).unwrap());
    for (k, v) in parsed.frames[0].iter().enumerate() {
        assert!(v.abs() < 1e-5, "channel {k}: {v}");
    }
}

#[test]
fn knee_bending_and_turning_has_no_flips() {
    // A T-pose turning a full circle about the vertical while the right knee
    // bends from straight to 120 degrees and back (also slightly backwards),
    // 400 frames: every rotation must change smoothly.
    let lengths: BoneLengths = std::array::from_fn(|b| 0.1 + 0.02 * b as f32);
    let rest = t_pose(&lengths);
    let poses: Vec<Pose> = (0..400)
        .map(|t| {
            let s = t as f64 / 399.0;
            let mut p = rest;
            let bend = (120.0 * (std::f64::consts::PI * s).sin() - 5.0).to_radians();
            // Knee bends backwards: rotate the calf about the x axis.
            let knee = p[2].map(f64::from);
            let calf = sub(p[3].map(f64::from), knee);
            p[3] = add(knee, mul_vec(&about(0, bend), calf)).map(|v| v as f32);
            let turn = about(1, std::f64::consts::TAU * s);
            p.map(|q| mul_vec(&turn, q.map(f64::from)).map(|v| v as f32))
        })
        .collect();
    let report = round_trip(&Motion::new(&poses, &lengths, 50.0).unwrap(), 2e-6);
    assert!(report.max_step_deg < 5.0, "{report:?}");
}

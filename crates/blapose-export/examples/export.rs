//! Export a replay or adjusted `.npz` to BVH, C3D and TRC, and time it.
//!
//! ```sh
//! cargo run --release -p blapose-export --example export -- a.npz --bvh a.bvh --c3d a.c3d --trc a.trc
//! cargo run --release -p blapose-export --example export -- a.npz --frames 10000 --bvh /tmp/t.bvh   # timing
//! ```
//!
//! Poses: `adjusted_3d` (else `pose_3d`); lengths: the last row of
//! `bone_lengths` (else the last frame's own); `fps` (else 50); up:
//! `camera_up` (else camera axes). `--frames N` repeats the sequence
//! back and forth to N frames. The client's `--bvh/--c3d/--trc` do the same
//! after a replay or adjustment; this is for files already adjusted.

use std::path::PathBuf;
use std::time::Instant;

use blapose_export::{save, Format, Motion};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let input = PathBuf::from(
        args.next()
            .ok_or("usage: export FILE.npz [--frames N] [--bvh P] [--c3d P] [--trc P]")?,
    );
    let (mut frames, mut outputs) = (None, Vec::new());
    while let Some(flag) = args.next() {
        let value = args.next().ok_or(format!("{flag} needs a value"))?;
        match flag.as_str() {
            "--frames" => frames = Some(value.parse::<usize>()?),
            "--bvh" => outputs.push((Format::Bvh, PathBuf::from(value))),
            "--c3d" => outputs.push((Format::C3d, PathBuf::from(value))),
            "--trc" => outputs.push((Format::Trc, PathBuf::from(value))),
            _ => return Err(format!("unknown flag {flag}").into()),
        }
    }
    let npz = blapose_data::npz::read_npz(&input)?;
    let key = if npz.contains("adjusted_3d") {
        "adjusted_3d"
    } else {
        "pose_3d"
    };
    let mut poses = npz.poses(key)?;
    let lengths: [f32; 16] = match npz.get("bone_lengths") {
        Ok(a) if a.data().len() >= 16 => a.data()[a.data().len() - 16..].try_into()?,
        _ => blapose_core::bones::bone_lengths(poses.last().ok_or("no poses")?),
    };
    let fps = npz.get("fps").map(|a| a.data()[0] as f64).unwrap_or(50.0);
    if let Some(n) = frames {
        let cycle: Vec<_> = poses.iter().chain(poses.iter().rev()).copied().collect();
        poses = cycle.iter().cycle().take(n).copied().collect();
    }
    let mut motion = Motion::new(&poses, &lengths, fps)?;
    if let Ok(up) = npz.get("camera_up") {
        let u = up.data();
        motion = motion.with_up([u[0] as f64, u[1] as f64, u[2] as f64])?;
    }
    println!(
        "{}: {} frames of {key} at {fps} fps, re-posed with the last bone lengths (moved joints by at most {:.3} mm)",
        input.display(),
        motion.len(),
        1000.0 * motion.repose_shift()
    );
    for (format, path) in outputs {
        let start = Instant::now();
        let saved = save(&motion, format, &path)?;
        let ms = start.elapsed().as_secs_f64() * 1000.0;
        println!(
            "{} {}: {} bytes in {ms:.1} ms",
            format.name(),
            path.display(),
            saved.bytes
        );
        if let Some(r) = saved.bvh {
            println!(
                "  largest frame-to-frame joint rotation {:.1} deg ({}, frame {}); forward kinematics within {:.2e} m",
                r.max_step_deg, r.max_step_joint, r.max_step_frame, r.max_fk_error_m
            );
        }
    }
    Ok(())
}

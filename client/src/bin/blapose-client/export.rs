//! `--bvh`, `--c3d`, `--trc` (on `replay` and `adjust`): the adjusted motion
//! for animation tools (BVH) and biomechanics tools (C3D, OpenSim's TRC),
//! written by `blapose-export`.
//!
//! The paths are checked before the file is sent, so a typo costs nothing.
//! A skeleton's bones cannot change length, so every file uses one set of
//! lengths, the last frame's: for the offline Bi-GRU the sequence's one set,
//! for a stream its final estimate, and then every frame is re-posed with it
//! (the output says so). The up direction is the file's `camera_up` when it
//! has one (whether or not `--camera` sends it), else the camera's `-y`.

use anyhow::{Context, Result};
use blapose_client::Adjusted;
use blapose_export::{check_path, save, Format, Motion};

use crate::IoArgs;

/// Frame rate of a file without `fps` (the HTML report assumes the same).
const DEFAULT_FPS: f64 = 50.0;

impl IoArgs {
    /// The export files asked for, in the order BVH, C3D, TRC.
    fn exports(&self) -> Vec<(Format, &std::path::Path)> {
        [
            (Format::Bvh, &self.bvh),
            (Format::C3d, &self.c3d),
            (Format::Trc, &self.trc),
        ]
        .into_iter()
        .filter_map(|(f, p)| p.as_deref().map(|p| (f, p)))
        .collect()
    }

    /// Fail before any work when an export path cannot be written.
    pub(crate) fn check_exports(&self) -> Result<()> {
        for (_, path) in self.exports() {
            check_path(path)?;
        }
        Ok(())
    }

    /// Write the files asked for from `result` (`fps` and `up`: the file's).
    pub(crate) fn write_exports(
        &self,
        result: &Adjusted,
        fps: Option<f32>,
        up: Option<[f32; 3]>,
    ) -> Result<()> {
        let files = self.exports();
        if files.is_empty() {
            return Ok(());
        }
        let lengths = result
            .bone_lengths
            .last()
            .context("cannot export: the sequence has no poses")?;
        let fps = fps.map_or(DEFAULT_FPS, f64::from);
        let mut motion = Motion::new(&result.placed_poses(), lengths, fps)?;
        if let Some(up) = up {
            motion = motion.with_up(up.map(f64::from))?;
        }
        let names: Vec<&str> = files.iter().map(|(f, _)| f.name()).collect();
        if result.bone_lengths.iter().all(|l| l == lengths) {
            println!(
                "{}: the sequence's one set of bone lengths, {fps} frames/s",
                names.join(", ")
            );
        } else {
            println!(
                "{}: every frame re-posed with the final bone lengths (they changed over the stream; \
                 joints moved by at most {:.1} mm), {fps} frames/s",
                names.join(", "),
                1000.0 * motion.repose_shift()
            );
        }
        for (format, path) in files {
            let saved = save(&motion, format, path)?;
            match saved.bvh {
                Some(r) => println!(
                    "wrote {} (BVH: 21 joints, metres, Y up; largest frame-to-frame joint rotation {:.1} deg, {} at frame {})",
                    path.display(),
                    r.max_step_deg,
                    r.max_step_joint,
                    r.max_step_frame
                ),
                None => println!("wrote {} ({}: 17 markers, millimetres, Z up)", path.display(), format.name()),
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use crate::{Cli, Command};
    use clap::Parser;
    use std::path::PathBuf;

    fn io(args: &[&str]) -> crate::IoArgs {
        match Cli::try_parse_from(args).unwrap().command {
            Command::Replay { io, .. } | Command::Adjust { io, .. } => io,
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn export_flags_parse_and_bad_paths_fail_first() {
        for command in ["replay", "adjust"] {
            let io = io(&[
                "blapose-client",
                command,
                "x.npz",
                "--bvh",
                "a.bvh",
                "--c3d",
                "a.c3d",
                "--trc",
                "a.trc",
            ]);
            assert_eq!(io.bvh, Some(PathBuf::from("a.bvh")));
            assert_eq!(io.exports().len(), 3);
            assert!(io.check_exports().is_ok());
        }
        let io = io(&[
            "blapose-client",
            "adjust",
            "x.npz",
            "--c3d",
            "/nonexistent-dir/a.c3d",
        ]);
        let e = io.check_exports().unwrap_err().to_string();
        assert_eq!(
            e,
            "cannot write /nonexistent-dir/a.c3d: its directory does not exist"
        );
        assert!(Cli::try_parse_from(["blapose-client", "info", "--bvh", "a.bvh"]).is_err());
    }
}

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
//! With `--motion` the poses are placed at their roots; when the server
//! also gave world coordinates (a calibration with a camera height), the
//! files are in the world, the floor at height 0.

use anyhow::{bail, Context, Result};
use blapose_client::Adjusted;
use blapose_export::c3d::MAX_FRAMES as C3D_MAX_FRAMES;
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

    /// Fail before any work when an export path cannot be written; warn,
    /// also before any work, when a sequence of `frames` frames is too long
    /// for a C3D ([`Self::refused_exports`]).
    pub(crate) fn check_exports(&self, frames: usize) -> Result<()> {
        for (_, path) in self.exports() {
            check_path(path)?;
        }
        if let Some(why) = self.c3d_refusal(frames) {
            eprintln!("warning: {why}");
        }
        Ok(())
    }

    /// Why the C3D asked for cannot hold `frames` frames (`None`: it can,
    /// or none was asked for).
    fn c3d_refusal(&self, frames: usize) -> Option<String> {
        let path = self.c3d.as_deref()?;
        (frames > C3D_MAX_FRAMES).then(|| {
            format!(
                "--c3d {}: a C3D holds at most {C3D_MAX_FRAMES} frames and the sequence has \
                 {frames}; every other file is written, the C3D is not (cut the sequence to \
                 {C3D_MAX_FRAMES} frames for a C3D, or use --trc: the same markers, no limit)",
                path.display()
            )
        })
    }

    /// After every other output is written: an error when a file asked for
    /// was skipped (a C3D too long for the format), so the exit status says
    /// so.
    pub(crate) fn refused_exports(&self, frames: usize) -> Result<()> {
        match self.c3d_refusal(frames) {
            Some(why) => bail!(why),
            None => Ok(()),
        }
    }

    /// Write the files asked for from `result` (`fps` and `up`: the file's).
    pub(crate) fn write_exports(
        &self,
        result: &Adjusted,
        fps: Option<f32>,
        up: Option<[f32; 3]>,
    ) -> Result<()> {
        let refused = self.c3d_refusal(result.adjusted.len()).is_some();
        let files: Vec<_> = self
            .exports()
            .into_iter()
            .filter(|(format, _)| !(refused && *format == Format::C3d))
            .collect();
        if files.is_empty() {
            return Ok(());
        }
        let lengths = result
            .bone_lengths
            .last()
            .context("cannot export: the sequence has no poses")?;
        let fps = fps.map_or(DEFAULT_FPS, f64::from);
        // Placed by the motion stage through a calibration with a camera
        // height: world coordinates, z up, the floor at 0. Placed without
        // one: camera space at the placed roots, up as the file says.
        let world = result.placement.as_ref().and_then(|p| p.world.as_ref());
        let (poses, up) = match world {
            Some(world) => (world.clone(), Some([0.0, 0.0, 1.0])),
            None => (result.placed_poses(), up.map(|u| u.map(f64::from))),
        };
        let mut motion = Motion::new(&poses, lengths, fps)?;
        if let Some(up) = up {
            motion = motion.with_up(up)?;
        }
        if world.is_some() {
            println!("exports in world coordinates (the floor at height 0, from the camera's height and up)");
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

    /// `command` asked for a BVH, a C3D and a TRC.
    fn all_three(command: &str) -> crate::IoArgs {
        io(&[
            "blapose-client",
            command,
            "x.npz",
            "--bvh",
            "a.bvh",
            "--c3d",
            "a.c3d",
            "--trc",
            "a.trc",
        ])
    }

    #[test]
    fn export_flags_parse_and_bad_paths_fail_first() {
        for command in ["replay", "adjust"] {
            let io = all_three(command);
            assert_eq!(io.bvh, Some(PathBuf::from("a.bvh")));
            assert_eq!(io.exports().len(), 3);
            assert!(io.check_exports(1).is_ok());
        }
        let io = io(&[
            "blapose-client",
            "adjust",
            "x.npz",
            "--c3d",
            "/nonexistent-dir/a.c3d",
        ]);
        let e = io.check_exports(1).unwrap_err().to_string();
        assert_eq!(
            e,
            "cannot write /nonexistent-dir/a.c3d: its directory does not exist"
        );
        assert!(Cli::try_parse_from(["blapose-client", "info", "--bvh", "a.bvh"]).is_err());
    }

    #[test]
    fn a_sequence_too_long_for_a_c3d_is_named_before_anything_runs() {
        let three = all_three("adjust");
        assert!(three.check_exports(65_535).is_ok());
        assert!(three.refused_exports(65_535).is_ok());
        // Over the limit: a warning first, the run goes on, every other
        // file is written, and the exit status is an error naming the limit
        // and what to do.
        assert!(three.check_exports(65_536).is_ok());
        let e = three.refused_exports(65_536).unwrap_err().to_string();
        assert!(e.contains("at most 65535 frames"), "{e}");
        assert!(e.contains("the sequence has 65536"), "{e}");
        assert!(e.contains("--trc"), "{e}");
        let without = io(&["blapose-client", "adjust", "x.npz", "--bvh", "a.bvh"]);
        assert!(without.refused_exports(1_000_000).is_ok());
    }
}

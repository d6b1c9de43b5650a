//! blapose-export: adjusted motion out to the tools people animate and
//! analyse it with.
//!
//! blapose's answer is a sequence of 3D joint positions with constant,
//! person-specific bone lengths. Animators want that as a skeleton with
//! rotations (BVH: Blender, MotionBuilder, game engines); biomechanists want
//! markers (C3D for every lab tool, TRC for OpenSim). This crate writes all
//! three from one [`Motion`], so the files of one request describe the same
//! movement:
//!
//! - [`Motion`] re-poses every frame with one set of bone lengths (a stream's
//!   lengths change as its estimate converges; a skeleton's cannot) and
//!   carries the frame rate and which way is up ([`axes`]).
//! - [`bvh`]: a 21-joint rig (the 17 joints by name plus two pelvis and two
//!   clavicle helpers, see [`rig`] for why), T-pose rest pose with the
//!   motion's lengths, metres, Y up; rotations solved with twist from the hip
//!   and shoulder lines and the knee and elbow planes.
//! - [`c3d`]: 17 points named as the joints, millimetres, Z up, float data.
//! - [`trc`]: the same markers as OpenSim's tab-separated TRC.
//!
//! Units and axes, in short: BVH in metres with Y up (the poses rotated so
//! the world's up is `+Y` and a person facing the camera faces `+Z`); C3D
//! and TRC in millimetres with Z up (`(X, -Z, Y)` of the BVH frame, what
//! Blender's BVH importer turns the BVH into). Nothing is translated.
//!
//! It depends on `blapose-core` alone (plus `thiserror`): no I/O crate, no
//! linear algebra crate; the rotation algebra it needs is in [`rot`].

pub mod axes;
pub mod bvh;
pub mod c3d;
mod error;
mod motion;
pub mod rig;
pub mod rot;
mod text;
pub mod trc;

use std::fs::File;
use std::path::{Path, PathBuf};

pub use axes::Axes;
pub use bvh::{write_bvh, BvhReport};
pub use c3d::write_c3d;
pub use error::ExportError;
pub use motion::Motion;
pub use trc::write_trc;

/// An export format.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Format {
    /// Biovision Hierarchy: skeleton and rotations, metres, Y up.
    Bvh,
    /// C3D: 17 points, millimetres, Z up.
    C3d,
    /// OpenSim TRC: 17 markers, millimetres, Z up.
    Trc,
}

impl Format {
    /// Its usual name.
    pub fn name(self) -> &'static str {
        match self {
            Format::Bvh => "BVH",
            Format::C3d => "C3D",
            Format::Trc => "TRC",
        }
    }
}

fn io_at(path: &Path) -> impl Fn(std::io::Error) -> ExportError + '_ {
    move |cause| ExportError::Io {
        path: path.to_path_buf(),
        cause,
    }
}

/// Check, before any work, that `path` can be written: its directory exists
/// and it is not a directory. (The write itself can still fail, e.g. on
/// permissions; its error names the path too.)
pub fn check_path(path: &Path) -> Result<(), ExportError> {
    let err = |msg: &str| ExportError::Io {
        path: path.to_path_buf(),
        cause: std::io::Error::other(msg.to_string()),
    };
    if path.is_dir() {
        return Err(err("it is a directory"));
    }
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    };
    if !dir.is_dir() {
        return Err(err("its directory does not exist"));
    }
    if std::fs::metadata(&dir)
        .map(|m| m.permissions().readonly())
        .unwrap_or(false)
    {
        return Err(err("its directory is read-only"));
    }
    Ok(())
}

/// What [`save`] wrote.
#[derive(Debug, Clone, PartialEq)]
pub struct Saved {
    /// The format.
    pub format: Format,
    /// Bytes written.
    pub bytes: u64,
    /// For a BVH, what writing it measured.
    pub bvh: Option<BvhReport>,
}

/// Write `motion` to the file `path` in `format`. A failed write removes
/// the partial file.
pub fn save(motion: &Motion, format: Format, path: &Path) -> Result<Saved, ExportError> {
    let file = File::create(path).map_err(io_at(path))?;
    let result = match format {
        Format::Bvh => write_bvh(motion, &file).map(Some),
        Format::C3d => write_c3d(motion, &file).map(|_| None),
        Format::Trc => {
            let name = path
                .file_name()
                .map_or_else(String::new, |n| n.to_string_lossy().into_owned());
            write_trc(motion, &file, &name).map(|_| None)
        }
    };
    let bvh = match result {
        Ok(r) => r,
        Err(e) => {
            drop(file);
            let _ = std::fs::remove_file(path);
            return Err(match e {
                ExportError::Io { cause, .. } => io_at(path)(cause),
                e => e,
            });
        }
    };
    let bytes = file.metadata().map_err(io_at(path))?.len();
    Ok(Saved { format, bytes, bvh })
}

#[cfg(test)]
mod tests {
    use super::*;
    use blapose_core::Pose;

    fn motion() -> Motion {
        let pose: Pose =
            std::array::from_fn(|j| [0.05 * j as f32, -0.1 * j as f32, 0.02 * (j % 3) as f32]);
        Motion::new(&[pose], &blapose_core::bones::bone_lengths(&pose), 50.0).unwrap()
    }

    #[test]
    fn unwritable_paths_are_named() {
        let e = check_path(Path::new("/nonexistent-dir/a.bvh")).unwrap_err();
        assert_eq!(
            e.to_string(),
            "cannot write /nonexistent-dir/a.bvh: its directory does not exist"
        );
        let dir = std::env::temp_dir();
        assert!(check_path(&dir)
            .unwrap_err()
            .to_string()
            .contains("it is a directory"));
        assert!(check_path(Path::new("relative.bvh")).is_ok());
        let e = save(&motion(), Format::C3d, Path::new("/nonexistent-dir/a.c3d")).unwrap_err();
        assert!(
            e.to_string()
                .starts_with("cannot write /nonexistent-dir/a.c3d: "),
            "{e}"
        );
    }

    #[test]
    fn save_writes_every_format() {
        let dir = std::env::temp_dir().join(format!("blapose-export-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        for (f, ext) in [
            (Format::Bvh, "bvh"),
            (Format::C3d, "c3d"),
            (Format::Trc, "trc"),
        ] {
            let path = dir.join(format!("a.{ext}"));
            let saved = save(&motion(), f, &path).unwrap();
            assert_eq!(saved.bytes, std::fs::metadata(&path).unwrap().len());
            assert_eq!(saved.bvh.is_some(), f == Format::Bvh);
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }
}

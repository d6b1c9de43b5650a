//! What the load test sends: the licence-clean example sequences in
//! `examples/*.npz`, read with the client crate's [`Sequence`] reader.
//!
//! Real recorded motion (walking, running, jumping) exercises the server the
//! way a camera does: plausible keypoints that pass validation, varied
//! layouts and image sizes across streams. Stream `i` replays sequence
//! `i % n`, cycling its frames; frame indices keep counting up so every
//! answer is distinct. The wire messages are built once here, so the load
//! generator spends its (shared) CPU on sending rather than on encoding.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use blapose_client::{InputFormat, Sequence, SequenceError, ToProto};
use blapose_proto::v1 as pb;

/// Why the workload could not be loaded.
#[derive(Debug, thiserror::Error)]
pub enum WorkloadError {
    /// The directory could not be listed.
    #[error("cannot read the example directory {path}: {source}")]
    Dir {
        /// The directory.
        path: PathBuf,
        /// The cause.
        #[source]
        source: std::io::Error,
    },
    /// The directory holds no `.npz` file.
    #[error("no .npz sequences in {0} (pass --examples DIR with replay files)")]
    Empty(PathBuf),
    /// A sequence file is malformed.
    #[error(transparent)]
    Sequence(#[from] SequenceError),
}

/// One sequence ready to send.
#[derive(Debug, Clone)]
pub struct Clip {
    /// File name, for the report.
    pub name: String,
    /// Layout and image size to open the session with.
    pub input_format: InputFormat,
    /// Every frame as its wire message (`frame_index` is set per send).
    pub frames: Arc<[pb::Frame]>,
}

impl Clip {
    /// A clip from a loaded sequence.
    pub fn from_sequence(name: impl Into<String>, seq: &Sequence) -> Self {
        Clip {
            name: name.into(),
            input_format: seq.input_format,
            frames: (0..seq.len()).map(|t| seq.frame(t).to_proto()).collect(),
        }
    }

    /// Frame `i` of an endless replay: frame `i % len` with index `i`.
    pub fn frame(&self, i: u64) -> pb::Frame {
        let mut f = self.frames[(i % self.frames.len() as u64) as usize].clone();
        f.frame_index = i;
        f
    }
}

/// The clips streams cycle through.
#[derive(Debug, Clone)]
pub struct Workload {
    /// At least one clip, each with at least one frame.
    pub clips: Vec<Clip>,
    /// Sessions ask for the causal motion stage.
    pub motion: bool,
}

impl Workload {
    /// Every `*.npz` in `dir`, in file-name order.
    pub fn from_dir(dir: &Path) -> Result<Self, WorkloadError> {
        let paths = replay_files(dir)?;
        let mut clips = Vec::with_capacity(paths.len());
        for path in paths {
            let seq = Sequence::load(&path, None)?;
            let name = path
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default();
            clips.push(Clip::from_sequence(name, &seq));
        }
        Ok(Workload {
            clips,
            motion: false,
        })
    }

    /// The clip stream `i` replays.
    pub fn clip(&self, stream: usize) -> &Clip {
        &self.clips[stream % self.clips.len()]
    }

    /// Total frames across clips.
    pub fn total_frames(&self) -> usize {
        self.clips.iter().map(|c| c.frames.len()).sum()
    }
}

/// Every `*.npz` in `dir`, in file-name order; at least one.
pub fn replay_files(dir: &Path) -> Result<Vec<PathBuf>, WorkloadError> {
    let entries = std::fs::read_dir(dir).map_err(|source| WorkloadError::Dir {
        path: dir.to_owned(),
        source,
    })?;
    let mut paths: Vec<PathBuf> = entries
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "npz"))
        .collect();
    if paths.is_empty() {
        return Err(WorkloadError::Empty(dir.to_owned()));
    }
    paths.sort();
    Ok(paths)
}

/// The workspace's `examples/` directory (where `cargo run` finds it).
pub fn default_examples_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../examples")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn loads_the_examples_and_cycles_frames() {
        let w = Workload::from_dir(&default_examples_dir()).unwrap();
        assert!(w.clips.len() >= 2);
        let clip = w.clip(0);
        let n = clip.frames.len() as u64;
        let f = clip.frame(n + 3);
        assert_eq!(f.frame_index, n + 3);
        assert_eq!(f.keypoints_2d, clip.frames[3].keypoints_2d);
        assert_eq!(f.pose_3d.len(), 17 * 3);
        // Streams are spread over the clips.
        assert_eq!(w.clip(1).name, w.clips[1].name);
        assert_eq!(w.clip(w.clips.len()).name, w.clips[0].name);
    }

    #[test]
    fn a_directory_without_sequences_is_a_clear_error() {
        let dir = std::env::temp_dir().join(format!("blapose-bench-empty-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let err = Workload::from_dir(&dir).unwrap_err();
        assert!(err.to_string().contains("no .npz"), "{err}");
        std::fs::remove_dir(&dir).unwrap();
        let err = Workload::from_dir(&dir).unwrap_err();
        assert!(
            err.to_string().contains(&dir.display().to_string()),
            "{err}"
        );
    }
}

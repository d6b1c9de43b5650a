//! Trained lifters as a server runs them: a weights file written by
//! `blapose train-lifter`, checked and turned into a [`TrainedLifter`] that
//! lifts one stream's frames as they arrive.
//!
//! Why this module exists: so far a client had to run its own lifter and
//! send the 3D pose with every frame. With a trained lifter the server can
//! do that itself, and a client needs nothing but a 2D detector. The weights
//! file says everything needed to rebuild the network (the trainer writes a
//! JSON [`LifterMetadata`] under the safetensors header key
//! [`METADATA_KEY`], its architecture a [`LifterArch`], and the tensors
//! under the reference VideoPose3D names that [`VideoPose3d::new`] loads),
//! so serving one takes no size flags.
//!
//! What is refused, each with its own [`TrainedLifterError`]: files without
//! the metadata, architectures other than VideoPose3D (the trainer's `mlp`
//! lifts single frames in a different network this crate does not have),
//! keypoint layouts other than Human3.6M-17, and *centred* models: their
//! pose for frame `t` needs the frames after `t`, which a live stream has
//! not sent yet. A causal model's pose belongs to the last frame of its
//! window, so each new frame is answered at once.
//!
//! Per stream, a [`SlidingWindow`] of [`TrainedLifter::receptive_field`]
//! frames holds the recent normalized keypoints (edge-padded at the start
//! of a stream, as the reference pads a sequence); [`TrainedLifter::lift`]
//! turns it into the newest frame's pose, and [`TrainedLifter::lift_windows`]
//! does many streams' windows in one batched call. Poses are root-relative
//! with the root (pelvis) exactly at 0, as the reference evaluation sets it
//! (a trained file's pelvis outputs are 0 anyway).

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};

use blapose_core::{Pose, NUM_JOINTS};
use candle_core::{DType, Device, Tensor};
use candle_nn::VarBuilder;
use serde::{Deserialize, Serialize};

use crate::error::LifterError;
use crate::{poses_from_tensor, Lifter, SlidingWindow, VideoPose3d};
use crate::{Result as LifterResult, INPUT_FEATURES};

/// The architecture types the metadata records (defined in [`crate::arch`]).
pub use crate::arch::{LifterArch, MlpArch, VideoPoseArch};

/// Safetensors header key of the lifter metadata JSON (the trainer's
/// `blapose_train::lifter::weights::METADATA_KEY`).
pub const METADATA_KEY: &str = "blapose_lifter";

/// The keypoint layout a served lifter must have been trained on: the
/// Human3.6M-17 order the server converts every client layout to.
pub const KEYPOINT_LAYOUT: &str = "h36m17";

/// Largest receptive field accepted (frames): every session of a server
/// holds a window this long, so a file asking for more is refused rather
/// than trusted. The reference's largest model has 243.
pub const MAX_RECEPTIVE_FIELD: usize = 4096;

/// Values of one window frame (17 joints x 2).
pub const FRAME_VALUES: usize = NUM_JOINTS * INPUT_FEATURES;

/// Why a lifter weights file cannot be served.
#[derive(Debug, thiserror::Error)]
pub enum TrainedLifterError {
    /// The file could not be read.
    #[error("cannot read {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The cause.
        #[source]
        source: std::io::Error,
    },
    /// The bytes are not a safetensors file.
    #[error("not a safetensors file: {0}")]
    Format(String),
    /// The header has no lifter metadata.
    #[error("no {METADATA_KEY:?} metadata in the safetensors header (not a lifter weights file written by `blapose train-lifter`?)")]
    MissingMetadata,
    /// The metadata is not the JSON the trainer writes.
    #[error("invalid {METADATA_KEY:?} metadata: {0}")]
    BadMetadata(String),
    /// An architecture this crate cannot serve.
    #[error("the lifter is a {model:?}, which cannot be served: only videopose (temporal convolution) lifters can")]
    UnsupportedArch {
        /// The architecture's `model` name.
        model: String,
    },
    /// A centred model, which needs future frames.
    #[error("{name} is a centred lifter: its pose for a frame needs the {future} frames after it, which a live stream has not sent yet; serve a causal one (`blapose train-lifter --model videopose --causal`)")]
    NotCausal {
        /// The lifter's name.
        name: String,
        /// Frames after the output frame in its window.
        future: usize,
    },
    /// A size the network cannot have or the server will not hold.
    #[error("invalid lifter size: {0}")]
    Size(String),
    /// Trained on keypoints in another joint order.
    #[error("the lifter was trained on {0:?} keypoints; the server feeds {KEYPOINT_LAYOUT} (Human3.6M-17, normalized screen coordinates)")]
    KeypointLayout(String),
    /// The tensors do not build the network the metadata describes
    /// (missing tensors, wrong shapes), or running it failed.
    #[error("lifter weights: {0}")]
    Weights(#[from] LifterError),
}

impl From<candle_core::Error> for TrainedLifterError {
    fn from(e: candle_core::Error) -> Self {
        Self::Weights(LifterError::Candle(e))
    }
}

/// Result alias for this module.
pub type Result<T> = std::result::Result<T, TrainedLifterError>;

/// The receptive field of `arch` if a server can hold and build it: an odd
/// filter width, channels, and at most [`MAX_RECEPTIVE_FIELD`] frames.
fn servable_receptive_field(arch: &VideoPoseArch) -> Result<usize> {
    let rf = arch.receptive_field().filter(|&r| r <= MAX_RECEPTIVE_FIELD);
    let rf = rf.ok_or_else(|| {
        TrainedLifterError::Size(format!(
            "filter width {} and {} blocks give a receptive field over {MAX_RECEPTIVE_FIELD} frames",
            arch.filter_width, arch.blocks
        ))
    })?;
    if arch.filter_width.is_multiple_of(2) || arch.channels == 0 {
        return Err(TrainedLifterError::Size(format!(
            "filter width must be odd and channels > 0, got width {} and {} channels",
            arch.filter_width, arch.channels
        )));
    }
    Ok(rf)
}

/// Provenance and conventions of a lifter weights file: the trainer
/// writes it and the server and the evaluation read it back, one struct
/// over one [`LifterArch`], so the two sides cannot drift apart.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LifterMetadata {
    /// Architecture and size.
    pub arch: LifterArch,
    /// 2D input layout (`h36m17`).
    pub keypoint_layout: String,
    /// How pixels were normalized.
    pub input_normalization: String,
    /// What the outputs are.
    pub output: String,
    /// Free text: subjects, detections, augmentation.
    pub training_data: String,
    /// Optimizer steps trained.
    pub train_steps: u64,
    /// Further key/value pairs (training configuration, timings, ...).
    #[serde(default)]
    pub extra: BTreeMap<String, String>,
}

impl LifterMetadata {
    /// Flat key/value pairs for display (e.g. a server's ModelInfo):
    /// `arch` as JSON, the named fields, and `extra.*`.
    pub fn to_pairs(&self) -> BTreeMap<String, String> {
        let mut out = BTreeMap::new();
        let arch = serde_json::to_string(&self.arch).unwrap_or_else(|e| e.to_string());
        out.insert("arch".to_string(), arch);
        out.insert("keypoint_layout".to_string(), self.keypoint_layout.clone());
        out.insert(
            "input_normalization".to_string(),
            self.input_normalization.clone(),
        );
        out.insert("output".to_string(), self.output.clone());
        out.insert("training_data".to_string(), self.training_data.clone());
        out.insert("train_steps".to_string(), self.train_steps.to_string());
        for (k, v) in &self.extra {
            out.insert(format!("extra.{k}"), v.clone());
        }
        out
    }
}

/// The lifter metadata of a weights file, without loading its tensors.
pub fn read_metadata(bytes: &[u8]) -> Result<LifterMetadata> {
    let (_, header) = safetensors::SafeTensors::read_metadata(bytes)
        .map_err(|e| TrainedLifterError::Format(e.to_string()))?;
    let json = header
        .metadata()
        .as_ref()
        .and_then(|m| m.get(METADATA_KEY))
        .ok_or(TrainedLifterError::MissingMetadata)?;
    serde_json::from_str(json).map_err(|e| TrainedLifterError::BadMetadata(e.to_string()))
}

/// The keypoint layout name without case, `-` or `_` (`H36M-17` is `h36m17`).
fn canonical_layout(name: &str) -> String {
    name.chars()
        .filter(|c| !matches!(c, '-' | '_' | ' '))
        .flat_map(char::to_lowercase)
        .collect()
}

/// A trained causal VideoPose3D lifter, ready to lift streams online.
pub struct TrainedLifter {
    model: VideoPose3d,
    arch: VideoPoseArch,
    metadata: LifterMetadata,
    name: String,
    receptive_field: usize,
}

impl std::fmt::Debug for TrainedLifter {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TrainedLifter")
            .field("name", &self.name)
            .field("params", &self.params())
            .field("metadata", &self.metadata)
            .finish()
    }
}

impl TrainedLifter {
    /// Load a weights file written by `blapose train-lifter`.
    pub fn from_file(path: &Path) -> Result<Self> {
        let bytes = std::fs::read(path).map_err(|source| TrainedLifterError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        Self::from_bytes(&bytes)
    }

    /// Load the bytes of a weights file written by `blapose train-lifter`:
    /// check its metadata (a causal videopose lifter on Human3.6M-17
    /// keypoints), then build the network from its tensors.
    pub fn from_bytes(bytes: &[u8]) -> Result<Self> {
        let metadata = read_metadata(bytes)?;
        let arch = match metadata.arch {
            LifterArch::VideoPose(a) => a,
            other => {
                return Err(TrainedLifterError::UnsupportedArch {
                    model: other.model().to_string(),
                })
            }
        };
        let receptive_field = servable_receptive_field(&arch)?;
        let name = arch.name();
        if !arch.causal {
            return Err(TrainedLifterError::NotCausal {
                name,
                future: receptive_field / 2,
            });
        }
        if canonical_layout(&metadata.keypoint_layout) != KEYPOINT_LAYOUT {
            return Err(TrainedLifterError::KeypointLayout(
                metadata.keypoint_layout.clone(),
            ));
        }
        let tensors = candle_core::safetensors::load_buffer(bytes, &Device::Cpu)
            .map_err(|e| TrainedLifterError::Format(e.to_string()))?;
        let vb = VarBuilder::from_tensors(tensors, DType::F32, &Device::Cpu);
        let model = VideoPose3d::new(arch.config(), vb)?;
        Ok(Self {
            model,
            arch,
            metadata,
            name,
            receptive_field,
        })
    }

    /// Short name, e.g. `videopose27-causal` (as the trainer names it).
    pub fn name(&self) -> &str {
        &self.name
    }

    /// Frames in one input window.
    pub fn receptive_field(&self) -> usize {
        self.receptive_field
    }

    /// Trainable parameters (batch-norm running statistics excluded).
    pub fn params(&self) -> usize {
        self.model.params()
    }

    /// The architecture.
    pub fn arch(&self) -> &VideoPoseArch {
        &self.arch
    }

    /// The file's metadata (training provenance and conventions).
    pub fn metadata(&self) -> &LifterMetadata {
        &self.metadata
    }

    /// The network.
    pub fn model(&self) -> &VideoPose3d {
        &self.model
    }

    /// An empty window for one stream.
    pub fn window(&self) -> SlidingWindow {
        SlidingWindow::new(self.receptive_field)
    }

    /// The pose of the newest frame in `window` (one of [`Self::window`]'s,
    /// with at least one frame pushed), root at 0.
    pub fn lift(&self, window: &mut SlidingWindow) -> LifterResult<Pose> {
        let shape_error = |got: Vec<usize>| LifterError::Shape {
            what: "lifter window",
            expected: format!(
                "({}, {NUM_JOINTS}, {INPUT_FEATURES}) with at least one frame pushed",
                self.receptive_field
            ),
            got,
        };
        if window.frames() != self.receptive_field {
            return Err(shape_error(vec![
                window.frames(),
                NUM_JOINTS,
                INPUT_FEATURES,
            ]));
        }
        let x = window
            .tensor()?
            .ok_or_else(|| shape_error(vec![0, NUM_JOINTS, INPUT_FEATURES]))?;
        let mut poses = self.forward(&x)?;
        poses.pop().ok_or_else(|| shape_error(x.dims().to_vec()))
    }

    /// The newest frame's pose of each of `batch` windows, given as
    /// `batch x receptive_field x 17 x 2` values (windows one after the
    /// other, each oldest frame first, e.g. from
    /// [`SlidingWindow::extend_with_next`]); roots at 0.
    pub fn lift_windows(&self, windows: &[f32], batch: usize) -> LifterResult<Vec<Pose>> {
        let per_window = self.receptive_field * FRAME_VALUES;
        if batch == 0 || windows.len() != batch * per_window {
            return Err(LifterError::Shape {
                what: "lifter windows",
                expected: format!(
                    "({batch} > 0 windows) x {} frames x {NUM_JOINTS} x {INPUT_FEATURES} = {} values",
                    self.receptive_field,
                    batch * per_window
                ),
                got: vec![windows.len()],
            });
        }
        let x = Tensor::from_slice(
            windows,
            (batch, self.receptive_field, NUM_JOINTS, INPUT_FEATURES),
            &Device::Cpu,
        )?;
        self.forward(&x)
    }

    fn forward(&self, x: &Tensor) -> LifterResult<Vec<Pose>> {
        let mut poses = poses_from_tensor(&self.model.forward_window(x)?)?;
        for p in &mut poses {
            p[0] = [0.0; 3];
        }
        Ok(poses)
    }
}

/// Serialize `tensors` and `metadata` as a lifter weights file (the format
/// `blapose train-lifter` writes).
pub fn weights_file_bytes(
    tensors: &HashMap<String, Tensor>,
    metadata: &LifterMetadata,
) -> Result<Vec<u8>> {
    let json = serde_json::to_string(metadata)
        .map_err(|e| TrainedLifterError::BadMetadata(e.to_string()))?;
    let header = HashMap::from([(METADATA_KEY.to_string(), json)]);
    let mut named: Vec<(&str, &Tensor)> = tensors.iter().map(|(k, v)| (k.as_str(), v)).collect();
    named.sort_by_key(|(k, _)| *k);
    safetensors::serialize(named, Some(header))
        .map_err(|e| TrainedLifterError::Format(e.to_string()))
}

/// Metadata for a file of random weights (see [`random_tensors`]).
pub fn random_metadata(arch: VideoPoseArch, seed: u64) -> LifterMetadata {
    LifterMetadata {
        arch: LifterArch::VideoPose(arch),
        keypoint_layout: KEYPOINT_LAYOUT.to_string(),
        input_normalization: "screen: u = x/w*2-1, v = y/w*2-h/w".to_string(),
        output: "16 joints (H36M-17 order without the pelvis, which is fixed at 0), root-relative camera space, metres".to_string(),
        training_data: format!("none: random weights (seed {seed}) for tests"),
        train_steps: 0,
        extra: BTreeMap::new(),
    }
}

/// Every tensor of a VideoPose3D of size `arch` with random weights
/// ([`RandomInit::perturbed`]: batch-norm statistics too), under the
/// reference names, with the pelvis rows of `shrink` zeroed as in a trained
/// file. For tests and benchmarks that need a weights file.
pub fn random_tensors(arch: VideoPoseArch, seed: u64) -> Result<HashMap<String, Tensor>> {
    servable_receptive_field(&arch)?;
    let (_, mut tensors) =
        crate::init::record_random(seed, |vb| VideoPose3d::new(arch.config(), vb))?;
    for name in ["shrink.weight", "shrink.bias"] {
        if let Some(t) = tensors.get(name) {
            let rows = t.dim(0)?;
            let zero = t.narrow(0, 0, 3)?.zeros_like()?;
            let zeroed = Tensor::cat(&[&zero, &t.narrow(0, 3, rows - 3)?], 0)?;
            tensors.insert(name.to_string(), zeroed);
        }
    }
    Ok(tensors)
}

/// A complete weights file of random weights ([`random_tensors`],
/// [`random_metadata`]).
pub fn random_weights_file(arch: VideoPoseArch, seed: u64) -> Result<Vec<u8>> {
    weights_file_bytes(&random_tensors(arch, seed)?, &random_metadata(arch, seed))
}

#[cfg(test)]
mod tests {
    use super::*;
    use blapose_core::Keypoints2d;

    fn small(causal: bool) -> VideoPoseArch {
        VideoPoseArch {
            filter_width: 3,
            blocks: 1,
            channels: 16,
            dropout: 0.25,
            causal,
        }
    }

    fn frame(t: usize) -> Keypoints2d {
        std::array::from_fn(|j| {
            let a = 0.3 * t as f32 + 0.7 * j as f32;
            [0.4 * a.sin(), 0.3 * a.cos() - 0.1]
        })
    }

    fn refusal(bytes: &[u8]) -> TrainedLifterError {
        match TrainedLifter::from_bytes(bytes) {
            Ok(l) => panic!("{} was accepted", l.name()),
            Err(e) => e,
        }
    }

    #[test]
    fn a_causal_videopose_file_loads_and_lifts_like_the_network() {
        let bytes = random_weights_file(small(true), 3).unwrap();
        let lifter = TrainedLifter::from_bytes(&bytes).unwrap();
        assert_eq!(lifter.name(), "videopose9-causal");
        assert_eq!(lifter.receptive_field(), 9);
        // expand (16 x 34 x 3) + 1 block (16 x 16 x 3 + 16 x 16) + 3 batch
        // norms (2 x 16 each) + shrink (51 x 16 + 51).
        assert_eq!(lifter.params(), 1632 + 768 + 256 + 3 * 32 + 816 + 51);
        assert_eq!(lifter.metadata().train_steps, 0);
        assert!(lifter.metadata().to_pairs()["arch"].contains("\"causal\":true"));

        // The same tensors loaded straight into the network give the same
        // poses on the same window; the root is exactly 0.
        let tensors = candle_core::safetensors::load_buffer(&bytes, &Device::Cpu).unwrap();
        let vb = VarBuilder::from_tensors(tensors, DType::F32, &Device::Cpu);
        let net = VideoPose3d::new(small(true).config(), vb).unwrap();
        let mut window = lifter.window();
        for t in 0..12 {
            window.push(frame(t));
            let got = lifter.lift(&mut window).unwrap();
            let want = poses_from_tensor(
                &net.forward_window(&window.tensor().unwrap().unwrap())
                    .unwrap(),
            )
            .unwrap()
            .remove(0);
            assert_eq!(got[0], [0.0; 3]);
            assert_eq!(want[0], [0.0; 3], "trained-like pelvis rows are zero");
            assert_eq!(got, want, "frame {t}");
            assert!(got.iter().flatten().all(|v| v.is_finite()));
        }
    }

    #[test]
    fn batched_windows_match_one_by_one_and_bad_shapes_are_errors() {
        let lifter =
            TrainedLifter::from_bytes(&random_weights_file(small(true), 4).unwrap()).unwrap();
        let mut windows = Vec::new();
        let mut singles = Vec::new();
        for s in 0..3 {
            let mut w = lifter.window();
            for t in 0..(2 + 5 * s) {
                w.push(frame(t + 11 * s));
            }
            let next = frame(100 + s);
            w.extend_with_next(&next, &mut windows);
            w.push(next);
            singles.push(lifter.lift(&mut w).unwrap());
        }
        let batched = lifter.lift_windows(&windows, 3).unwrap();
        for (a, b) in batched.iter().zip(&singles) {
            for (u, v) in a.iter().flatten().zip(b.iter().flatten()) {
                assert!((u - v).abs() < 1e-5, "{u} vs {v}");
            }
        }
        assert!(lifter.lift_windows(&windows[1..], 3).is_err());
        assert!(lifter.lift_windows(&[], 0).is_err());
        assert!(lifter.lift(&mut lifter.window()).is_err(), "empty window");
        assert!(
            lifter.lift(&mut SlidingWindow::new(4)).is_err(),
            "wrong length"
        );
    }

    #[test]
    fn the_root_is_zero_even_when_the_pelvis_rows_are_not() {
        let mut tensors = random_tensors(small(true), 5).unwrap();
        let bias = Tensor::ones(51, DType::F32, &Device::Cpu).unwrap();
        tensors.insert("shrink.bias".into(), bias);
        let bytes = weights_file_bytes(&tensors, &random_metadata(small(true), 5)).unwrap();
        let lifter = TrainedLifter::from_bytes(&bytes).unwrap();
        let mut w = lifter.window();
        w.push(frame(0));
        assert_eq!(lifter.lift(&mut w).unwrap()[0], [0.0; 3]);
    }

    #[test]
    fn centred_mlp_and_foreign_files_are_refused_with_their_reason() {
        let centred = random_weights_file(small(false), 1).unwrap();
        let e = refusal(&centred);
        assert!(
            matches!(&e, TrainedLifterError::NotCausal { name, future: 4 } if name == "videopose9"),
            "{e}"
        );
        assert!(e.to_string().contains("--causal"), "{e}");

        let tensors = random_tensors(small(true), 1).unwrap();
        let mut meta = random_metadata(small(true), 1);
        meta.arch = LifterArch::Mlp(MlpArch {
            hidden: 1024,
            blocks: 2,
            dropout: 0.5,
        });
        let e = refusal(&weights_file_bytes(&tensors, &meta).unwrap());
        assert!(
            matches!(&e, TrainedLifterError::UnsupportedArch { model } if model == "mlp"),
            "{e}"
        );

        let mut meta = random_metadata(small(true), 1);
        meta.keypoint_layout = "coco17".into();
        let e = refusal(&weights_file_bytes(&tensors, &meta).unwrap());
        assert!(matches!(e, TrainedLifterError::KeypointLayout(_)), "{e}");
        meta.keypoint_layout = "H36M-17".into();
        assert!(TrainedLifter::from_bytes(&weights_file_bytes(&tensors, &meta).unwrap()).is_ok());

        // No metadata at all (e.g. a bone-length model's file).
        let mut named: Vec<(&str, &Tensor)> =
            tensors.iter().map(|(k, v)| (k.as_str(), v)).collect();
        named.sort_by_key(|(k, _)| *k);
        let bare = safetensors::serialize(named.clone(), None).unwrap();
        assert!(matches!(
            refusal(&bare),
            TrainedLifterError::MissingMetadata
        ));
        let other = HashMap::from([("blapose".to_string(), "{}".to_string())]);
        let foreign = safetensors::serialize(named, Some(other)).unwrap();
        assert!(matches!(
            refusal(&foreign),
            TrainedLifterError::MissingMetadata
        ));

        // Metadata that is not the trainer's JSON; an unknown architecture.
        let bad = HashMap::from([(METADATA_KEY.to_string(), "{\"arch\":".to_string())]);
        let mut named: Vec<(&str, &Tensor)> =
            tensors.iter().map(|(k, v)| (k.as_str(), v)).collect();
        named.sort_by_key(|(k, _)| *k);
        let e = refusal(&safetensors::serialize(named.clone(), Some(bad)).unwrap());
        assert!(matches!(e, TrainedLifterError::BadMetadata(_)), "{e}");
        let json = serde_json::to_string(&random_metadata(small(true), 1))
            .unwrap()
            .replace("\"videopose\"", "\"poseformer\"");
        let unknown = HashMap::from([(METADATA_KEY.to_string(), json)]);
        let e = refusal(&safetensors::serialize(named, Some(unknown)).unwrap());
        assert!(e.to_string().contains("poseformer"), "{e}");

        // Not safetensors; not readable.
        assert!(matches!(
            refusal(b"not weights"),
            TrainedLifterError::Format(_)
        ));
        let missing = std::env::temp_dir().join("blapose-no-such-lifter.safetensors");
        let e = TrainedLifter::from_file(&missing).unwrap_err();
        assert!(matches!(e, TrainedLifterError::Io { .. }), "{e}");
    }

    #[test]
    fn sizes_and_tensors_must_agree_with_the_metadata() {
        // The metadata says 32 channels, the tensors have 16.
        let tensors = random_tensors(small(true), 2).unwrap();
        let mut wide = small(true);
        wide.channels = 32;
        let e = refusal(&weights_file_bytes(&tensors, &random_metadata(wide, 2)).unwrap());
        assert!(matches!(e, TrainedLifterError::Weights(_)), "{e}");
        // A missing tensor.
        let mut partial = tensors.clone();
        partial.remove("layers_bn.1.running_var");
        let e = refusal(&weights_file_bytes(&partial, &random_metadata(small(true), 2)).unwrap());
        assert!(e.to_string().contains("running_var"), "{e}");
        // Absurd sizes are refused before anything is allocated.
        for (width, blocks) in [(2, 1), (3, 40), (3, usize::MAX)] {
            let mut a = small(true);
            a.filter_width = width;
            a.blocks = blocks;
            let e = refusal(&weights_file_bytes(&tensors, &random_metadata(a, 2)).unwrap());
            assert!(
                matches!(e, TrainedLifterError::Size(_)),
                "{width} {blocks}: {e}"
            );
        }
    }

    /// The shipped lifter files' metadata parses into [`LifterMetadata`]
    /// and writes back byte for byte (the trainer writes it with the same
    /// types); the causal one serves. Skips where `models/` is absent.
    #[test]
    fn shipped_metadata_round_trips_byte_for_byte() {
        let models = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../models");
        let mut seen = 0;
        for entry in std::fs::read_dir(&models).into_iter().flatten() {
            let path = entry.unwrap().path();
            let name = path.file_name().unwrap().to_string_lossy().into_owned();
            if !(name.starts_with("lifter_") && name.ends_with(".safetensors")) {
                continue;
            }
            let bytes = std::fs::read(&path).unwrap();
            let (_, header) = safetensors::SafeTensors::read_metadata(&bytes).unwrap();
            let json = &header.metadata().as_ref().unwrap()[METADATA_KEY];
            let metadata = read_metadata(&bytes).unwrap();
            assert_eq!(&serde_json::to_string(&metadata).unwrap(), json, "{name}");
            if name.contains("causal") {
                let lifter = TrainedLifter::from_bytes(&bytes).unwrap();
                assert_eq!(lifter.name(), "videopose27-causal");
            }
            seen += 1;
        }
        if seen == 0 {
            println!("skipping: no lifter files in {}", models.display());
        }
    }

    #[test]
    fn a_file_on_disk_loads() {
        let path = std::env::temp_dir().join(format!(
            "blapose-lifters-trained-{}.safetensors",
            std::process::id()
        ));
        std::fs::write(&path, random_weights_file(small(true), 6).unwrap()).unwrap();
        let lifter = TrainedLifter::from_file(&path);
        let _ = std::fs::remove_file(&path);
        assert_eq!(lifter.unwrap().receptive_field(), 9);
    }
}

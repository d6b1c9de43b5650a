//! Human3.6M in the layout of `../shared/data/h36m`.
//!
//! - `poses_3d.npz`: key `S{n}/{action}` -> `(T, 17, 3)` world coordinates,
//!   metres, 50 Hz.
//! - `detections_sh.npz`: key `S{n}/{action}/{camera}` -> `(T, 16, 2)`
//!   Stacked Hourglass detections in pixels (layout
//!   [`blapose_core::layouts::KeypointLayout::Sh16`]).
//! - `cameras.json`: per subject and camera id, the calibration used by
//!   [`blapose_core::camera::Camera`].
//!
//! `detections_sh.npz` also holds the five sequences whose 3D poses are
//! missing (S5 Discussion 2/3, S7 Discussion, S7 SittingDown 1, S9
//! Discussion 1), and S11 Directions has no detections from camera 54138969
//! (its video is corrupt in Human3.6M): pair the two by key, never by
//! position. NaN or infinite values are rejected at load time
//! ([`H36mError::NonFinite`]).
//!
//! Action names contain spaces (`Walking 1`), never `/`, so keys split on
//! `/` unambiguously. Loaders take a subject list so a test or tool can load
//! one subject without paying for all seven.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use blapose_core::camera::{Camera, CameraError};
use blapose_core::Pose;
use serde::Deserialize;

use crate::npz::{read_npz_filtered, NpzError};

/// The standard training subjects (protocol of Martinez et al./VideoPose3D).
pub const TRAIN_SUBJECTS: [&str; 5] = ["S1", "S5", "S6", "S7", "S8"];
/// The standard test subjects.
pub const TEST_SUBJECTS: [&str; 2] = ["S9", "S11"];
/// All annotated subjects.
pub const ALL_SUBJECTS: [&str; 7] = ["S1", "S5", "S6", "S7", "S8", "S9", "S11"];

/// 3D poses, relative to the data root.
pub const POSES_FILE: &str = "h36m/poses_3d.npz";
/// Stacked Hourglass detections, relative to the data root.
pub const DETECTIONS_FILE: &str = "h36m/detections_sh.npz";
/// Camera calibration, relative to the data root.
pub const CAMERAS_FILE: &str = "h36m/cameras.json";

/// One frame of Stacked Hourglass detections (SH16 order, pixels).
pub type ShKeypoints = [[f32; 2]; 16];
/// `subject -> action -> frames`.
pub type PosesBySubject = BTreeMap<String, BTreeMap<String, Vec<Pose>>>;
/// `subject -> action -> camera id -> frames`.
pub type DetectionsBySubject =
    BTreeMap<String, BTreeMap<String, BTreeMap<String, Vec<ShKeypoints>>>>;

/// Why Human3.6M data could not be loaded.
#[derive(Debug, thiserror::Error)]
pub enum H36mError {
    /// Reading an npz file failed.
    #[error(transparent)]
    Npz(#[from] NpzError),
    /// A file could not be read.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        #[source]
        source: std::io::Error,
    },
    /// `cameras.json` is not valid JSON of the expected structure.
    #[error("{path}: malformed cameras JSON: {source}")]
    Json {
        /// The file.
        path: PathBuf,
        /// The parse error (names the line, column and field).
        #[source]
        source: serde_json::Error,
    },
    /// A camera's calibration is invalid.
    #[error("subject {subject}: {source}")]
    Camera {
        /// Subject.
        subject: String,
        /// The problem.
        #[source]
        source: CameraError,
    },
    /// `cameras.json` lists joint names other than the ones blapose uses.
    #[error("cameras.json: {list} is {found:?}, expected {expected:?}")]
    JointOrder {
        /// Which list (`joints_17` or `sh_16`).
        list: &'static str,
        /// What the file says.
        found: Vec<String>,
        /// What blapose expects.
        expected: Vec<&'static str>,
    },
    /// An array holds NaN or infinite values.
    #[error("{file}: array {key:?} has a non-finite value in frame {frame}")]
    NonFinite {
        /// The file.
        file: &'static str,
        /// The array's key.
        key: String,
        /// First frame with a non-finite value.
        frame: usize,
    },
    /// A key does not have the `S{n}/{action}[/{camera}]` form.
    #[error("{file}: malformed key {key:?} (expected {expected})")]
    BadKey {
        /// The file.
        file: &'static str,
        /// The key.
        key: String,
        /// The expected form.
        expected: &'static str,
    },
}

#[derive(Deserialize)]
struct RawCameraFile {
    joints_17: Vec<String>,
    sh_16: Vec<String>,
    fps: f64,
    cameras: BTreeMap<String, BTreeMap<String, RawCamera>>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawCamera {
    #[serde(rename = "R")]
    rotation: [[f64; 3]; 3],
    center: [f64; 3],
    focal: [f64; 2],
    principal: [f64; 2],
    k: [f64; 3],
    p: [f64; 2],
    res: [u32; 2],
}

/// The calibration of every subject's cameras.
#[derive(Debug, Clone, PartialEq)]
pub struct CameraSet {
    /// Frame rate of the sequences (50).
    pub fps: f64,
    /// Cameras per subject, sorted by camera id.
    pub by_subject: BTreeMap<String, Vec<Camera>>,
}

impl CameraSet {
    /// A subject's cameras (sorted by id).
    pub fn subject(&self, subject: &str) -> Option<&[Camera]> {
        self.by_subject.get(subject).map(Vec::as_slice)
    }

    /// One camera by subject and id.
    pub fn get(&self, subject: &str, id: &str) -> Option<&Camera> {
        self.subject(subject)?.iter().find(|c| c.id == id)
    }
}

/// Parse the text of `cameras.json` (validating every camera and the joint
/// orders). `path` is only used in error messages.
pub fn parse_cameras(json: &str, path: &Path) -> Result<CameraSet, H36mError> {
    let raw: RawCameraFile = serde_json::from_str(json).map_err(|source| H36mError::Json {
        path: path.to_owned(),
        source,
    })?;
    let expect = |list, found: &Vec<String>, expected: &[&'static str]| {
        if found
            .iter()
            .map(String::as_str)
            .eq(expected.iter().copied())
        {
            Ok(())
        } else {
            Err(H36mError::JointOrder {
                list,
                found: found.clone(),
                expected: expected.to_vec(),
            })
        }
    };
    expect(
        "joints_17",
        &raw.joints_17,
        &blapose_core::skeleton::JOINT_NAMES,
    )?;
    expect("sh_16", &raw.sh_16, &blapose_core::layouts::SH16_JOINTS)?;
    let mut by_subject = BTreeMap::new();
    for (subject, cams) in raw.cameras {
        let mut list = Vec::with_capacity(cams.len());
        for (id, c) in cams {
            let cam = Camera {
                id,
                rotation: c.rotation,
                center: c.center,
                focal: c.focal,
                principal: c.principal,
                radial: c.k,
                tangential: c.p,
                width: c.res[0],
                height: c.res[1],
            };
            cam.validate().map_err(|source| H36mError::Camera {
                subject: subject.clone(),
                source,
            })?;
            list.push(cam);
        }
        by_subject.insert(subject, list);
    }
    Ok(CameraSet {
        fps: raw.fps,
        by_subject,
    })
}

/// Load `h36m/cameras.json` under the data root.
pub fn load_cameras(root: &Path) -> Result<CameraSet, H36mError> {
    let path = root.join(CAMERAS_FILE);
    let text = std::fs::read_to_string(&path).map_err(|source| H36mError::Io {
        path: path.clone(),
        source,
    })?;
    parse_cameras(&text, &path)
}

fn subject_of(key: &str) -> &str {
    key.split('/').next().unwrap_or("")
}

fn check_finite<const J: usize, const D: usize>(
    file: &'static str,
    key: &str,
    frames: &[[[f32; D]; J]],
) -> Result<(), H36mError> {
    match frames
        .iter()
        .position(|f| !f.as_flattened().iter().all(|v| v.is_finite()))
    {
        Some(frame) => Err(H36mError::NonFinite {
            file,
            key: key.to_owned(),
            frame,
        }),
        None => Ok(()),
    }
}

/// Load the 3D sequences of `subjects` (e.g. [`TRAIN_SUBJECTS`]) from
/// `h36m/poses_3d.npz` under the data root.
pub fn load_poses(root: &Path, subjects: &[&str]) -> Result<PosesBySubject, H36mError> {
    let npz = read_npz_filtered(root.join(POSES_FILE), |k| subjects.contains(&subject_of(k)))?;
    let mut out = PosesBySubject::new();
    for (key, _) in npz.iter() {
        let Some((subject, action)) = key
            .split_once('/')
            .filter(|(_, a)| !a.is_empty() && !a.contains('/'))
        else {
            return Err(H36mError::BadKey {
                file: POSES_FILE,
                key: key.to_owned(),
                expected: "S{n}/{action}",
            });
        };
        let poses = npz.poses(key)?;
        check_finite(POSES_FILE, key, &poses)?;
        out.entry(subject.to_owned())
            .or_default()
            .insert(action.to_owned(), poses);
    }
    Ok(out)
}

/// Load the Stacked Hourglass detections of `subjects` from
/// `h36m/detections_sh.npz` under the data root.
pub fn load_detections(root: &Path, subjects: &[&str]) -> Result<DetectionsBySubject, H36mError> {
    let npz = read_npz_filtered(root.join(DETECTIONS_FILE), |k| {
        subjects.contains(&subject_of(k))
    })?;
    let mut out = DetectionsBySubject::new();
    for (key, _) in npz.iter() {
        let parts: Vec<&str> = key.split('/').collect();
        let [subject, action, camera] = parts[..] else {
            return Err(H36mError::BadKey {
                file: DETECTIONS_FILE,
                key: key.to_owned(),
                expected: "S{n}/{action}/{camera}",
            });
        };
        let frames = npz.frames::<16, 2>(key)?;
        check_finite(DETECTIONS_FILE, key, &frames)?;
        out.entry(subject.to_owned())
            .or_default()
            .entry(action.to_owned())
            .or_default()
            .insert(camera.to_owned(), frames);
    }
    Ok(out)
}

/// What [`H36m::load`] reads besides the cameras.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Parts {
    /// Load `poses_3d.npz`.
    pub poses: bool,
    /// Load `detections_sh.npz`.
    pub detections: bool,
}

impl Parts {
    /// Poses and detections.
    pub const ALL: Parts = Parts {
        poses: true,
        detections: true,
    };
    /// Poses only.
    pub const POSES: Parts = Parts {
        poses: true,
        detections: false,
    };
}

/// Human3.6M for a set of subjects: cameras, 3D sequences, detections.
#[derive(Debug, Clone)]
pub struct H36m {
    /// Camera calibration (all subjects).
    pub cameras: CameraSet,
    /// 3D sequences, `subject -> action -> frames` (world, metres).
    pub poses: PosesBySubject,
    /// Detections, `subject -> action -> camera -> frames` (pixels, SH16).
    pub detections: DetectionsBySubject,
}

impl H36m {
    /// Load the cameras and the requested parts for `subjects`.
    pub fn load(root: &Path, subjects: &[&str], parts: Parts) -> Result<Self, H36mError> {
        let cameras = load_cameras(root)?;
        let poses = if parts.poses {
            load_poses(root, subjects)?
        } else {
            PosesBySubject::new()
        };
        let detections = if parts.detections {
            load_detections(root, subjects)?
        } else {
            DetectionsBySubject::new()
        };
        Ok(Self {
            cameras,
            poses,
            detections,
        })
    }

    /// Every loaded 3D sequence as `(subject, action, frames)`.
    pub fn sequences(&self) -> impl Iterator<Item = (&str, &str, &[Pose])> {
        self.poses.iter().flat_map(|(s, acts)| {
            acts.iter()
                .map(move |(a, p)| (s.as_str(), a.as_str(), p.as_slice()))
        })
    }

    /// One 3D sequence.
    pub fn sequence(&self, subject: &str, action: &str) -> Option<&[Pose]> {
        self.poses.get(subject)?.get(action).map(Vec::as_slice)
    }

    /// Detections of one sequence seen by one camera.
    pub fn detections(&self, subject: &str, action: &str, camera: &str) -> Option<&[ShKeypoints]> {
        self.detections
            .get(subject)?
            .get(action)?
            .get(camera)
            .map(Vec::as_slice)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const GOOD: &str = r#"{"joints_17": ["pelvis","r_hip","r_knee","r_ankle","l_hip","l_knee","l_ankle","spine","thorax","neck_nose","head","l_shoulder","l_elbow","l_wrist","r_shoulder","r_elbow","r_wrist"],
      "sh_16": ["r_ankle","r_knee","r_hip","l_hip","l_knee","l_ankle","pelvis","spine","thorax","head","r_wrist","r_elbow","r_shoulder","l_shoulder","l_elbow","l_wrist"],
      "fps": 50, "units": "m",
      "cameras": {"S9": {"1": {"R": [[1,0,0],[0,1,0],[0,0,1]], "center": [0,0,-5], "focal": [1000,1000],
                               "principal": [500,500], "k": [0,0,0], "p": [0,0], "res": [1000,1000]}}}}"#;

    #[test]
    fn parses_a_minimal_file() {
        let set = parse_cameras(GOOD, Path::new("x.json")).unwrap();
        let cam = set.get("S9", "1").unwrap();
        assert_eq!(cam.project_world_to_pixels([0.5, 0.0, 0.0]), [600.0, 500.0]);
        assert_eq!(set.fps, 50.0);
        assert!(set.get("S9", "2").is_none() && set.subject("S1").is_none());
    }

    #[test]
    fn malformed_json_is_a_typed_error() {
        let p = Path::new("cams.json");
        let e = parse_cameras("{\"joints_17\": [", p).unwrap_err();
        assert!(matches!(e, H36mError::Json { .. }), "{e}");
        assert!(
            e.to_string()
                .starts_with("cams.json: malformed cameras JSON"),
            "{e}"
        );
        let e = parse_cameras(&GOOD.replace("\"focal\": [1000,1000],", ""), p).unwrap_err();
        assert!(e.to_string().contains("missing field `focal`"), "{e}");
        let e = parse_cameras(&GOOD.replace("[1000,1000],", "[1000],"), p).unwrap_err();
        assert!(matches!(e, H36mError::Json { .. }), "{e}");
        let e = parse_cameras(&GOOD.replace("[0,0,1]]", "[0,0,2]]"), p).unwrap_err();
        assert!(
            matches!(
                e,
                H36mError::Camera {
                    source: CameraError::NotARotation { .. },
                    ..
                }
            ),
            "{e}"
        );
        let e = parse_cameras(
            &GOOD.replace("\"res\": [1000,1000]", "\"res\": [0,1000]"),
            p,
        )
        .unwrap_err();
        assert!(matches!(e, H36mError::Camera { .. }), "{e}");
        let e = parse_cameras(
            &GOOD.replace("\"r_hip\",\"r_knee\"", "\"r_knee\",\"r_hip\""),
            p,
        )
        .unwrap_err();
        assert!(
            matches!(
                e,
                H36mError::JointOrder {
                    list: "joints_17",
                    ..
                }
            ),
            "{e}"
        );
    }

    fn temp_root(name: &str) -> std::path::PathBuf {
        let root = std::env::temp_dir().join(format!("blapose-h36m-{}-{name}", std::process::id()));
        std::fs::create_dir_all(root.join("h36m")).unwrap();
        root
    }

    #[test]
    fn bad_arrays_and_keys_are_typed_errors() {
        use crate::npz::{write_npz, Array, Npz};
        let root = temp_root("bad");
        let mut pose: Pose = [[0.1; 3]; 17];
        let write = |npz: &Npz| write_npz(root.join(POSES_FILE), npz).unwrap();

        let mut npz = Npz::new();
        npz.insert("S9/Walking 1", Array::from_poses(&[pose, pose]));
        write(&npz);
        assert_eq!(
            load_poses(&root, &["S9"]).unwrap()["S9"]["Walking 1"].len(),
            2
        );
        assert!(load_poses(&root, &["S1"]).unwrap().is_empty());

        pose[3][1] = f32::NAN;
        npz.insert("S9/Walking 1", Array::from_poses(&[[[0.0; 3]; 17], pose]));
        write(&npz);
        let e = load_poses(&root, &["S9"]).unwrap_err();
        assert!(
            matches!(&e, H36mError::NonFinite { frame: 1, key, .. } if key == "S9/Walking 1"),
            "{e}"
        );

        let mut npz = Npz::new();
        npz.insert(
            "S9/Walking 1",
            Array::new(vec![2, 16, 2], vec![0.0; 64]).unwrap(),
        );
        write(&npz);
        let e = load_poses(&root, &["S9"]).unwrap_err();
        assert!(e.to_string().contains("expected (_, 17, 3)"), "{e}");

        let mut npz = Npz::new();
        npz.insert("S9/Walking/extra", Array::from_poses(&[]));
        write(&npz);
        let e = load_poses(&root, &["S9"]).unwrap_err();
        assert!(matches!(e, H36mError::BadKey { .. }), "{e}");

        let mut npz = Npz::new();
        npz.insert(
            "S9/Walking 1",
            Array::new(vec![1, 16, 2], vec![0.0; 32]).unwrap(),
        );
        write_npz(root.join(DETECTIONS_FILE), &npz).unwrap();
        let e = load_detections(&root, &["S9"]).unwrap_err();
        assert!(matches!(e, H36mError::BadKey { .. }), "{e}");
        std::fs::remove_dir_all(&root).ok();
    }

    #[test]
    fn missing_files_are_io_errors() {
        let root = Path::new("/nonexistent/blapose");
        assert!(matches!(load_cameras(root), Err(H36mError::Io { .. })));
        assert!(matches!(
            load_poses(root, &["S9"]),
            Err(H36mError::Npz(NpzError::Io { .. }))
        ));
    }
}

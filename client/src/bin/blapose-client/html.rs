//! A self-contained HTML report of an adjustment (`replay`/`adjust --html`).
//!
//! Numbers in a table say *how much* an adjustment helped; a report shows
//! *what* it did: the input and the adjusted skeletons side by side in 3D
//! (animated, with a frame slider and a shared orbit camera), every bone's
//! length over time, the left/right asymmetry and, with ground truth, the
//! per-frame MPJPE and the before/after table ([`Evaluation`]). The file
//! must open anywhere, offline and years later, so it is one HTML file with
//! no external resource: styles, script and data are inline.
//!
//! There is one page, `python/src/blapose/report_template.html`: this crate
//! embeds it ([`TEMPLATE`]) and the Python package ships and fills the same
//! file (`blapose.report.write_html`), so both write the same report. The
//! writers only serialize raw data ([`ReportData`]: poses as flat arrays in
//! metres rounded to 0.1 mm, the skeleton, the frame rate, the metrics table
//! and header lines) into the template's one [`DATA_PLACEHOLDER`]; the page
//! derives bone lengths, asymmetry and per-frame errors itself. Every `<`
//! in the JSON is escaped (`\u003c`), so no string can close the script
//! element that holds it.

use std::path::{Path, PathBuf};

use blapose_client::{evaluate, Adjusted, ClientError, Evaluation, ModelInfo, Sequence};
use blapose_core::skeleton::{BONE_NAMES, JOINT_NAMES, PARENTS};
use blapose_core::Pose;
use serde::Serialize;

/// The report page, with one [`DATA_PLACEHOLDER`] (shared with the Python
/// package, which ships this file).
pub const TEMPLATE: &str = include_str!("../../../../python/src/blapose/report_template.html");
/// What [`ReportData::render`] replaces with the report's JSON.
pub const DATA_PLACEHOLDER: &str = "__BLAPOSE_REPORT_DATA__";
/// The data's `format` field.
pub const FORMAT: &str = "blapose-report/1";

/// Why a report could not be written.
#[derive(Debug, thiserror::Error)]
pub enum HtmlError {
    /// No frames to show.
    #[error("the report has no frames")]
    Empty,
    /// A pose set's frame count differs from `before`'s.
    #[error("{what} has {got} frames but the input poses have {expected}")]
    FrameCount {
        /// `after` or `gt`.
        what: &'static str,
        /// Its frames.
        got: usize,
        /// Frames of `before`.
        expected: usize,
    },
    /// A pose coordinate is NaN or infinite (JSON has no such numbers).
    #[error("{what}: frame {frame}, joint {joint} is not finite")]
    NonFinite {
        /// `before`, `after` or `gt`.
        what: &'static str,
        /// Frame index.
        frame: usize,
        /// Joint index.
        joint: usize,
    },
    /// Serializing the data failed (a non-finite fps or metric).
    #[error("serializing the report data: {0}")]
    Json(#[from] serde_json::Error),
    /// Writing the file failed.
    #[error("writing {}: {source}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
}

/// The skeleton the page draws (Human3.6M-17, from [`blapose_core::skeleton`]);
/// sides and symmetric pairs follow from the `l_`/`r_` names.
#[derive(Debug, Clone, Serialize)]
pub struct SkeletonData {
    /// Joint names.
    pub joint_names: Vec<&'static str>,
    /// Bone names (bone `i` ends at joint `i + 1`).
    pub bone_names: Vec<&'static str>,
    /// Parent of each joint.
    pub parents: Vec<usize>,
}

impl Default for SkeletonData {
    fn default() -> Self {
        SkeletonData {
            joint_names: JOINT_NAMES.to_vec(),
            bone_names: BONE_NAMES.to_vec(),
            parents: PARENTS.to_vec(),
        }
    }
}

/// The report's data: the JSON object the page reads.
#[derive(Debug, Clone, Serialize)]
pub struct ReportData {
    /// Always [`FORMAT`].
    pub format: &'static str,
    /// Header title (e.g. the replay file's name).
    pub title: Option<String>,
    /// Frames.
    pub frames: usize,
    /// Frame rate (playback speed and time axes); `None`: unknown.
    pub fps: Option<f64>,
    /// The skeleton.
    pub skeleton: SkeletonData,
    /// World "up" in the poses' coordinates; `None`: `-y` (camera axes).
    pub up: Option<[f64; 3]>,
    /// Name of the poses before adjustment.
    pub before_label: String,
    /// Name of the adjusted poses.
    pub after_label: String,
    /// `T * 17 * 3` metres, rounded to 0.1 mm.
    pub before: Vec<f64>,
    /// `T * 17 * 3` metres, rounded to 0.1 mm.
    pub after: Vec<f64>,
    /// Ground truth, `T * 17 * 3` metres, rounded to 0.1 mm.
    pub gt: Option<Vec<f64>>,
    /// The before/after table ([`Evaluation`]).
    pub metrics: Option<Evaluation>,
    /// Extra header lines, `[key, value]`, in order.
    pub info: Vec<(String, String)>,
    /// The pelvis per frame in the poses' axes, `T * 3` metres rounded to
    /// 0.1 mm (motion answers): the page draws its path seen from above.
    pub root: Option<Vec<f64>>,
}

/// Metres rounded to 0.1 mm (`0.0 + x`: no `-0`), as the page's data holds them.
fn tenth_mm(v: f64) -> f64 {
    0.0 + (v * 1e4).round() / 1e4
}

/// Poses as a flat list in metres, rounded to 0.1 mm ([`tenth_mm`]).
fn flat(what: &'static str, poses: &[Pose]) -> Result<Vec<f64>, HtmlError> {
    let mut out = Vec::with_capacity(poses.len() * 51);
    for (frame, pose) in poses.iter().enumerate() {
        for (joint, p) in pose.iter().enumerate() {
            if !p.iter().all(|v| v.is_finite()) {
                return Err(HtmlError::NonFinite { what, frame, joint });
            }
            out.extend(p.iter().map(|&v| tenth_mm(f64::from(v))));
        }
    }
    Ok(out)
}

impl ReportData {
    /// The data for `before` and `after` (and optionally `gt`), checked:
    /// the same, non-zero number of frames, finite values. Labels default
    /// to "input" and "adjusted"; set the other fields directly.
    pub fn new(before: &[Pose], after: &[Pose], gt: Option<&[Pose]>) -> Result<Self, HtmlError> {
        if before.is_empty() {
            return Err(HtmlError::Empty);
        }
        let same = |what, poses: &[Pose]| {
            if poses.len() == before.len() {
                Ok(())
            } else {
                Err(HtmlError::FrameCount {
                    what,
                    got: poses.len(),
                    expected: before.len(),
                })
            }
        };
        same("after", after)?;
        if let Some(gt) = gt {
            same("gt", gt)?;
        }
        Ok(ReportData {
            format: FORMAT,
            title: None,
            frames: before.len(),
            fps: None,
            skeleton: SkeletonData::default(),
            up: None,
            before_label: "input".into(),
            after_label: "adjusted".into(),
            before: flat("before", before)?,
            after: flat("after", after)?,
            gt: gt.map(|g| flat("gt", g)).transpose()?,
            metrics: None,
            info: Vec::new(),
            root: None,
        })
    }

    /// The report of what `blapose-client replay`/`adjust` did to `seq`:
    /// before is the file's `pose_3d` (or the server lifter's poses), after
    /// the answers, with the file's `gt_3d` (and the table of
    /// [`evaluate`]) and `fps` (50 when the file has none); `title` names
    /// the file. `up` is the world's up direction in the poses' axes (the
    /// file's `camera_up`, when known).
    pub fn from_adjusted(
        title: &str,
        seq: &Sequence,
        result: &Adjusted,
        up: Option<[f32; 3]>,
    ) -> anyhow::Result<Self> {
        let first = result.first_frame.min(seq.len());
        let end = (first + result.adjusted.len()).min(seq.len());
        let before = match &result.lifter {
            Some(_) => &result.lifted[..],
            None => &seq.pose_3d[first..end],
        };
        let gt = seq.gt_3d.as_ref().map(|g| &g[first..end]);
        let mut data = ReportData::new(before, &result.adjusted, gt)?;
        if let Some(gt) = gt {
            // As the library reports it ("metrics: ..."), for the same message.
            let evaluation = evaluate(before, &result.adjusted, gt).map_err(ClientError::Metric)?;
            data.metrics = Some(evaluation);
        }
        data.title = Some(title.to_string());
        data.fps = Some(seq.fps.map_or(50.0, f64::from));
        data.up = up.map(|u| u.map(f64::from));
        data.before_label = match &result.lifter {
            Some(name) => format!("input (server lifter {name})"),
            None => "input".into(),
        };
        let family = if result.camera.is_some() {
            "camera-aware"
        } else {
            "default"
        };
        data.after_label = format!("adjusted ({})", result.model);
        let mode = if result.session.is_some() {
            "stream"
        } else {
            "offline call"
        };
        data.info.push((
            "model".into(),
            format!("{} ({family}, {mode})", result.model),
        ));
        if let Some(s) = &result.session {
            data.info.push(("session".into(), s.session_id.clone()));
        }
        if let Some(camera) = &result.camera {
            data.info.push(("camera".into(), camera.to_string()));
        }
        if let Some(placement) = result
            .placement
            .as_ref()
            .filter(|p| p.roots.len() == data.frames)
        {
            data.root = Some(
                placement
                    .roots
                    .iter()
                    .flatten()
                    .map(|&v| tenth_mm(f64::from(v)))
                    .collect(),
            );
            let focal = if placement.focal_assumed {
                "placed (focal length assumed: distances scale with the true one)"
            } else {
                "placed through the calibration"
            };
            data.info.push(("motion".into(), focal.into()));
        }
        Ok(data)
    }

    /// Header lines about the server: its version and the weights of the
    /// model that served (`camera_aware` selects the family).
    pub fn add_server_info(&mut self, server: &str, info: &ModelInfo, result: &Adjusted) {
        self.info.push((
            "server".into(),
            format!("{server} (blapose-server {})", info.server_version),
        ));
        let served = info
            .models
            .iter()
            .find(|m| m.model == Some(result.model) && m.camera_aware == result.camera.is_some());
        if let Some(m) = served {
            let sha = m.weights_sha256.get(..12).unwrap_or(&m.weights_sha256);
            self.info.push((
                "weights".into(),
                format!("{} ({}, sha256 {sha})", m.name, m.weights_source),
            ));
        }
    }

    /// The data as the page embeds it: compact JSON with every `<` escaped.
    pub fn to_json(&self) -> Result<String, HtmlError> {
        Ok(serde_json::to_string(self)?.replace('<', "\\u003c"))
    }

    /// The report page.
    pub fn render(&self) -> Result<String, HtmlError> {
        Ok(TEMPLATE.replacen(DATA_PLACEHOLDER, &self.to_json()?, 1))
    }

    /// Write the report page to `path`.
    pub fn write(&self, path: impl AsRef<Path>) -> Result<(), HtmlError> {
        let path = path.as_ref();
        std::fs::write(path, self.render()?).map_err(|source| HtmlError::Io {
            path: path.to_owned(),
            source,
        })
    }
}

/// A parsed JSON value ([`embedded_data`]).
#[cfg(test)]
pub type JsonValue = serde_json::Value;

/// The JSON data embedded in a report page (what [`ReportData::render`]
/// put there), for tests.
#[cfg(test)]
pub fn embedded_data(html: &str) -> Option<JsonValue> {
    const START: &str = r#"<script id="blapose-data" type="application/json">"#;
    let start = html.find(START)? + START.len();
    let end = start + html[start..].find("</script>")?;
    serde_json::from_str(&html[start..end]).ok()
}

#[cfg(test)]
mod tests {
    use super::*;
    use blapose_client::PoseMetrics;

    fn pose(t: usize, scale: f32) -> Pose {
        std::array::from_fn(|j| {
            let j = j as f32;
            [
                scale * (0.1 * j + 0.01 * t as f32).sin(),
                scale * 0.07 * j,
                scale * (0.3 * j).cos(),
            ]
        })
    }

    fn poses(scale: f32) -> Vec<Pose> {
        (0..5).map(|t| pose(t, scale)).collect()
    }

    #[test]
    fn the_template_has_one_placeholder_and_no_remote_resources() {
        assert_eq!(TEMPLATE.matches(DATA_PLACEHOLDER).count(), 1);
        assert_eq!(
            TEMPLATE.matches(r#"<script id="blapose-data""#).count(),
            1,
            "readers find the data by its element"
        );
        let lower = TEMPLATE.to_ascii_lowercase();
        assert!(!lower.contains("http://") && !lower.contains("https://"));
        for tag in ["<script src", "<link", "<img", "<iframe", "@import", "url("] {
            assert!(!lower.contains(tag), "the template uses {tag}");
        }
    }

    #[test]
    fn the_page_carries_the_data_rounded_to_a_tenth_of_a_millimetre() {
        let (before, after, gt) = (poses(1.0), poses(0.9), poses(0.95));
        let mut data = ReportData::new(&before, &after, Some(&gt)).unwrap();
        data.title = Some("walk.npz".into());
        data.fps = Some(50.0);
        data.metrics = Some(evaluate(&before, &after, &gt).unwrap());
        data.info.push(("model".into(), "gru".into()));
        let html = data.render().unwrap();
        assert!(!html.contains(DATA_PLACEHOLDER));
        let v = embedded_data(&html).expect("data in the page");
        assert_eq!(v["format"], FORMAT);
        assert_eq!(v["frames"], 5);
        assert_eq!(v["title"], "walk.npz");
        assert_eq!(v["fps"], 50.0);
        assert_eq!(v["skeleton"]["joint_names"][16], "r_wrist");
        assert_eq!(v["skeleton"]["bone_names"].as_array().unwrap().len(), 16);
        assert_eq!(v["skeleton"]["parents"][11], 8);
        assert_eq!(v["info"][0][0], "model");
        assert!(v["metrics"]["after"]["p_mpjpe_mm"].is_number());
        for (key, set) in [("before", &before), ("after", &after), ("gt", &gt)] {
            let flat = v[key].as_array().unwrap();
            assert_eq!(flat.len(), 5 * 17 * 3, "{key}");
            for (i, x) in flat.iter().enumerate() {
                let x = x.as_f64().unwrap();
                let want = f64::from(set[i / 51][(i % 51) / 3][i % 3]);
                assert!(
                    (x - want).abs() <= 0.5e-4 + 1e-9,
                    "{key}[{i}]: {x} vs {want}"
                );
                assert!(
                    (x * 1e4 - (x * 1e4).round()).abs() < 1e-6,
                    "{x} is not rounded"
                );
            }
        }
        // Without ground truth: no gt, no table.
        let v = embedded_data(
            &ReportData::new(&before, &after, None)
                .unwrap()
                .render()
                .unwrap(),
        )
        .unwrap();
        assert!(v["gt"].is_null() && v["metrics"].is_null());
    }

    #[test]
    fn no_string_can_close_the_script_element() {
        let mut data = ReportData::new(&poses(1.0), &poses(1.0), None).unwrap();
        data.title = Some("</script><script>alert(1)</script><!--".into());
        data.info.push(("a</b".into(), "</SCRIPT>".into()));
        let html = data.render().unwrap();
        let start = html.find(r#"<script id="blapose-data""#).unwrap();
        let data_end = start + html[start..].find("</script>").unwrap();
        let json = &html[start..data_end];
        assert!(!json.contains("</") && !json.contains("<!--"), "{json}");
        let v = embedded_data(&html).unwrap();
        assert_eq!(v["title"], "</script><script>alert(1)</script><!--");
        assert_eq!(v["info"][0][1], "</SCRIPT>");
    }

    #[test]
    fn the_filled_page_references_nothing_remote() {
        let mut data = ReportData::new(&poses(1.0), &poses(1.1), None).unwrap();
        data.info
            .push(("server".into(), "http://127.0.0.1:50051".into()));
        let html = data.render().unwrap();
        let lower = html.to_ascii_lowercase();
        for pattern in [
            r#"src="http"#,
            r#"src='http"#,
            r#"href="http"#,
            r#"href='http"#,
            "<link",
            "<img",
            "url(http",
            "<script src",
        ] {
            assert!(!lower.contains(pattern), "{pattern}");
        }
        // Outside the data (where a server URL may be text), no URL at all.
        let start = html.find(r#"<script id="blapose-data""#).unwrap();
        let end = start + html[start..].find("</script>").unwrap();
        let outside = format!("{}{}", &lower[..start], &lower[end..]);
        assert!(!outside.contains("http://") && !outside.contains("https://"));
    }

    #[test]
    fn bad_input_is_refused() {
        let before = poses(1.0);
        assert!(matches!(
            ReportData::new(&[], &[], None),
            Err(HtmlError::Empty)
        ));
        assert!(matches!(
            ReportData::new(&before, &before[..4], None),
            Err(HtmlError::FrameCount {
                what: "after",
                got: 4,
                expected: 5
            })
        ));
        assert!(matches!(
            ReportData::new(&before, &before, Some(&before[..2])),
            Err(HtmlError::FrameCount { what: "gt", .. })
        ));
        let mut bad = before.clone();
        bad[3][7][1] = f32::NAN;
        assert!(matches!(
            ReportData::new(&before, &bad, None),
            Err(HtmlError::NonFinite {
                what: "after",
                frame: 3,
                joint: 7
            })
        ));
        let mut data = ReportData::new(&before, &before, None).unwrap();
        data.metrics = Some(Evaluation {
            frames: 5,
            before: PoseMetrics {
                mpjpe_mm: f64::NAN,
                p_mpjpe_mm: 0.0,
                mpjve_mm: None,
                bone_error_mm: 0.0,
            },
            after: PoseMetrics {
                mpjpe_mm: 0.0,
                p_mpjpe_mm: 0.0,
                mpjve_mm: None,
                bone_error_mm: 0.0,
            },
        });
        // serde_json writes NaN as null: the page shows a dash.
        assert!(data.render().is_ok());
        let dir = std::env::temp_dir().join("blapose-html-test-missing-dir/x/y");
        assert!(matches!(
            data.write(dir.join("r.html")),
            Err(HtmlError::Io { .. })
        ));
    }
}

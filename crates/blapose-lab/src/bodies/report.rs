//! The many-bodies benchmark's report: the rows and baselines, and what
//! is needed to read and reproduce them (individuals, seed, cameras, the
//! prior, each trial's motion and camera); and its markdown table.
//!
//! Why its own module: the JSON (`blapose-lab bodies --json`) is what the
//! model card's numbers are read from; its schema is kept here, in one
//! place.

use blapose_train::camera_range::{CameraRange, DrawnCamera};
use serde::Serialize;

use super::score::{Baseline, Row};
use crate::real_check::RealCheckInfo;

/// One trial in the report (what each individual saw).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct TrialInfo {
    /// Survey id.
    pub subject_id: u64,
    /// Motion.
    pub motion: String,
    /// First frame.
    pub start: usize,
    /// True total length (metres).
    pub true_total_m: f64,
    /// The camera.
    pub camera: DrawnCamera,
}

/// The whole report (`--json`): the `rows`, and
/// everything needed to read and reproduce them.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct BodiesReport {
    /// One row per (model, input).
    pub rows: Vec<Row>,
    /// Constant answers: the prior and the training subjects' mean.
    pub baselines: Vec<Baseline>,
    /// Individuals (held-out ANSUR people).
    pub individuals: usize,
    /// Of which male.
    pub male: usize,
    /// Of which female.
    pub female: usize,
    /// Frames per individual (50 Hz).
    pub frames_per_individual: usize,
    /// Frames read per model.
    pub frames: usize,
    /// Master seed.
    pub seed: u64,
    /// The camera distribution.
    pub camera_distribution: CameraRange,
    /// The prior (population-mean body of the training population), metres.
    pub prior_m: Vec<f32>,
    /// How the rows are computed.
    pub protocol: String,
    /// Wall-clock seconds of the whole benchmark (data loading included
    /// when the caller sets it).
    pub seconds: f64,
    /// Per individual: motion, camera, true size.
    pub trials: Vec<TrialInfo>,
    /// What the real-detection check ran on (`None`: not run).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub real_check: Option<RealCheckInfo>,
}

/// The report as a markdown table: the models beside the baselines.
pub fn markdown(r: &BodiesReport) -> String {
    let mut s = format!(
        "## Many-bodies benchmark: {} held-out ANSUR II individuals ({} male, {} female), \
         {} frames each on S9/S11 motion, wide cameras, seed {}\n\n",
        r.individuals, r.male, r.female, r.frames_per_individual, r.seed
    );
    let check = r.real_check.is_some();
    s.push_str(
        "| model | input | mean bone error (mm) | prior (mm) | ratio to prior | size slope | \
         at prior size (mm) |",
    );
    s.push_str(if check {
        " training subjects' real SH (mm) |\n|---|---|---:|---:|---:|---:|---:|---:|\n"
    } else {
        "\n|---|---|---:|---:|---:|---:|---:|\n"
    });
    let real = |v: Option<f64>| match (check, v) {
        (false, _) => String::new(),
        (true, Some(v)) => format!(" {v:.2} |"),
        (true, None) => " - |".into(),
    };
    for row in &r.rows {
        s.push_str(&format!(
            "| {} | {} | {:.2} | {:.2} | {:.3} | {:.3} | {:.2} |{}\n",
            row.model,
            row.input,
            row.mean_bone_error_mm,
            row.prior_mean_bone_error_mm,
            row.ratio_to_prior,
            row.size_slope,
            row.at_prior_size_mm,
            real(row.real_check_mm)
        ));
    }
    let prior_mm = r
        .baselines
        .first()
        .map_or(f64::NAN, |b| b.mean_bone_error_mm);
    for b in &r.baselines {
        s.push_str(&format!(
            "| baseline: {} | - | {:.2} | {:.2} | {:.3} | 0 | - |{}\n",
            b.name.name(),
            b.mean_bone_error_mm,
            prior_mm,
            b.ratio_to_prior,
            real(b.real_check_mm)
        ));
    }
    if let Some(c) = &r.real_check {
        s.push_str(&format!(
            "\nReal-detection check: {} trials ({} frames) of {}'s Stacked Hourglass detections \
             with their true lengths (training data; camera-aware models read them with each \
             view's calibration; the stature regression with each subject's matched stature, \
             which reads the truth).\n",
            c.trials,
            c.frames,
            c.subjects.join(", ")
        ));
    }
    s
}

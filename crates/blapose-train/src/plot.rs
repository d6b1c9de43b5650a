//! Plots: the training curve and the online model's error against frames
//! seen (SVG through plotters, no system fonts needed for SVG text), so a
//! run's curve and the model card's figures come from the logs and reports
//! themselves rather than from a separate tool.

use std::path::Path;

use plotters::prelude::*;

use crate::error::TrainError;
use crate::run::read_log_column;

fn plot_err<E: std::fmt::Display>(e: E) -> TrainError {
    TrainError::Plot(e.to_string())
}

/// Lines `(label, points)` on one chart; `log_x` for frame counts.
pub fn line_chart(
    path: &Path,
    title: &str,
    x_label: &str,
    y_label: &str,
    series: &[(String, Vec<(f64, f64)>)],
    log_x: bool,
) -> Result<(), TrainError> {
    let pts = series
        .iter()
        .flat_map(|(_, p)| p.iter())
        .filter(|(x, y)| x.is_finite() && y.is_finite());
    let (mut x0, mut x1, mut y1) = (f64::MAX, f64::MIN, 0.0f64);
    for &(x, y) in pts {
        x0 = x0.min(x);
        x1 = x1.max(x);
        y1 = y1.max(y);
    }
    if x0 > x1 {
        return Err(TrainError::Plot(format!("{title}: nothing to plot")));
    }
    if x1 <= x0 {
        x1 = x0 + 1.0;
    }
    let root = SVGBackend::new(path, (900, 560)).into_drawing_area();
    root.fill(&WHITE).map_err(plot_err)?;
    let y_range = 0.0..(y1 * 1.1).max(1e-6);
    let colors = [BLUE, RED, GREEN, MAGENTA, CYAN, BLACK];
    macro_rules! draw {
        ($chart:expr) => {{
            let mut chart = $chart;
            chart
                .configure_mesh()
                .x_desc(x_label)
                .y_desc(y_label)
                .draw()
                .map_err(plot_err)?;
            for (i, (label, p)) in series.iter().enumerate() {
                let c = colors[i % colors.len()];
                chart
                    .draw_series(LineSeries::new(p.iter().copied(), c.stroke_width(2)))
                    .map_err(plot_err)?
                    .label(label.as_str())
                    .legend(move |(x, y)| {
                        PathElement::new(vec![(x, y), (x + 20, y)], c.stroke_width(2))
                    });
            }
            chart
                .configure_series_labels()
                .background_style(WHITE.mix(0.8))
                .border_style(BLACK)
                .draw()
                .map_err(plot_err)?;
        }};
    }
    let mut builder = ChartBuilder::on(&root);
    builder
        .caption(title, ("sans-serif", 22))
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(60);
    if log_x {
        draw!(builder
            .build_cartesian_2d((x0.max(1e-3)..x1).log_scale(), y_range)
            .map_err(plot_err)?);
    } else {
        draw!(builder
            .build_cartesian_2d(x0..x1, y_range)
            .map_err(plot_err)?);
    }
    root.present().map_err(plot_err)?;
    Ok(())
}

/// Columns `(name, label)` of a training log against steps on one chart
/// (columns absent from the log or without finite values are left out).
pub fn log_curve(
    log: &Path,
    out: &Path,
    title: &str,
    y_label: &str,
    columns: &[(&str, &str)],
) -> Result<(), TrainError> {
    let mut series = Vec::new();
    for (col, label) in columns {
        if let Ok(p) = read_log_column(log, col) {
            if !p.is_empty() {
                series.push((label.to_string(), p));
            }
        }
    }
    line_chart(out, title, "step", y_label, &series, false)
}

/// The training curve from a training log: training loss and validation
/// errors (mm) against steps.
pub fn training_curve(log: &Path, out: &Path) -> Result<(), TrainError> {
    log_curve(
        log,
        out,
        "bone-length training",
        "mean bone-length error (mm)",
        &[
            ("train_loss_mm", "training loss (synthetic)"),
            ("val_synth_mm", "validation, synthetic"),
            ("val_real_sh_mm", "validation, real SH (training subjects)"),
            (
                "val_real_sh_running_mm",
                "validation, real SH, running mean",
            ),
        ],
    )
}

/// The lifter training curve ([`crate::lifter::train::LOG_HEADER`]):
/// training loss and held-out MPJPE (mm) against steps.
pub fn lifter_training_curve(log: &Path, out: &Path) -> Result<(), TrainError> {
    log_curve(
        log,
        out,
        "lifter training",
        "MPJPE (mm)",
        &[
            ("train_loss_mm", "training loss (16 joints, augmented)"),
            ("val_mpjpe_mm", "validation, held-out frames"),
            (
                "val_mpjpe_flip_mm",
                "validation, held-out frames, test-time flip",
            ),
        ],
    )
}

/// The online model's error against frames seen (log x), with the naive
/// baselines as flat lines.
pub fn error_curve(report: &crate::eval::EvalReport, out: &Path) -> Result<(), TrainError> {
    let pts: Vec<(f64, f64)> = report
        .curve
        .iter()
        .map(|c| (c.frames as f64, c.mean_bone_error_mm))
        .collect();
    let (x0, x1) = (
        pts.first().map_or(1.0, |p| p.0),
        pts.last().map_or(1.0, |p| p.0),
    );
    let mut series = vec![(
        format!("{} ({} input), running mean", report.model, report.input),
        pts,
    )];
    for (name, s) in &report.baselines {
        series.push((
            format!("baseline: {name}"),
            vec![(x0, s.mean_bone_error_mm), (x1, s.mean_bone_error_mm)],
        ));
    }
    line_chart(
        out,
        "bone-length error vs frames seen",
        "frames seen",
        "mean bone-length error (mm)",
        &series,
        true,
    )
}

//! The table as markdown: the conditions it was measured under (steps,
//! runs, machine, load), then each row beside the paper's figure.

use crate::Report;

pub(crate) fn markdown(report: &Report) -> String {
    let c = &report.conditions;
    let mut s = String::new();
    s.push_str("## FPS: online, batch 1, one output frame per step, no test-time flip\n\n");
    if c.steps < 10_000 {
        s.push_str(&format!(
            "- **{} steps per measurement — fewer than the paper's 10,000 (quick run)**\n",
            c.steps
        ));
    } else {
        s.push_str(&format!(
            "- {} steps per measurement (the paper: 10,000)\n",
            c.steps
        ));
    }
    s.push_str(&format!(
        "- median of {} runs, {} warm-up steps each; random weights\n",
        c.runs, c.warmup
    ));
    s.push_str(&format!(
        "- lifters: {} variants; adjustment = online GRU step + running mean + adjust_pose{}\n",
        if c.causal_lifters {
            "causal (VideoPose3D, Anatomy3D)"
        } else {
            "centred"
        },
        if c.overlap {
            " (GRU step concurrent with the lifter; in-step overhead = adjust_pose only)"
        } else {
            " (after the lifter, one after the other)"
        }
    ));
    s.push_str(&format!(
        "- CPU: {} ({} logical CPUs)\n",
        c.cpu, c.logical_cpus
    ));
    s.push_str(&format!(
        "- threads: lifters {} ({}), GRU engine {} ({}, {} weights); GRU weights: {}\n",
        c.candle_threads, c.thread_env, c.gru_threads, c.gru_isa, c.gru_precision, c.gru_weights
    ));
    s.push_str(&format!(
        "- load average before: {}; after: {}\n",
        c.load_average_before, c.load_average_after
    ));
    s.push_str(&format!(
        "- adjustment alone: {:.1} µs per frame\n",
        c.adjustment_alone_us
    ));
    s.push_str(
        "- overhead (FPS) = 1 - FPS with adjustment / FPS (the paper's measure; separate runs, ",
    );
    s.push_str(
        "so sensitive to load changes); overhead (in-step) = share of each adjusted step spent ",
    );
    s.push_str("in the adjustment, timed inside the same steps\n");
    s.push_str("- CPU use: process CPU time / wall time during the timed steps (alone / with adjustment); ");
    s.push_str("below the thread count means the process waited for a CPU\n\n");
    s.push_str("| model | frames | params | FPS | FPS with adjustment | overhead (FPS) | overhead (in-step) | paper FPS | paper with adjustment | paper overhead | MPJPE (mm) | CPU use |\n");
    s.push_str("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n");
    let opt = |v: Option<f64>, f: &dyn Fn(f64) -> String| v.map(f).unwrap_or_else(|| "-".into());
    for r in &report.rows {
        s.push_str(&format!(
            "| {} | {} | {} | {:.1} | {} | {} | {} | {:.0} | {} | {} | {} | {} |\n",
            r.model,
            r.frames
                .map(|f| f.to_string())
                .unwrap_or_else(|| "-".into()),
            thousands(r.params),
            r.fps,
            opt(r.fps_with_adjustment, &|v| format!("{v:.1}")),
            opt(r.adjustment_overhead_pct, &|v| format!("{v:.1} %")),
            opt(r.adjustment_share_pct, &|v| format!("{v:.1} %")),
            r.paper_fps,
            opt(r.paper_fps_with_adjustment, &|v| format!("{v:.0}")),
            opt(r.paper_overhead_pct, &|v| format!("{v:.1} %")),
            r.mpjpe_mm
                .map(|v| format!("{v:.1}"))
                .unwrap_or_else(|| "—".into()),
            match (r.cpu_pct, r.cpu_pct_with_adjustment) {
                (Some(a), Some(w)) => format!("{a:.0} / {w:.0} %"),
                (Some(a), None) => format!("{a:.0} %"),
                _ => "-".into(),
            },
        ));
    }
    s
}

pub(crate) fn thousands(n: usize) -> String {
    let digits = n.to_string();
    let mut out = String::new();
    for (i, ch) in digits.chars().enumerate() {
        if i > 0 && (digits.len() - i).is_multiple_of(3) {
            out.push(',');
        }
        out.push(ch);
    }
    out
}

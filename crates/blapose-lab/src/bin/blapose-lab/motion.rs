//! `blapose-lab motion`: every candidate motion filter on subjects the
//! choice may be made on ([`blapose_lab::motion_sweep`]), as one markdown
//! table (and JSON). Why a command of its own: it loads the lifter and
//! both bone-length models and lifts each trial once for all candidates.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{ensure, Result};
use blapose_core::motion::{CausalMotionConfig, CausalSmoothing};
use blapose_data::h36m::{H36m, Parts, TEST_SUBJECTS, TRAIN_SUBJECTS};
use blapose_lab::motion_sweep::{
    causal_direction_candidates, causal_root_candidates, fir_fit, lift_all, offline_candidates,
    prefiltered, root_joint_sets, Row, Sweep,
};
use blapose_model::ModelKind;
use blapose_train::dataset::{mean_subject_lengths, subject_lengths};
use blapose_train::eval_adjust::{LengthEstimates, MethodReport};
use blapose_train::lifter::data::{lifter_sequences, LifterSequence};
use blapose_train::lifter::predict::StreamLifter;
use blapose_train::lifter::weights as lifter_weights;
use blapose_train::motion_eval::Scene;

/// Arguments of `blapose-lab motion`.
#[derive(clap::Args, Debug)]
pub struct MotionArgs {
    /// The lifter whose motion is filtered.
    #[arg(long, default_value = "models/lifter_videopose27_causal.safetensors")]
    lifter_weights: PathBuf,
    /// Online GRU weights.
    #[arg(long, default_value = "models/bone_length_gru.safetensors")]
    gru_weights: PathBuf,
    /// Offline Bi-GRU weights.
    #[arg(long, default_value = "models/bone_length_bigru.safetensors")]
    bigru_weights: PathBuf,
    /// Subjects to choose on (training subjects only: S9/S11 are refused).
    #[arg(long, default_value = "S1,S5,S6,S7,S8", value_delimiter = ',')]
    subjects: Vec<String>,
    /// Every k-th trial (the held-out split).
    #[arg(long, default_value_t = 8)]
    every: usize,
    /// Write every row as JSON here.
    #[arg(long)]
    json: Option<PathBuf>,
    /// Data root (default: $BLAPOSE_DATA or ../shared/data).
    #[arg(long)]
    data: Option<PathBuf>,
    /// Measure only the learned refiners (`blapose_lab::motion_refiner`,
    /// fitted across cameras on recordings with no held-out trial), beside
    /// the baselines and the served stages.
    #[arg(long)]
    refiners: bool,
    /// Measure only the root solve's scale bias
    /// (`blapose_lab::root_scale`): per subject and camera, and one factor
    /// fitted on the other subjects.
    #[arg(long)]
    root_scale: bool,
}

fn line(group: &str, name: &str, m: &MethodReport) -> String {
    let c = |v: Option<f64>| v.map_or("-".to_string(), |v| format!("{v:.2}"));
    format!(
        "| {group} | {name} | {:.2} | {:.2} | {} | {} | {} |\n",
        m.avg.mpjpe_mm,
        m.avg.mpjve_mm.unwrap_or(f64::NAN),
        c(m.motion.accel_error_mm),
        c(m.motion.mrpe_mm),
        c(m.motion.foot_skate_mm),
    )
}

/// `blapose-lab motion`.
pub fn run(a: MotionArgs) -> Result<()> {
    for s in &a.subjects {
        ensure!(
            TRAIN_SUBJECTS.contains(&s.as_str()),
            "{s}: choose on training subjects only ({}; never {})",
            TRAIN_SUBJECTS.join(","),
            TEST_SUBJECTS.join(",")
        );
    }
    let root = blapose_data::data_root(a.data.clone());
    let subjects: Vec<&str> = a.subjects.iter().map(String::as_str).collect();
    let t0 = Instant::now();
    // The selection split: every k-th trial; the learned filter is fitted
    // on the trials half-way between them.
    let every = a.every.max(2);
    let (trials, fit_trials, scenes, all) = {
        let h36m = H36m::load(&root, &subjects, Parts::ALL)?;
        let all: Vec<LifterSequence> = lifter_sequences(&h36m, &subjects)?;
        let trials: Vec<LifterSequence> = all.iter().step_by(every).cloned().collect();
        let fit_trials: Vec<LifterSequence> =
            all.iter().skip(every / 2).step_by(every).cloned().collect();
        let scenes = trials
            .iter()
            .map(|t| Scene::build(&h36m, t))
            .collect::<Result<Vec<_>, _>>()?;
        (trials, fit_trials, scenes, all)
    };
    let training_mean = {
        let h36m = H36m::load(&root, &TRAIN_SUBJECTS, Parts::POSES)?;
        mean_subject_lengths(&subject_lengths(&h36m), &TRAIN_SUBJECTS)
    };
    let gru_weights = blapose_model::weights::load(&a.gru_weights, ModelKind::Gru)?;
    let bigru_weights = blapose_model::weights::load(&a.bigru_weights, ModelKind::BiGru)?;
    let mut estimates =
        LengthEstimates::compute(&trials, Some(&gru_weights), Some(&bigru_weights))?;
    estimates.training_mean = training_mean;
    eprintln!(
        "{} trials ({} frames), estimates in {:.1}s",
        trials.len(),
        trials.iter().map(|t| t.frames()).sum::<usize>(),
        t0.elapsed().as_secs_f64()
    );
    let loaded = lifter_weights::load(&a.lifter_weights)?;
    let lifter = StreamLifter::new(&loaded)?;
    let sweep = Sweep {
        trials: &trials,
        adjusters: estimates.adjusters(),
    };
    let lifted = lift_all(&trials, &|s| lifter.lift(&s.trial, true))?;
    eprintln!("lifted in {:.1}s", t0.elapsed().as_secs_f64());
    let (served_causal, served_offline) = Sweep::served();
    let mut rows: Vec<(String, Row)> = Vec::new();
    let mut push = |group: &str, name: String, report: Option<MethodReport>| {
        if let Some(report) = report {
            rows.push((
                group.to_string(),
                Row {
                    candidate: name,
                    report,
                },
            ));
        }
    };
    // Baselines, and the served stages.
    let served = sweep.evaluate(&lifted, &scenes, served_causal, served_offline)?;
    push(
        "baseline",
        "before (lifter as it is)".into(),
        Some(served.before.clone()),
    );
    push(
        "baseline",
        "gru (no motion stage)".into(),
        served.gru.clone(),
    );
    push(
        "baseline",
        "bigru (no motion stage)".into(),
        served.bigru.clone(),
    );
    push(
        "baseline",
        "true lengths (oracle)".into(),
        served.ground_truth_lengths.clone(),
    );
    push("served", "gru_motion".into(), served.gru_motion.clone());
    push("served", "bigru_motion".into(), served.bigru_motion.clone());
    if a.root_scale {
        return root_scale_report(&trials, &lifted, &scenes, estimates.adjusters().gru);
    }
    if a.refiners {
        for (group, name, report) in refiner_rows(
            &sweep,
            &trials,
            &across_cameras(&all, &trials),
            &lifted,
            &lifter,
            &scenes,
        )? {
            push(group, name, report);
        }
        return finish(&rows, a.json.as_deref(), t0);
    }
    let fit = {
        let lifted = lift_all(&fit_trials, &|s| lifter.lift(&s.trial, true))?;
        let lengths = LengthEstimates::compute(&fit_trials, Some(&gru_weights), None)?
            .gru
            .unwrap_or_default();
        fir_fit(&fit_trials, &lifted, &lengths)?
    };
    eprintln!("fitted in {:.1}s", t0.elapsed().as_secs_f64());
    let mut candidates = causal_direction_candidates();
    for (v, acc) in [
        (0.0, 0.0),
        (1.0, 0.0),
        (4.0, 0.0),
        (0.0, 4.0),
        (4.0, 4.0),
        (4.0, 16.0),
        (16.0, 16.0),
        (16.0, 64.0),
        (64.0, 64.0),
    ] {
        if let Some(taps) = fit.solve(v, acc) {
            candidates.push((
                format!("learned fir velocity {v} accel {acc}"),
                Some(CausalSmoothing::Fir(taps)),
            ));
            eprintln!("fir {v} {acc}: {:?}", taps.0);
        }
    }
    for (name, directions) in candidates {
        let causal = CausalMotionConfig {
            directions,
            ..served_causal
        };
        let r = sweep.evaluate(&lifted, &scenes, causal, served_offline)?;
        push("causal directions", name, r.gru_motion);
        eprintln!("{:.0}s", t0.elapsed().as_secs_f64());
    }
    for (name, root_filter) in causal_root_candidates() {
        let causal = CausalMotionConfig {
            root: root_filter,
            ..served_causal
        };
        let r = sweep.evaluate(&lifted, &scenes, causal, served_offline)?;
        push("causal root", name, r.gru_motion);
    }
    for (name, weights) in root_joint_sets() {
        let weighted: Vec<Scene> = scenes
            .iter()
            .map(|s| {
                let mut s = s.clone();
                for r in &mut s.rays {
                    r.1 = weights;
                }
                s
            })
            .collect();
        let r = sweep.evaluate(&lifted, &weighted, served_causal, served_offline)?;
        push("root joints", format!("{name} (causal)"), r.gru_motion);
        push("root joints", format!("{name} (offline)"), r.bigru_motion);
    }
    for (name, offline) in offline_candidates() {
        let r = sweep.evaluate(&lifted, &scenes, served_causal, offline)?;
        push("offline", name, r.bigru_motion);
    }
    eprintln!("filters in {:.1}s", t0.elapsed().as_secs_f64());
    for (name, smoothing) in causal_direction_candidates().into_iter().filter(|(n, _)| {
        n == "one-euro min 1 Hz beta 0.5" || n == "kalman q 1 r 4e-4" || n == "kalman q 3 r 1.6e-3"
    }) {
        let Some(smoothing) = smoothing else { continue };
        let pre = lift_all(&trials, &|s| {
            let mut trial = s.trial.clone();
            trial.input = prefiltered(&trial.input, smoothing);
            lifter.lift(&trial, true)
        })?;
        let plain = CausalMotionConfig {
            directions: None,
            ..served_causal
        };
        let r = sweep.evaluate(&pre, &scenes, plain, served_offline)?;
        push(
            "2D before lifting",
            format!("{name} (then gru)"),
            r.gru_motion,
        );
        let r = sweep.evaluate(&pre, &scenes, served_causal, served_offline)?;
        push(
            "2D before lifting",
            format!("{name} + served directions"),
            r.gru_motion,
        );
    }
    finish(&rows, a.json.as_deref(), t0)
}

fn finish(rows: &[(String, Row)], json: Option<&std::path::Path>, t0: Instant) -> Result<()> {
    let mut md = String::from(
        "| group | candidate | MPJPE (mm) | MPJVE (mm/frame) | accel (mm/frame²) | MRPE (mm) | foot skate (mm/frame) |\n\
         |---|---|---|---|---|---|---|\n",
    );
    for (g, r) in rows {
        md.push_str(&line(g, &r.candidate, &r.report));
    }
    println!("{md}");
    eprintln!("done in {:.1}s", t0.elapsed().as_secs_f64());
    if let Some(p) = json {
        let json: Vec<_> = rows
            .iter()
            .map(|(g, r)| serde_json::json!({"group": g, "candidate": r.candidate, "report": r.report}))
            .collect();
        std::fs::write(p, serde_json::to_string_pretty(&json)?)?;
    }
    Ok(())
}

type RefinerRow = (&'static str, String, Option<MethodReport>);

/// Every camera of every other recording (subject and sequence) of `all`
/// with no trial in `held_out`: the refiner reads camera-space directions,
/// so it is fitted across cameras and never on a held-out recording.
fn across_cameras(all: &[LifterSequence], held_out: &[LifterSequence]) -> Vec<LifterSequence> {
    use std::collections::HashSet;
    let recording = |t: &LifterSequence| (t.trial.subject.clone(), t.trial.sequence.clone());
    let held: HashSet<_> = held_out.iter().map(recording).collect();
    let mut recordings: Vec<_> = all
        .iter()
        .map(recording)
        .filter(|r| !held.contains(r))
        .collect();
    recordings.dedup();
    let chosen: HashSet<_> = recordings.into_iter().step_by(2).collect();
    all.iter()
        .filter(|t| chosen.contains(&recording(t)))
        .cloned()
        .collect()
}

/// Learned refiners ([`blapose_lab::motion_refiner`]) of several windows
/// and weights, fitted on `fit_trials` and applied to the lifted poses of
/// `trials` before the adjustment: causal ones scored as `gru_motion`,
/// offline ones (reading later frames) as `bigru_motion`, each with no
/// other direction filter.
fn refiner_rows(
    sweep: &Sweep,
    trials: &[LifterSequence],
    fit_trials: &[LifterSequence],
    lifted: &blapose_lab::motion_sweep::Lifted,
    lifter: &StreamLifter,
    scenes: &[Scene],
) -> Result<Vec<RefinerRow>> {
    use blapose_core::motion::OfflineMotionConfig;
    use blapose_lab::motion_refiner::{refine_poses, RefinerFit, RefinerWindow};
    use blapose_lab::motion_sweep::key;
    let t0 = Instant::now();
    let fit_lifted = lift_all(fit_trials, &|s| lifter.lift(&s.trial, true))?;
    let (served_causal, served_offline) = Sweep::served();
    let causal_plain = CausalMotionConfig {
        directions: None,
        ..served_causal
    };
    let offline_plain = OfflineMotionConfig {
        directions: None,
        ..served_offline
    };
    let window = |past, future, past_2d| RefinerWindow {
        past,
        future,
        past_2d,
    };
    let mut rows = Vec::new();
    for w in [window(8, 0, 0), window(16, 0, 2), window(12, 12, 0)] {
        let mut fit = RefinerFit::new(w);
        for t in fit_trials {
            fit.add(&fit_lifted[&key(t)], &t.trial.input, &t.target);
        }
        eprintln!("refiner {w:?} fitted at {:.0}s", t0.elapsed().as_secs_f64());
        for (v, acc) in [(0.0, 0.0), (4.0, 4.0), (16.0, 16.0), (64.0, 64.0)] {
            let Some(refiner) = fit.solve(v, acc, 1e-6) else {
                eprintln!("refiner {w:?} {v} {acc}: singular");
                continue;
            };
            let refined: blapose_lab::motion_sweep::Lifted = trials
                .iter()
                .map(|t| {
                    (
                        key(t),
                        refine_poses(&refiner, &lifted[&key(t)], &t.trial.input),
                    )
                })
                .collect();
            let r = sweep.evaluate(&refined, scenes, causal_plain, offline_plain)?;
            let name = format!(
                "refiner past {} future {} 2d {} velocity {v} accel {acc}",
                w.past, w.future, w.past_2d
            );
            if refiner.is_causal() {
                rows.push(("refiner (causal)", name, r.gru_motion));
            } else {
                rows.push(("refiner (offline)", name, r.bigru_motion));
            }
        }
    }
    Ok(rows)
}

/// `--root-scale`: how far the root solve places people, per pose source.
fn root_scale_report(
    trials: &[LifterSequence],
    lifted: &blapose_lab::motion_sweep::Lifted,
    scenes: &[Scene],
    gru: Option<&[Vec<blapose_core::BoneLengths>]>,
) -> Result<()> {
    use blapose_core::bones::{adjust_sequence_per_frame, adjust_sequence_with, ZeroBonePolicy};
    use blapose_lab::motion_sweep::key;
    use blapose_lab::root_scale::{fit_scale, median_depth_ratio, mrpe_mm, RootPairs};
    let mut sources: Vec<(&str, Vec<RootPairs>)> = Vec::new();
    let solve = |t: &LifterSequence, poses: &[blapose_core::Pose], s: &Scene| {
        RootPairs::solve(&t.trial.subject, &t.trial.camera, poses, s)
    };
    sources.push((
        "true pose",
        trials
            .iter()
            .zip(scenes)
            .map(|(t, s)| solve(t, &t.target, s))
            .collect(),
    ));
    sources.push((
        "lifter as it is",
        trials
            .iter()
            .zip(scenes)
            .map(|(t, s)| solve(t, &lifted[&key(t)], s))
            .collect(),
    ));
    let mut true_lengths = Vec::new();
    for (t, s) in trials.iter().zip(scenes) {
        let adj = adjust_sequence_with(&lifted[&key(t)], &t.trial.gt, ZeroBonePolicy::KeepInput)?;
        true_lengths.push(solve(t, &adj, s));
    }
    sources.push(("lifter directions, true lengths", true_lengths));
    if let Some(g) = gru {
        let mut v = Vec::new();
        for ((t, s), l) in trials.iter().zip(scenes).zip(g) {
            let adj = adjust_sequence_per_frame(&lifted[&key(t)], l, ZeroBonePolicy::KeepInput)?;
            v.push(solve(t, &adj, s));
        }
        sources.push(("lifter directions, gru lengths", v));
    }
    let mut subjects: Vec<&str> = trials.iter().map(|t| t.trial.subject.as_str()).collect();
    subjects.dedup();
    let mut cameras: Vec<&str> = trials.iter().map(|t| t.trial.camera.as_str()).collect();
    cameras.sort();
    cameras.dedup();
    println!("| source | MRPE (mm) | k (all) | MRPE x k (mm) | MRPE, k from other subjects (mm) | median depth ratio |");
    println!("|---|---|---|---|---|---|");
    for (name, pairs) in &sources {
        let k = fit_scale(pairs);
        // Leave one subject out: each subject's roots scaled by the factor
        // fitted on the others.
        let mut held = Vec::new();
        for s in &subjects {
            let k_other = fit_scale(pairs.iter().filter(|p| p.subject != *s));
            let mine: Vec<&RootPairs> = pairs.iter().filter(|p| p.subject == *s).collect();
            held.extend(mine.into_iter().map(|p| {
                let mut p = p.clone();
                p.solved
                    .iter_mut()
                    .for_each(|v| *v = v.map(|x| x * k_other));
                p
            }));
        }
        println!(
            "| {name} | {:.1} | {k:.4} | {:.1} | {:.1} | {:.4} |",
            mrpe_mm(pairs, 1.0),
            mrpe_mm(pairs, k),
            mrpe_mm(&held, 1.0),
            median_depth_ratio(pairs)
        );
        for s in &subjects {
            let p: Vec<&RootPairs> = pairs.iter().filter(|p| p.subject == *s).collect();
            eprintln!(
                "  {name} {s}: k {:.4} median ratio {:.4}",
                fit_scale(p.iter().copied()),
                median_depth_ratio(p.iter().copied())
            );
        }
        for c in &cameras {
            let p: Vec<&RootPairs> = pairs.iter().filter(|p| p.camera == *c).collect();
            eprintln!(
                "  {name} camera {c}: k {:.4} median ratio {:.4}",
                fit_scale(p.iter().copied()),
                median_depth_ratio(p.iter().copied())
            );
        }
    }
    Ok(())
}

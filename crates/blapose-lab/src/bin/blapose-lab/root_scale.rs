//! `blapose-lab motion --root-scale`: where the root solve's error sits
//! ([`blapose_lab::root_scale`]): per pose source (the true pose, the
//! lifter as it is, its directions with the true or the GRU's lengths),
//! the error with and without one depth factor, per subject and camera,
//! and what a robust solve, a causal median and a learned depth correction
//! (each fitted on the other subjects) change.

use anyhow::Result;
use blapose_train::lifter::data::LifterSequence;
use blapose_train::motion_eval::Scene;

/// Human3.6M's focal length (pixels, about the same for its four cameras):
/// the robust solve's thresholds are given in pixels.
const H36M_FOCAL_PX: f64 = 1145.0;

/// `--root-scale`: how far the root solve places people, per pose source.
pub fn report(
    trials: &[LifterSequence],
    lifted: &blapose_lab::motion_sweep::Lifted,
    scenes: &[Scene],
    gru: Option<&[Vec<blapose_core::BoneLengths>]>,
) -> Result<()> {
    use blapose_core::bones::{adjust_sequence_per_frame, adjust_sequence_with, ZeroBonePolicy};
    use blapose_lab::motion_sweep::key;
    use blapose_lab::root_scale::{
        depth_split_mm, fit_scale, median_depth_ratio, mrpe_mm, RootPairs,
    };
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
    // The lifter's directions with the true and with the GRU's lengths,
    // adjusted once for every measurement below.
    let true_adjusted = trials
        .iter()
        .map(|t| adjust_sequence_with(&lifted[&key(t)], &t.trial.gt, ZeroBonePolicy::KeepInput))
        .collect::<Result<Vec<_>, _>>()?;
    let gru_adjusted = match gru {
        Some(g) => Some(
            trials
                .iter()
                .zip(g)
                .map(|(t, l)| {
                    adjust_sequence_per_frame(&lifted[&key(t)], l, ZeroBonePolicy::KeepInput)
                })
                .collect::<Result<Vec<_>, _>>()?,
        ),
        None => None,
    };
    let solve_all = |adjusted: &[Vec<blapose_core::Pose>]| -> Vec<RootPairs> {
        trials
            .iter()
            .zip(scenes)
            .zip(adjusted)
            .map(|((t, s), a)| solve(t, a, s))
            .collect()
    };
    let true_pairs = solve_all(&true_adjusted);
    sources.push(("lifter directions, true lengths", true_pairs.clone()));
    let gru_pairs = gru_adjusted.as_deref().map(solve_all);
    if let Some(p) = &gru_pairs {
        sources.push(("lifter directions, gru lengths", p.clone()));
    }
    let mut subjects: Vec<&str> = trials.iter().map(|t| t.trial.subject.as_str()).collect();
    subjects.dedup();
    // Robust solves and causal medians of the served pose sources.
    if let (Some(adjusted), Some(gru_pairs)) = (&gru_adjusted, &gru_pairs) {
        use blapose_lab::root_scale::{causal_median, place_roots_robust};
        for c_px in [5.0, 10.0, 20.0, 40.0] {
            let pairs: Vec<RootPairs> = trials
                .iter()
                .zip(scenes)
                .zip(adjusted)
                .map(|((t, s), a)| RootPairs {
                    subject: t.trial.subject.clone(),
                    camera: t.trial.camera.clone(),
                    solved: place_roots_robust(a, s, c_px / H36M_FOCAL_PX, 4),
                    truth: s.root.clone(),
                })
                .collect();
            let k = fit_scale(&pairs);
            println!(
                "| gru lengths, huber {c_px} px | {:.1} | {k:.4} | {:.1} | | |",
                mrpe_mm(&pairs, 1.0),
                mrpe_mm(&pairs, k)
            );
        }
        // A learned depth correction: fitted on the true-length solves of
        // the other subjects, applied to each subject's solves.
        {
            use blapose_lab::root_scale::{depth_features, DepthCorrection};
            let feats = |poses: &[Vec<blapose_core::Pose>]| -> Vec<Vec<Vec<f64>>> {
                poses
                    .iter()
                    .zip(scenes)
                    .map(|(a, s)| {
                        a.iter()
                            .zip(&s.rays)
                            .map(|(p, (r, _))| depth_features(r, p))
                            .collect()
                    })
                    .collect()
            };
            let true_feats = feats(&true_adjusted);
            let gru_feats = feats(adjusted);
            for lambda in [1.0, 100.0, 10000.0] {
                let mut held_true = Vec::new();
                let mut held_gru = Vec::new();
                for s in &subjects {
                    let samples = true_pairs
                        .iter()
                        .zip(&true_feats)
                        .filter(|(p, _)| p.subject != *s)
                        .flat_map(|(p, f)| {
                            p.solved
                                .iter()
                                .zip(&p.truth)
                                .zip(f)
                                .filter(|((a, _), _)| a[2] > 0.1)
                                .map(|((a, b), f)| (f.as_slice(), (b[2] / a[2]).ln()))
                        });
                    let Some(model) = DepthCorrection::fit(samples, lambda) else {
                        continue;
                    };
                    for (pairs, fs, out) in [
                        (&true_pairs, &true_feats, &mut held_true),
                        (gru_pairs, &gru_feats, &mut held_gru),
                    ] {
                        for (p, f) in pairs.iter().zip(fs).filter(|(p, _)| p.subject == *s) {
                            let mut p = p.clone();
                            for (v, f) in p.solved.iter_mut().zip(f) {
                                let k = model.factor(f);
                                *v = v.map(|x| x * k);
                            }
                            out.push(p);
                        }
                    }
                }
                println!(
                    "| learned depth, lambda {lambda}: true lengths | {:.1} | | | | |",
                    mrpe_mm(&held_true, 1.0)
                );
                println!(
                    "| learned depth, lambda {lambda}: gru lengths | {:.1} | | | | |",
                    mrpe_mm(&held_gru, 1.0)
                );
            }
        }
        for w in [5, 11, 25, 51, 101] {
            let pairs: Vec<RootPairs> = gru_pairs
                .iter()
                .map(|p| RootPairs {
                    solved: causal_median(&p.solved, w),
                    ..p.clone()
                })
                .collect();
            let k = fit_scale(&pairs);
            println!(
                "| gru lengths, causal median {w} | {:.1} | {k:.4} | {:.1} | | |",
                mrpe_mm(&pairs, 1.0),
                mrpe_mm(&pairs, k)
            );
        }
    }
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
        let [dz, dxy, bias, wobble] = depth_split_mm(pairs);
        eprintln!(
            "  {name}: |dz| {dz:.1} |dxy| {dxy:.1} trial bias rms {bias:.1} wobble rms {wobble:.1}"
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

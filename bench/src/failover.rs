//! The failover check behind `deploy/failover-test.sh`: many sessions
//! streaming through a load balancer while one replica goes away.
//!
//! Every session replays one of the example sequences with
//! [`replay_across`], which keeps the latest session token and, when its
//! stream fails, resumes the session (through the balancer, which sends it
//! to a replica that is up) and re-sends the frames after the token. The
//! check runs the same sessions twice: once undisturbed (the reference),
//! once with a signal sent to one replica's process after a share of all
//! frames was answered. It then counts, per session, frames without an
//! answer (lost), frames the session's final state counted more than once
//! or answered more than once (duplicated), the largest difference of any
//! answered bone length from the reference run, and the longest wait
//! between two answers the client saw.
//!
//! Comparing against a reference run through the same balancer, rather
//! than against stored numbers, keeps the check honest for any weights:
//! an uninterrupted session's answers do not depend on the replica.

use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use blapose_client::{replay_across, Adjusted, Client, ClientError, ReplayOptions, Sequence};
use serde::Serialize;

/// A session's outcome in one run.
#[derive(Debug, Clone)]
pub struct SessionRun {
    /// Frames of the sequence.
    pub frames: usize,
    /// What the replay returned.
    pub result: Result<Adjusted, String>,
    /// Longest time between two consecutive answers (or between the start
    /// and the first answer).
    pub max_gap: Duration,
}

/// Run `sessions` concurrent replays through `client`, session `i`
/// replaying `sequences[i % len]`. `on_progress` sees the number of frames
/// answered so far, all sessions together, after every answer.
pub async fn run_sessions(
    client: &Client,
    sequences: &[Arc<Sequence>],
    sessions: usize,
    options: &ReplayOptions,
    on_progress: Arc<dyn Fn(usize) + Send + Sync>,
) -> Vec<SessionRun> {
    let answered = Arc::new(AtomicUsize::new(0));
    let mut tasks = Vec::with_capacity(sessions);
    for i in 0..sessions {
        let client = client.clone();
        let seq = sequences[i % sequences.len()].clone();
        let mut options = options.clone();
        options.label = Some(format!("failover-{i}"));
        let answered = answered.clone();
        let on_progress = on_progress.clone();
        tasks.push(tokio::spawn(async move {
            let last = Mutex::new((Instant::now(), Duration::ZERO, 0usize));
            let result = replay_across(std::slice::from_ref(&client), &seq, &options, |n| {
                let mut last = last.lock().unwrap_or_else(|e| e.into_inner());
                let now = Instant::now();
                last.1 = last.1.max(now - last.0);
                last.0 = now;
                let new = n.saturating_sub(last.2);
                last.2 = n;
                let total = answered.fetch_add(new, Ordering::Relaxed) + new;
                on_progress(total);
            })
            .await
            .map_err(|e: ClientError| e.to_string());
            let max_gap = last.into_inner().unwrap_or_else(|e| e.into_inner()).1;
            SessionRun {
                frames: seq.len(),
                result,
                max_gap,
            }
        }));
    }
    let mut runs = Vec::with_capacity(sessions);
    for task in tasks {
        runs.push(task.await.unwrap_or_else(|e| SessionRun {
            frames: 0,
            result: Err(format!("the session's task failed: {e}")),
            max_gap: Duration::ZERO,
        }));
    }
    runs
}

/// What a disturbed run did to its sessions, against the reference run.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct FailoverReport {
    /// Sessions streamed.
    pub sessions: usize,
    /// Sessions whose replay failed (each such session's unanswered frames
    /// count as lost).
    pub sessions_failed: usize,
    /// Sessions whose stream failed at least once and were resumed.
    pub sessions_resumed: usize,
    /// Frames of all sequences.
    pub frames: usize,
    /// Frames without an answer.
    pub frames_lost: usize,
    /// Frames answered more than once, or counted more than once by the
    /// session's final state (its `frames_seen` above the sequence's
    /// length).
    pub frames_duplicated: usize,
    /// Largest difference of any bone length answered, against the
    /// reference run's answer to the same frame, in metres.
    pub max_length_diff_m: f64,
    /// Largest difference of any adjusted joint coordinate, in metres.
    pub max_pose_diff_m: f64,
    /// Longest wait between two answers a session saw, in milliseconds.
    pub gap_ms_max: f64,
    /// The same in the reference run, for comparison.
    pub reference_gap_ms_max: f64,
    /// The first error of a failed session, if any.
    pub first_error: Option<String>,
}

/// Compare `disturbed` with `reference` (same sessions, same order).
pub fn compare(reference: &[SessionRun], disturbed: &[SessionRun]) -> FailoverReport {
    let mut report = FailoverReport {
        sessions: disturbed.len(),
        sessions_failed: 0,
        sessions_resumed: 0,
        frames: 0,
        frames_lost: 0,
        frames_duplicated: 0,
        max_length_diff_m: 0.0,
        max_pose_diff_m: 0.0,
        gap_ms_max: 0.0,
        reference_gap_ms_max: 0.0,
        first_error: None,
    };
    for (reference, run) in reference.iter().zip(disturbed) {
        report.frames += run.frames;
        report.gap_ms_max = report.gap_ms_max.max(run.max_gap.as_secs_f64() * 1e3);
        report.reference_gap_ms_max = report
            .reference_gap_ms_max
            .max(reference.max_gap.as_secs_f64() * 1e3);
        let done = match &run.result {
            Ok(done) => done,
            Err(e) => {
                report.sessions_failed += 1;
                report.frames_lost += run.frames;
                report.first_error.get_or_insert_with(|| e.clone());
                continue;
            }
        };
        if done.resumes > 0 {
            report.sessions_resumed += 1;
        }
        let answered = done.first_frame + done.adjusted.len();
        report.frames_lost += done.first_frame + run.frames.saturating_sub(answered);
        report.frames_duplicated += answered.saturating_sub(run.frames);
        let seen = done.session.as_ref().map_or(0, |s| s.frames_seen as usize);
        report.frames_duplicated += seen.saturating_sub(run.frames);
        let Ok(expected) = &reference.result else {
            continue;
        };
        let pairs = (done.first_frame..answered).filter_map(|t| {
            let i = t.checked_sub(expected.first_frame)?;
            Some((
                (
                    &done.bone_lengths[t - done.first_frame],
                    expected.bone_lengths.get(i)?,
                ),
                (
                    &done.adjusted[t - done.first_frame],
                    expected.adjusted.get(i)?,
                ),
            ))
        });
        for ((lengths, expected_lengths), (pose, expected_pose)) in pairs {
            for (a, b) in lengths.iter().zip(expected_lengths.iter()) {
                report.max_length_diff_m = report.max_length_diff_m.max(f64::from((a - b).abs()));
            }
            for (a, b) in pose.iter().flatten().zip(expected_pose.iter().flatten()) {
                report.max_pose_diff_m = report.max_pose_diff_m.max(f64::from((a - b).abs()));
            }
        }
    }
    report
}

/// Frames per second over a whole run: answered frames over the time from
/// the first session's start to the last one's end.
pub fn frames_per_second(runs: &[SessionRun], elapsed: Duration) -> f64 {
    let answered: usize = runs
        .iter()
        .filter_map(|r| r.result.as_ref().ok())
        .map(|d| d.adjusted.len())
        .sum();
    answered as f64 / elapsed.as_secs_f64().max(1e-9)
}

#[cfg(test)]
mod tests {
    use super::*;
    use blapose_client::ModelKind;

    fn adjusted(first: usize, lengths: &[f32], seen: u64, resumes: u32) -> Adjusted {
        let n = lengths.len();
        Adjusted {
            model: ModelKind::Gru,
            first_frame: first,
            adjusted: vec![[[0.0; 3]; 17]; n],
            bone_lengths: lengths.iter().map(|&l| [l; 16]).collect(),
            lifter: None,
            lifted: Vec::new(),
            elapsed: Duration::from_secs(1),
            session: Some(blapose_client::SessionSummary {
                session_id: "s".into(),
                frames_seen: seen,
                bone_lengths: None,
            }),
            resumes,
            camera: None,
            placement: None,
        }
    }

    fn run(result: Result<Adjusted, String>, frames: usize, gap_ms: u64) -> SessionRun {
        SessionRun {
            frames,
            result,
            max_gap: Duration::from_millis(gap_ms),
        }
    }

    #[test]
    fn an_identical_run_loses_and_duplicates_nothing() {
        let reference = [run(Ok(adjusted(0, &[0.4, 0.41, 0.42], 3, 0)), 3, 20)];
        let same = [run(Ok(adjusted(0, &[0.4, 0.41, 0.42], 3, 1)), 3, 350)];
        let r = compare(&reference, &same);
        assert_eq!((r.frames_lost, r.frames_duplicated), (0, 0));
        assert_eq!(r.max_length_diff_m, 0.0);
        assert_eq!((r.sessions_resumed, r.sessions_failed), (1, 0));
        assert_eq!((r.gap_ms_max, r.reference_gap_ms_max), (350.0, 20.0));
    }

    #[test]
    fn lost_duplicated_and_changed_frames_are_counted() {
        let reference = [
            run(Ok(adjusted(0, &[0.4, 0.41, 0.42], 3, 0)), 3, 20),
            run(Ok(adjusted(0, &[0.4, 0.41, 0.42], 3, 0)), 3, 20),
            run(Ok(adjusted(0, &[0.4, 0.41, 0.42], 3, 0)), 3, 20),
        ];
        let disturbed = [
            // The last frame unanswered; the second answered differently.
            run(Ok(adjusted(0, &[0.4, 0.415], 2, 1)), 3, 20),
            // A frame processed twice by the final state.
            run(Ok(adjusted(0, &[0.4, 0.41, 0.42], 4, 1)), 3, 20),
            run(Err("gone".into()), 3, 20),
        ];
        let r = compare(&reference, &disturbed);
        assert_eq!(r.frames, 9);
        assert_eq!(r.frames_lost, 1 + 3);
        assert_eq!(r.frames_duplicated, 1);
        assert!((r.max_length_diff_m - 0.005).abs() < 1e-6, "{r:?}");
        assert_eq!(r.sessions_failed, 1);
        assert_eq!(r.first_error.as_deref(), Some("gone"));
    }
}

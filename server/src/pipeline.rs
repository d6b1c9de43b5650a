//! The batcher thread: each batch taken from the queue goes through the
//! stages in the order a frame flows, prepare -> step -> answer, and every
//! frame is answered on its oneshot.
//!
//! [`start`] warms every model up (so a server reports SERVING only with
//! models that work) and starts the thread that drains the queue
//! ([`crate::batch`]). For each batch: [`crate::prepare`] finishes the rows
//! (missing joints held, poses lifted; it needs the state the session's
//! previous frame left, which is why it runs here and not before the
//! queue), [`crate::step`] runs one batched GRU step per model, and
//! [`crate::answer`] commits each finite row to its session and builds its
//! answer. A row refused at any stage is answered there and skips the
//! rest, leaving its session as it was.

use std::sync::Arc;
use std::time::Instant;

use blapose_core::Pose;

use crate::answer;
use crate::backend::{Backend, BackendError};
use crate::batch::{Batcher, BatcherConfig, Batches, Queued};
use crate::frame::{StepError, StepResult};
use crate::metrics;
use crate::models::LoadedLifter;
use crate::prepare::{self, LiftScratch};
use crate::step::{self, OnlineBackends, StepBuffers};

/// Warm every model (and the server lifter) up and start the batcher
/// thread.
pub fn start<B: Backend>(
    mut backends: OnlineBackends<B>,
    config: BatcherConfig,
    lifter: Option<Arc<LoadedLifter>>,
) -> Result<Batcher, BackendError> {
    step::warm_up(&mut backends.default)?;
    if let Some(camera_aware) = &mut backends.camera_aware {
        step::warm_up(camera_aware)?;
    }
    if let Some(lifter) = &lifter {
        prepare::warm_up_lifter(lifter)?;
    }
    Batcher::start(config, move |batches| run(batches, backends, lifter))
        .map_err(|e| BackendError::Model(format!("cannot start the batcher thread: {e}")))
}

/// What the thread keeps between batches (no allocation per batch).
struct Scratch {
    step: StepBuffers,
    lift: LiftScratch,
    /// For each batch index, the lifted pose (lifting rows that succeeded).
    lifted: Vec<Option<Pose>>,
}

fn run<B: Backend>(
    batches: Batches,
    mut backends: OnlineBackends<B>,
    lifter: Option<Arc<LoadedLifter>>,
) {
    let max = batches.config().max_batch;
    let mut scratch = Scratch {
        step: StepBuffers::new(max),
        lift: LiftScratch::default(),
        lifted: Vec::with_capacity(max),
    };
    let mut batch: Vec<Queued> = Vec::with_capacity(max);
    while batches.next(&mut batch) {
        run_batch(
            &mut backends,
            &mut batch,
            &mut scratch,
            lifter.as_deref(),
            &batches,
        );
    }
}

/// One batch through prepare, step and answer.
fn run_batch<B: Backend>(
    backends: &mut OnlineBackends<B>,
    batch: &mut Vec<Queued>,
    scratch: &mut Scratch,
    lifter: Option<&LoadedLifter>,
    batches: &Batches,
) {
    let started = Instant::now();
    // Prepare: `answers[i]` is set once row i is answered, by any stage.
    let mut answers: Vec<Option<StepResult>> = batch
        .iter_mut()
        .map(|item| prepare::fill_missing(&mut item.job))
        .collect();
    prepare::lift(
        lifter,
        batch,
        &mut answers,
        &mut scratch.lifted,
        &mut scratch.lift,
    );
    for item in batch.iter() {
        metrics::queue_wait(started.saturating_duration_since(item.enqueued));
    }
    // Step.
    let n = step::run(backends, batch, &mut answers, &mut scratch.step);
    // Answer: commit each stepped row still unanswered.
    for (i, hidden, lengths) in scratch.step.stepped() {
        if answers[i].is_none() {
            let lifted = scratch.lifted[i];
            answers[i] = Some(answer::commit(&batch[i].job, hidden, lengths, lifted));
        }
    }
    metrics::batch(n, started.elapsed(), batches.queue_len());
    for (item, answer) in batch.drain(..).zip(answers) {
        // `None` cannot happen (every row was answered above); be explicit
        // rather than panic.
        let answer = answer.unwrap_or_else(|| Err(StepError::Model("frame was not run".into())));
        // A dropped receiver means the stream went away; nothing to do.
        let _ = item.job.reply.send(answer);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::backend::INPUT_DIM;
    use crate::batch::SubmitError;
    use crate::fakes::{answer, config, gated_batcher, job, session_config, start, Fake};
    use crate::session::{SessionCamera, SessionConfig, SessionStore};
    use blapose_core::level::LevelCamera;
    use blapose_model::input::{ModelInput, ViewCalibration};
    use std::sync::atomic::Ordering;
    use std::time::Duration;

    #[tokio::test]
    async fn camera_sessions_run_rectified_on_the_camera_aware_model() {
        let (default, camera_aware) = (Fake::default(), Fake::default());
        let (default_log, aware_log) = (default.log.clone(), camera_aware.log.clone());
        let backends = OnlineBackends {
            default,
            camera_aware: Some(camera_aware),
        };
        let batcher = super::start(backends, config(8, 50, 100), None).unwrap();
        let (store, _g) = SessionStore::new(10, Duration::from_secs(60));
        let view = ViewCalibration {
            up: [0.0, -0.95, -0.31],
            focal: [1150.0, 1150.0],
            principal: [500.0, 510.0],
            image_size: (1000, 1000),
            camera_height: None,
            lens: None,
        };
        let (up, focal, principal) = (view.up, view.focal, view.principal);
        let level = LevelCamera::from_pixels(up, focal, principal, 1000, 1000).unwrap();
        let plain = store.open(session_config()).unwrap();
        let aware = store
            .open(SessionConfig {
                camera: Some(SessionCamera {
                    calibration: Default::default(),
                    input: ModelInput::level().camera(&view).unwrap(),
                    view: view.clone(),
                }),
                ..session_config()
            })
            .unwrap();
        let _guards = [batcher.stream_guard(), batcher.stream_guard()];
        let (j1, r1) = job(&plain.session, plain.epoch, 0.25, 0.5);
        let (j2, r2) = job(&aware.session, aware.epoch, 0.25, 0.5);
        batcher.submit(j1).unwrap();
        batcher.submit(j2).unwrap();
        let (a, b) = (r1.await.unwrap().unwrap(), r2.await.unwrap().unwrap());
        // What the camera-aware model must have been given.
        let mut rectified = [0.0f32; INPUT_DIM];
        (rectified[0], rectified[1]) = (0.25, 0.5);
        level.rectify_frames(&mut rectified);
        assert_ne!(rectified[..2], [0.25, 0.5]);
        // Each log starts with its model's warm-up step.
        assert_eq!(default_log.lock().unwrap()[1..], [vec![0.5]]);
        assert_eq!(aware_log.lock().unwrap()[1..], [vec![rectified[1]]]);
        assert_eq!(a.lengths.unwrap()[0], 0.25);
        assert_eq!(b.lengths.unwrap()[0], rectified[0]);
        batcher.close();
    }

    #[tokio::test]
    async fn bad_rows_and_failed_steps_leave_sessions_untouched() {
        let fake = Fake::default();
        let fail = fake.fail.clone();
        let batcher = start(fake, config(8, 0, 100)).unwrap();
        let (store, _g) = SessionStore::new(10, Duration::from_secs(60));
        let a = store.open(session_config()).unwrap();
        let b = store.open(session_config()).unwrap();
        let (j, rx) = job(&a.session, a.epoch, 2.0, 0.0);
        batcher.submit(j).unwrap();
        rx.await.unwrap().unwrap();
        // A poisoned row for a, next to a good row for b.
        let (mut ja, ra) = job(&a.session, a.epoch, 5.0, 0.0);
        ja.input[2] = f32::NAN;
        let (jb, rb) = job(&b.session, b.epoch, 3.0, 1.0);
        batcher.submit(ja).unwrap();
        batcher.submit(jb).unwrap();
        assert_eq!(ra.await.unwrap(), Err(StepError::NonFinite));
        assert_eq!(rb.await.unwrap().unwrap().frames_seen, 1);
        {
            let st = a.session.lock();
            assert_eq!(st.frames_seen(), 1);
            assert!(st.hidden.iter().all(|&v| v == 2.0));
        }
        // A failing backend answers INTERNAL and changes nothing.
        fail.store(true, Ordering::Relaxed);
        let (j, rx) = job(&a.session, a.epoch, 7.0, 0.0);
        batcher.submit(j).unwrap();
        let err = rx.await.unwrap().unwrap_err();
        assert!(matches!(err, StepError::Model(_)));
        assert_eq!(err.code(), tonic::Code::Internal);
        assert!(a.session.lock().hidden.iter().all(|&v| v == 2.0));
        fail.store(false, Ordering::Relaxed);
        let (j, rx) = job(&a.session, a.epoch, 1.0, 0.0);
        batcher.submit(j).unwrap();
        assert_eq!(rx.await.unwrap().unwrap().frames_seen, 2);
    }

    #[tokio::test]
    async fn a_row_that_fails_the_whole_step_fails_only_its_own_frame() {
        // The first frame's step holds at the gate while the next two are
        // queued, so they share the next batch.
        let (batcher, gate, log) = gated_batcher(config(8, 0, 100));
        let (store, _g) = SessionStore::new(10, Duration::from_secs(60));
        let a = store.open(session_config()).unwrap();
        let b = store.open(session_config()).unwrap();
        let c = store.open(session_config()).unwrap();
        let (jc, rc) = job(&c.session, c.epoch, 1.0, 2.0);
        batcher.submit(jc).unwrap();
        gate.wait_entered(1);
        let (mut ja, ra) = job(&a.session, a.epoch, 4.0, 0.0);
        ja.input[2] = 999.0;
        let (jb, rb) = job(&b.session, b.epoch, 3.0, 1.0);
        batcher.submit(ja).unwrap();
        batcher.submit(jb).unwrap();
        gate.set_open(true);
        answer(rc).await.unwrap();
        assert!(matches!(answer(ra).await, Err(StepError::Model(_))));
        let ob = answer(rb).await.unwrap();
        assert_eq!(ob.frames_seen, 1);
        assert_eq!(ob.lengths.unwrap()[0], 3.0);
        assert_eq!(a.session.lock().frames_seen(), 0);
        assert!(a.session.lock().hidden.iter().all(|&v| v == 0.0));
        // The retry ran b alone (a batch of one after the failed pair).
        assert_eq!(log.lock().unwrap().last().map(Vec::len), Some(1));
    }

    #[tokio::test]
    async fn frames_of_a_superseded_stream_are_refused() {
        let batcher = start(Fake::default(), config(8, 0, 100)).unwrap();
        let (store, _g) = SessionStore::new(10, Duration::from_secs(60));
        let a = store.open(session_config()).unwrap();
        let resumed = store.resume(&a.session.id().to_string()).unwrap();
        let (j, rx) = job(&a.session, a.epoch, 1.0, 0.0);
        batcher.submit(j).unwrap();
        assert_eq!(rx.await.unwrap(), Err(StepError::Superseded));
        let (j, rx) = job(&resumed.session, resumed.epoch, 1.0, 0.0);
        batcher.submit(j).unwrap();
        assert_eq!(rx.await.unwrap().unwrap().frames_seen, 1);
    }

    #[test]
    fn warm_up_rejects_a_model_that_produces_nan() {
        struct Nan;
        impl Backend for Nan {
            fn step(
                &mut self,
                _: &[f32],
                h: &mut [f32],
                _: &mut [f32],
                _: usize,
            ) -> Result<(), BackendError> {
                h[0] = f32::NAN;
                Ok(())
            }
        }
        assert!(start(Nan, config(4, 0, 4)).is_err());
    }

    // The queue's rules ([`crate::batch`]), through the whole batcher.

    #[tokio::test]
    async fn frames_run_in_order_at_most_one_per_session_per_batch() {
        let fake = Fake::default();
        let log = fake.log.clone();
        // A delay no test waits out: a batch runs only once every attached
        // stream has a frame waiting.
        let batcher = start(fake, config(8, 3_600_000, 1000)).unwrap();
        let (store, _g) = SessionStore::new(100, Duration::from_secs(60));
        let sessions: Vec<_> = (0..5)
            .map(|_| store.open(session_config()).unwrap())
            .collect();
        let _guards: Vec<_> = sessions.iter().map(|_| batcher.stream_guard()).collect();
        let mut rxs = Vec::new();
        // 20 pipelined frames per session, interleaved; values 1..=20.
        for f in 1..=20 {
            for (s, a) in sessions.iter().enumerate() {
                let (j, rx) = job(&a.session, a.epoch, f as f32, s as f32);
                batcher.submit(j).unwrap();
                rxs.push((s, f, rx));
            }
        }
        let mut expected_sum = [0.0f32; 5];
        for (s, f, rx) in rxs {
            let out = answer(rx).await.unwrap();
            expected_sum[s] += f as f32;
            // Running sum of inputs as state => in-order, exactly-once.
            assert_eq!(out.frames_seen, f as u64, "session {s}");
            let mean_of_running_sums: f32 =
                (1..=f).map(|k| (k * (k + 1) / 2) as f32).sum::<f32>() / f as f32;
            assert!(
                (out.lengths.unwrap()[0] - mean_of_running_sums).abs() < 1e-3,
                "session {s} frame {f}"
            );
        }
        for (s, a) in sessions.iter().enumerate() {
            assert_eq!(a.session.lock().hidden[5], expected_sum[s]);
        }
        let log = log.lock().unwrap();
        // The first entry is the warm-up step.
        let log = &log[1..];
        assert_eq!(log.iter().map(Vec::len).sum::<usize>(), 100);
        for tags in log.iter() {
            assert!(tags.len() <= 8);
            let mut sorted = tags.clone();
            sorted.sort_by(f32::total_cmp);
            sorted.dedup();
            assert_eq!(
                sorted.len(),
                tags.len(),
                "a session appears twice in batch {tags:?}"
            );
        }
        // Every stream always has a frame waiting until the last batch, so
        // every batch is full-width: one frame of each of the 5 sessions.
        assert!(log.iter().all(|t| t.len() == 5), "batches: {log:?}");
        assert_eq!(log.len(), 20);
    }

    #[tokio::test]
    async fn full_queue_refuses_instead_of_dropping() {
        let (batcher, gate, _) = gated_batcher(config(1, 0, 3));
        let (store, _g) = SessionStore::new(100, Duration::from_secs(60));
        let a = store.open(session_config()).unwrap();
        let mut accepted = Vec::new();
        let mut refused = 0;
        // The first frame's step holds at the gate: 3 more fill the queue.
        let (j, rx) = job(&a.session, a.epoch, 1.0, 0.0);
        batcher.submit(j).unwrap();
        accepted.push(rx);
        gate.wait_entered(1);
        for f in 1..10 {
            let (j, rx) = job(&a.session, a.epoch, 1.0, f as f32);
            match batcher.submit(j) {
                Ok(()) => accepted.push(rx),
                Err(e) => {
                    assert_eq!(e, SubmitError::QueueFull { capacity: 3 });
                    assert_eq!(e.code(), tonic::Code::ResourceExhausted);
                    refused += 1;
                }
            }
        }
        assert_eq!(refused, 6);
        let recorder = crate::metrics::test_recorder();
        let (j, _rx) = job(&a.session, a.epoch, 1.0, 10.0);
        let again = ::metrics::with_local_recorder(&recorder, || batcher.submit(j));
        assert_eq!(again, Err(SubmitError::QueueFull { capacity: 3 }));
        assert_eq!(
            crate::metrics::limited_count(&recorder, "queue_capacity"),
            1
        );
        gate.set_open(true);
        let n = accepted.len();
        // Every accepted frame is answered; the state counts exactly those.
        for (k, rx) in accepted.into_iter().enumerate() {
            assert_eq!(answer(rx).await.unwrap().frames_seen, k as u64 + 1);
        }
        assert_eq!(a.session.lock().frames_seen(), n as u64);
    }

    #[tokio::test]
    async fn lone_stream_does_not_wait_for_the_queue_delay() {
        let fake = Fake::default();
        let log = fake.log.clone();
        // A delay no test waits out: the frames are answered only because
        // a lone stream does not wait for company.
        let batcher = start(fake, config(64, 3_600_000, 100)).unwrap();
        let (store, _g) = SessionStore::new(10, Duration::from_secs(60));
        let a = store.open(session_config()).unwrap();
        let _guard = batcher.stream_guard();
        for f in 0..20 {
            let (j, rx) = job(&a.session, a.epoch, 1.0, f as f32);
            batcher.submit(j).unwrap();
            answer(rx).await.unwrap();
        }
        // Warm-up, then one batch per frame.
        assert_eq!(log.lock().unwrap().len(), 21);
    }

    #[tokio::test]
    async fn partial_batch_waits_for_other_streams_up_to_the_delay() {
        let fake = Fake::default();
        let log = fake.log.clone();
        // A delay no test waits out: a's frame can only run once b's frame
        // is there too, in the same batch.
        let batcher = start(fake, config(64, 3_600_000, 100)).unwrap();
        let (store, _g) = SessionStore::new(10, Duration::from_secs(60));
        let a = store.open(session_config()).unwrap();
        let b = store.open(session_config()).unwrap();
        let _ga = batcher.stream_guard();
        let _gb = batcher.stream_guard();
        let (ja, ra) = job(&a.session, a.epoch, 1.0, 0.0);
        batcher.submit(ja).unwrap();
        let (jb, rb) = job(&b.session, b.epoch, 1.0, 1.0);
        batcher.submit(jb).unwrap();
        answer(ra).await.unwrap();
        answer(rb).await.unwrap();
        assert_eq!(log.lock().unwrap()[1..], [vec![0.0, 1.0]]);
        drop(batcher);

        // With only stream a's frame ever arriving, the delay ends the wait
        // (how long it waits is `the_batching_rule`'s business).
        let fake = Fake::default();
        let log = fake.log.clone();
        let batcher = start(fake, config(64, 10, 100)).unwrap();
        let _ga = batcher.stream_guard();
        let _gb = batcher.stream_guard();
        let (ja, ra) = job(&a.session, a.epoch, 1.0, 0.0);
        batcher.submit(ja).unwrap();
        answer(ra).await.unwrap();
        assert_eq!(log.lock().unwrap()[1..], [vec![0.0]]);
    }

    #[tokio::test]
    async fn close_drains_every_queued_frame_then_refuses() {
        // The gate holds the first step, so frames are still queued when
        // the batcher closes.
        let (batcher, gate, _) = gated_batcher(config(2, 0, 100));
        let (store, _g) = SessionStore::new(10, Duration::from_secs(60));
        let a = store.open(session_config()).unwrap();
        let mut rxs = Vec::new();
        for f in 0..10 {
            let (j, rx) = job(&a.session, a.epoch, 1.0, f as f32);
            batcher.submit(j).unwrap();
            rxs.push(rx);
        }
        gate.wait_entered(1);
        assert!(batcher.queue_len() >= 9, "frames are still queued");
        batcher.close();
        let (j, _rx) = job(&a.session, a.epoch, 1.0, 0.0);
        assert_eq!(batcher.submit(j), Err(SubmitError::ShuttingDown));
        gate.set_open(true);
        tokio::task::spawn_blocking(move || batcher.join())
            .await
            .unwrap();
        for (k, rx) in rxs.into_iter().enumerate() {
            assert_eq!(rx.await.unwrap().unwrap().frames_seen, k as u64 + 1);
        }
    }

    #[tokio::test]
    async fn one_clients_overload_is_refused_to_that_client_only() {
        use crate::quota::{ClientId, QuotaError};
        let (batcher, gate, _) = gated_batcher(config(1, 0, 100));
        let (store, _g) = SessionStore::new(10, Duration::from_secs(60));
        let greedy = ClientId::of("peer:greedy");
        let a = store.open_for(session_config(), greedy, 10).unwrap();
        let b = store.open_for(session_config(), greedy, 10).unwrap();
        let other = store
            .open_for(session_config(), ClientId::of("peer:other"), 10)
            .unwrap();
        let mut rxs = Vec::new();
        let mut submit = |s: &crate::session::Attachment| {
            let (j, rx) = job(&s.session, s.epoch, 1.0, 0.0);
            let result = batcher.submit_limited(j, 3, 4);
            rxs.push(rx);
            result
        };
        // The first frame is in the (held) step; the next ones wait.
        submit(&a).unwrap();
        gate.wait_entered(1);
        for _ in 0..3 {
            submit(&a).unwrap();
        }
        assert_eq!(
            submit(&a),
            Err(SubmitError::Quota(QuotaError::SessionFrames { limit: 3 }))
        );
        submit(&b).unwrap();
        let refused = submit(&b).unwrap_err();
        assert_eq!(
            refused,
            SubmitError::Quota(QuotaError::ClientFrames { limit: 4 })
        );
        assert_eq!(refused.code(), tonic::Code::ResourceExhausted);
        assert!(refused
            .to_string()
            .contains("--max-queued-frames-per-client"));
        // Another client's frame is queued as usual.
        submit(&other).unwrap();
        gate.set_open(true);
        tokio::task::spawn_blocking(move || batcher.join())
            .await
            .unwrap();
        let answered = {
            let mut n = 0;
            for rx in rxs {
                if rx.await.is_ok() {
                    n += 1;
                }
            }
            n
        };
        assert_eq!(answered, 6, "every queued frame answered");
    }
}

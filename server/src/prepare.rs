//! The prepare stage: a validated frame becomes the row the model reads,
//! exactly as the weights' input contract says.
//!
//! What a set of weights expects (screen coordinates, or keypoints
//! undistorted and rectified to the camera's level twin and perhaps scaled
//! to the floor) is written by the trainer into their metadata and read
//! once at load into a [`ModelInput`]. A calibration becomes the session's
//! (or request's) [`InputCamera`] through [`ModelInput::camera`] once, as
//! it is validated ([`validate::camera`]; a session keeps it for its
//! life), and this module is the only place the server applies it: every
//! frame is fed through [`InputCamera::prepare_frames`] ([`model_row`],
//! [`sequence`]). Streams and `AdjustSequence` share the recipe, so the
//! online and the offline models read a camera alike.
//!
//! [`ModelInput`]: blapose_model::input::ModelInput
//! [`ModelInput::camera`]: blapose_model::input::ModelInput::camera
//! [`InputCamera`]: blapose_model::input::InputCamera
//! [`InputCamera::prepare_frames`]: blapose_model::input::InputCamera::prepare_frames
//!
//! A stream's preparation also reads the session's past: a missing joint is
//! read held at its last detection ([`fill_missing`]), and a server-lifter
//! session's pose comes from the lifter's window of the session's earlier
//! frames ([`lift`]). Both depend on which earlier frames were *accepted*,
//! known only once the previous frame has been through its step, so they
//! run on the batcher thread when a batch is taken ([`crate::pipeline`]), where
//! a session's frames are processed strictly one after another. Each
//! lifting row's window plus its new frame is copied out (the session's
//! window is not touched), all of a batch's windows run through the lifter
//! in one call, and every pose is checked as a client's pose would be; the
//! new frame enters the window only with its GRU state
//! ([`crate::answer::commit`]), so a frame refused anywhere leaves the
//! window as it was. A lifter failure, even a panic, fails only the rows it
//! concerns. The lifter windows keep the keypoints as sent: rectification
//! is the last step, as a row is gathered for the model.

use std::panic::{catch_unwind, AssertUnwindSafe};
use std::time::Instant;

use blapose_core::missing::hold_fill_sequence;
use blapose_core::Pose;
use blapose_lifters::trained::FRAME_VALUES;
use blapose_lifters::TrainedLifter;

use crate::answer;
use crate::backend::BackendError;
use crate::batch::Queued;
use crate::frame::{FrameJob, StepError, StepResult};
use crate::metrics;
use crate::models::LoadedLifter;
use crate::validate::{self, ValidSequence};

/// One frame's model input (`out`, [`crate::backend::INPUT_DIM`] values):
/// the job's keypoints (missing joints already held), through its
/// session's camera when it has one.
pub fn model_row(job: &FrameJob, out: &mut [f32]) {
    out.copy_from_slice(&job.input);
    let camera = job.session.config().camera.as_ref();
    if let Some(camera) = camera.and_then(|c| c.input.as_ref()) {
        camera.prepare_frames(out);
    }
}

/// A whole sequence ready for the model.
#[derive(Debug, Clone, PartialEq)]
pub struct PreparedSequence {
    /// Which model to run.
    pub model: blapose_core::ModelKind,
    /// `frames x INPUT_DIM` model inputs: missing joints held, and prepared
    /// for the camera-aware models when the request sent a calibration.
    pub inputs: Vec<f32>,
    /// One pose per frame.
    pub poses: Vec<Pose>,
    /// Whether the request sent a calibration (the camera-aware models
    /// serve it).
    pub camera_aware: bool,
}

/// Prepare a validated `AdjustSequence` request for the model: hold
/// missing joints (at their last detection; before it, at their first),
/// then feed the frames through the request's camera (built by
/// [`validate::camera`] as the camera-aware models' contract says).
pub fn sequence(seq: ValidSequence) -> PreparedSequence {
    let ValidSequence {
        model,
        mut inputs,
        present,
        poses,
        camera,
    } = seq;
    if present.iter().any(|&p| !p) {
        hold_fill_sequence(&mut inputs, &present);
    }
    let camera_aware = camera.is_some();
    if let Some(camera) = camera.and_then(|c| c.input) {
        camera.prepare_frames(&mut inputs);
    }
    PreparedSequence {
        model,
        inputs,
        poses,
        camera_aware,
    }
}

/// Fill the frame's missing joints from its session's held ones. A frame
/// without a detected joint is answered here ([`answer::skipped`]) and
/// leaves the model state, the estimate and the held joints as they were:
/// it only counts among the frames seen. `Some` when the frame is answered
/// (or superseded).
pub fn fill_missing(job: &mut FrameJob) -> Option<StepResult> {
    if !job.present.contains(&false) {
        return None;
    }
    let mut st = job.session.lock();
    if !st.accepts(job.epoch) {
        return Some(Err(StepError::Superseded));
    }
    if st.held.fill(&mut job.input, &job.present) {
        return None;
    }
    Some(Ok(answer::skipped(job, &mut st)))
}

/// Lift one window of zeros and check the pose is finite, so a server
/// reports SERVING only with a lifter that works.
pub fn warm_up_lifter(lifter: &LoadedLifter) -> Result<(), BackendError> {
    let windows = vec![0.0f32; lifter.lifter.receptive_field() * FRAME_VALUES];
    match guarded(|| lifter.lifter.lift_windows(&windows, 1)) {
        Ok(poses) if poses.iter().flatten().flatten().all(|v| v.is_finite()) => Ok(()),
        Ok(_) => Err(BackendError::Model(
            "lifter warm-up produced non-finite values".into(),
        )),
        Err(e) => Err(BackendError::Model(format!("lifter warm-up failed: {e}"))),
    }
}

/// The lifter's buffers, kept between batches (they grow to the largest
/// batch of lifting rows seen, and stay empty without a lifter).
#[derive(Debug, Default)]
pub struct LiftScratch {
    /// Lifter windows of the lifting rows, one after the other.
    windows: Vec<f32>,
    /// For each lifter window, its index in the batch.
    rows: Vec<usize>,
}

/// Lift every lifting row of `batch` (`lifted[i]`: row `i`'s pose, `None`
/// for rows not lifted); rows that cannot be lifted, all of them on a
/// server without a lifter, get their answer here.
pub fn lift(
    lifter: Option<&LoadedLifter>,
    batch: &[Queued],
    answers: &mut [Option<StepResult>],
    lifted: &mut Vec<Option<Pose>>,
    scratch: &mut LiftScratch,
) {
    lifted.clear();
    lifted.resize(batch.len(), None);
    match lifter {
        Some(lifter) => lift_rows(&lifter.lifter, batch, answers, lifted, scratch),
        None => {
            for (item, answer) in batch.iter().zip(answers.iter_mut()) {
                if item.job.lift {
                    *answer = Some(Err(StepError::Lifter("this server has no lifter".into())));
                }
            }
        }
    }
}

/// Run `f`, turning a panic into an error: the lifter is a large numeric
/// library call on the batcher thread, and a panic there must fail its rows,
/// not stop the thread that serves every session.
fn guarded<T>(f: impl FnOnce() -> blapose_lifters::Result<T>) -> Result<T, String> {
    match catch_unwind(AssertUnwindSafe(f)) {
        Ok(Ok(v)) => Ok(v),
        Ok(Err(e)) => Err(e.to_string()),
        Err(panic) => Err(format!(
            "panicked: {}",
            panic
                .downcast_ref::<&str>()
                .map(|s| s.to_string())
                .or_else(|| panic.downcast_ref::<String>().cloned())
                .unwrap_or_else(|| "unknown cause".into())
        )),
    }
}

/// Copy each lifting row's window plus its new frame out (the window itself
/// is not changed), run all windows in one lifter call, and check each
/// pose.
fn lift_rows(
    lifter: &TrainedLifter,
    batch: &[Queued],
    answers: &mut [Option<StepResult>],
    lifted: &mut [Option<Pose>],
    scratch: &mut LiftScratch,
) {
    scratch.windows.clear();
    scratch.rows.clear();
    for (i, item) in batch.iter().enumerate() {
        if !item.job.lift {
            continue;
        }
        let st = item.job.session.lock();
        if !st.accepts(item.job.epoch) {
            answers[i] = Some(Err(StepError::Superseded));
            continue;
        }
        let Some(window) = st.window.as_deref() else {
            answers[i] = Some(Err(StepError::Lifter(
                "the session has no lifter window".into(),
            )));
            continue;
        };
        if window.frames() != lifter.receptive_field() {
            answers[i] = Some(Err(StepError::Lifter(format!(
                "the session's window holds {} frames, the lifter needs {}",
                window.frames(),
                lifter.receptive_field()
            ))));
            continue;
        }
        window.extend_with_next(&item.job.keypoints(), &mut scratch.windows);
        scratch.rows.push(i);
    }
    let n = scratch.rows.len();
    if n == 0 {
        return;
    }
    let started = Instant::now();
    let per_window = lifter.receptive_field() * FRAME_VALUES;
    match guarded(|| lifter.lift_windows(&scratch.windows, n)) {
        Ok(poses) if poses.len() == n => {
            for (&i, pose) in scratch.rows.iter().zip(poses) {
                accept_lifted(i, pose, answers, lifted);
            }
        }
        // Isolate the row that broke the call: one window at a time.
        failed => {
            let reason = match failed {
                Ok(poses) => format!("{} poses for {n} windows", poses.len()),
                Err(e) => e,
            };
            if n > 1 {
                tracing::warn!(error = %reason, rows = n, "batched lift failed; retrying its rows one by one");
            }
            for (r, &i) in scratch.rows.iter().enumerate() {
                let window = &scratch.windows[r * per_window..(r + 1) * per_window];
                match guarded(|| lifter.lift_windows(window, 1)).map(|mut p| p.pop()) {
                    Ok(Some(pose)) => accept_lifted(i, pose, answers, lifted),
                    Ok(None) => answers[i] = Some(Err(StepError::Lifter("no pose".into()))),
                    Err(e) => answers[i] = Some(Err(StepError::Lifter(e))),
                }
            }
        }
    }
    metrics::lift(n, started.elapsed());
}

fn accept_lifted(
    i: usize,
    pose: Pose,
    answers: &mut [Option<StepResult>],
    lifted: &mut [Option<Pose>],
) {
    match validate::lifted_pose(&pose) {
        Ok(pose) => lifted[i] = Some(pose),
        Err(e) => answers[i] = Some(Err(StepError::LiftedPose(e.to_string()))),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::backend::INPUT_DIM;
    use crate::fakes::{
        config, job, lift_job, lifting_config, session_config, start, start_with_lifter,
        test_lifter, window_len, Fake,
    };
    use crate::session::{InputFormat, SessionStore};
    use crate::validate::tests::{calibration, format, standing_pose, ANY_CAMERA};
    use crate::validate::InvalidInput;
    use blapose_core::layouts::KeypointLayout;
    use blapose_core::level::LevelCamera;
    use blapose_model::input::ModelInput;
    use blapose_proto::v1 as pb;
    use std::sync::atomic::Ordering;
    use std::time::Duration;

    #[tokio::test]
    async fn lifted_frames_enter_the_window_only_when_the_whole_frame_succeeds() {
        let fake = Fake::default();
        let fail = fake.fail.clone();
        let lifter = test_lifter();
        let batcher = start_with_lifter(fake, config(8, 0, 100), Some(lifter.clone())).unwrap();
        let (store, _g) = SessionStore::new(10, Duration::from_secs(60));
        let a = store.open(lifting_config(9)).unwrap();
        // The library path: the same frames through a window of our own.
        let mut mine = lifter.lifter.window();

        let (j, rx) = lift_job(&a.session, a.epoch, 0, 0.0);
        let frame0 = j.keypoints();
        batcher.submit(j).unwrap();
        let out = rx.await.unwrap().unwrap();
        mine.push(frame0);
        assert_eq!(out.lifted, Some(lifter.lifter.lift(&mut mine).unwrap()));
        assert_eq!(out.lifted.unwrap()[0], [0.0; 3]);
        assert_eq!((out.frames_seen, window_len(&a.session)), (1, 1));

        // The GRU step fails: lifted fine, but nothing is kept.
        fail.store(true, Ordering::Relaxed);
        let (j, rx) = lift_job(&a.session, a.epoch, 50, 0.0);
        batcher.submit(j).unwrap();
        assert!(matches!(rx.await.unwrap(), Err(StepError::Model(_))));
        fail.store(false, Ordering::Relaxed);
        assert_eq!(window_len(&a.session), 1);

        // A taken-over stream's lifting frame: refused before the lifter.
        let resumed = store.resume(&a.session.id().to_string()).unwrap();
        let (j, rx) = lift_job(&a.session, a.epoch, 51, 0.0);
        batcher.submit(j).unwrap();
        assert_eq!(rx.await.unwrap(), Err(StepError::Superseded));
        assert_eq!(window_len(&a.session), 1);

        // A pose that cannot be adjusted (here: out of bounds): refused.
        let (mut j, rx) = lift_job(&a.session, resumed.epoch, 52, 0.0);
        j.input[2..].fill(1e6);
        batcher.submit(j).unwrap();
        let err = rx.await.unwrap().unwrap_err();
        assert!(matches!(err, StepError::LiftedPose(_)), "{err}");
        assert_eq!(err.code(), tonic::Code::Internal);
        assert_eq!(window_len(&a.session), 1);

        // The next good frame continues from frame 0 alone.
        let (j, rx) = lift_job(&a.session, resumed.epoch, 1, 0.0);
        let frame1 = j.keypoints();
        batcher.submit(j).unwrap();
        let out = rx.await.unwrap().unwrap();
        mine.push(frame1);
        assert_eq!(out.lifted, Some(lifter.lifter.lift(&mut mine).unwrap()));
        assert_eq!((out.frames_seen, window_len(&a.session)), (2, 2));
    }

    #[tokio::test]
    async fn lifting_and_client_pose_frames_share_a_batch() {
        let fake = Fake::default();
        let log = fake.log.clone();
        let lifter = test_lifter();
        let batcher = start_with_lifter(fake, config(8, 500, 100), Some(lifter.clone())).unwrap();
        let (store, _g) = SessionStore::new(10, Duration::from_secs(60));
        let a = store.open(lifting_config(9)).unwrap();
        let b = store.open(lifting_config(9)).unwrap();
        let c = store.open(session_config()).unwrap();
        let _guards: Vec<_> = (0..3).map(|_| batcher.stream_guard()).collect();
        let (ja, ra) = lift_job(&a.session, a.epoch, 3, 0.0);
        let (jb, rb) = lift_job(&b.session, b.epoch, 8, 1.0);
        let (jc, rc) = job(&c.session, c.epoch, 1.0, 2.0);
        let (fa, fb) = (ja.keypoints(), jb.keypoints());
        for j in [ja, jb, jc] {
            batcher.submit(j).unwrap();
        }
        let (oa, ob, oc) = (
            ra.await.unwrap().unwrap(),
            rb.await.unwrap().unwrap(),
            rc.await.unwrap().unwrap(),
        );
        assert_eq!(
            log.lock().unwrap().last().map(Vec::len),
            Some(3),
            "one batch"
        );
        for (out, frame) in [(oa, fa), (ob, fb)] {
            let mut w = lifter.lifter.window();
            w.push(frame);
            let want = lifter.lifter.lift(&mut w).unwrap();
            let got = out.lifted.expect("lifted");
            for (u, v) in got.iter().flatten().zip(want.iter().flatten()) {
                assert!((u - v).abs() < 1e-5, "{u} vs {v}");
            }
        }
        assert_eq!(oc.lifted, None, "a client pose is not lifted");
        assert!(c.session.lock().window.is_none());
    }

    #[tokio::test]
    async fn a_batcher_without_a_lifter_refuses_lifting_frames() {
        let batcher = start(Fake::default(), config(8, 0, 100)).unwrap();
        let (store, _g) = SessionStore::new(10, Duration::from_secs(60));
        let a = store.open(lifting_config(9)).unwrap();
        let (j, rx) = lift_job(&a.session, a.epoch, 0, 0.0);
        batcher.submit(j).unwrap();
        assert!(matches!(rx.await.unwrap(), Err(StepError::Lifter(_))));
        assert_eq!(a.session.lock().frames_seen(), 0);
    }

    #[test]
    fn panics_in_the_lifter_become_errors() {
        let r: Result<(), String> = guarded(|| panic!("boom"));
        assert_eq!(r, Err("panicked: boom".to_string()));
        let r: Result<u8, String> = guarded(|| Ok(3));
        assert_eq!(r, Ok(3));
    }

    /// A validated sequence, prepared for `contract`.
    fn prepared(
        req: &pb::AdjustSequenceRequest,
        contract: Option<&ModelInput>,
    ) -> Result<PreparedSequence, InvalidInput> {
        validate::sequence(req, contract).map(sequence)
    }

    fn pixels() -> InputFormat {
        InputFormat::pixels(KeypointLayout::H36m17, 1000, 1000)
    }

    #[test]
    fn a_floor_scaled_contract_reads_the_camera_scaled_to_its_height() {
        let c = pb::CameraCalibration {
            height: 1.5,
            ..calibration()
        };
        let floor = ModelInput::from_training(true, true, true);
        let camera = validate::camera(Some(&c), &pixels(), Some(&floor))
            .unwrap()
            .unwrap();
        assert_eq!(camera.calibration, c, "echoed as sent");
        let input = camera
            .input
            .expect("a floor-scaled contract reads a camera");
        assert_eq!(input.level().floor_scale_height(), Some(1.5));
        let plain = validate::camera(Some(&c), &pixels(), Some(&ANY_CAMERA))
            .unwrap()
            .unwrap();
        assert_eq!(plain.input.unwrap().level().floor_scale_height(), None);
        // Refusals are the validation's.
        assert_eq!(
            validate::camera(Some(&c), &pixels(), None),
            Err(InvalidInput::NoCameraAwareModel)
        );
        assert_eq!(validate::camera(None, &pixels(), Some(&floor)), Ok(None));
    }

    #[test]
    fn a_lens_distortion_is_undone() {
        let with = |distortion: Vec<f32>| pb::CameraCalibration {
            distortion,
            ..calibration()
        };
        let camera = |c: pb::CameraCalibration| {
            validate::camera(Some(&c), &pixels(), Some(&ANY_CAMERA))
                .unwrap()
                .unwrap()
                .input
                .unwrap()
        };
        let plain = camera(calibration());
        for ok in [
            vec![-0.2, 0.05, 0.001, -0.001],
            vec![-0.2, 0.05, 0.001, -0.001, 0.01],
        ] {
            // A corner keypoint lands elsewhere than without.
            let lens = camera(with(ok));
            let mut corner = vec![0.9f32; 34];
            let mut same = corner.clone();
            lens.prepare_frames(&mut corner);
            plain.prepare_frames(&mut same);
            assert!(
                (corner[0] - same[0]).abs() > 0.01,
                "{} vs {}",
                corner[0],
                same[0]
            );
        }
    }

    /// Joints below [`crate::validate::MISSING_CONFIDENCE`] are not read:
    /// any coordinates (NaN included) give the same inputs, those of the
    /// joint held at its last detection (or its first, before it).
    #[test]
    fn missing_joints_of_a_sequence_are_held_whatever_their_coordinates() {
        let fmt = format(1, Some(pb::input_format::Coordinates::Normalized(true)));
        let kp: Vec<f32> = (0..3 * 34).map(|i| 0.01 * (i % 50) as f32).collect();
        let mut req = pb::AdjustSequenceRequest {
            input_format: Some(fmt),
            model: 0,
            num_frames: 3,
            keypoints_2d: kp.clone(),
            confidence: vec![0.9; 3 * 17],
            poses_3d: standing_pose().repeat(3),
            camera: None,
            subject: None,
            motion: None,
        };
        let clean = prepared(&req, None).unwrap().inputs;
        // Joint 5 lost in frame 1, joint 2 lost in frame 0.
        req.confidence[17 + 5] = 0.0;
        req.confidence[2] = 0.05;
        req.keypoints_2d[34 + 10] = f32::NAN;
        req.keypoints_2d[34 + 11] = 1e9;
        req.keypoints_2d[4] = -7.0;
        let held = prepared(&req, None).unwrap().inputs;
        req.keypoints_2d[34 + 10] = 0.3;
        req.keypoints_2d[4] = 0.9;
        assert_eq!(
            prepared(&req, None).unwrap().inputs,
            held,
            "coordinates not read"
        );
        let at =
            |t: usize, j: usize| [held[t * INPUT_DIM + 2 * j], held[t * INPUT_DIM + 2 * j + 1]];
        let was = |t: usize, j: usize| {
            [
                clean[t * INPUT_DIM + 2 * j],
                clean[t * INPUT_DIM + 2 * j + 1],
            ]
        };
        assert_eq!(at(1, 5), was(0, 5), "held from frame 0");
        assert_eq!(at(0, 2), was(1, 2), "before its first detection: that one");
        for (t, j) in [(0, 0), (1, 4), (2, 5), (2, 2)] {
            assert_eq!(at(t, j), was(t, j), "detected joints unchanged");
        }
        req.confidence = vec![0.0; 3 * 17];
        assert_eq!(prepared(&req, None), Err(InvalidInput::NothingDetected));
        assert_eq!(
            prepared(&req, None).unwrap_err().to_status().code(),
            tonic::Code::InvalidArgument
        );
    }

    #[test]
    fn a_sequence_with_a_camera_is_rectified_for_the_model() {
        let fmt = format(
            1,
            Some(pb::input_format::Coordinates::ImageSize(pb::ImageSize {
                width: 1000,
                height: 1000,
            })),
        );
        let keypoints: Vec<f32> = (0..2 * 34).map(|i| 300.0 + 7.0 * i as f32).collect();
        let mut req = pb::AdjustSequenceRequest {
            input_format: Some(fmt),
            model: 0,
            num_frames: 2,
            keypoints_2d: keypoints,
            confidence: vec![],
            poses_3d: standing_pose().repeat(2),
            camera: None,
            subject: None,
            motion: None,
        };
        let plain = prepared(&req, Some(&ANY_CAMERA)).unwrap();
        req.camera = Some(calibration());
        assert_eq!(prepared(&req, None), Err(InvalidInput::NoCameraAwareModel));
        let rectified = prepared(&req, Some(&ANY_CAMERA)).unwrap();
        assert!(rectified.camera_aware && !plain.camera_aware);
        // What the camera's level twin makes of the frames.
        let c = calibration();
        let level = LevelCamera::from_pixels(
            [c.up[0], c.up[1], c.up[2]].map(f64::from),
            [c.focal_x, c.focal_y].map(f64::from),
            [c.principal_x, c.principal_y].map(f64::from),
            1000,
            1000,
        )
        .unwrap();
        let mut want = plain.inputs.clone();
        level.rectify_frames(&mut want);
        assert_eq!(rectified.inputs, want);
        assert_ne!(rectified.inputs, plain.inputs);
        assert_eq!(rectified.poses, plain.poses);
    }
}

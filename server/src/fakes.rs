//! Test support for the batcher's stages: a fake online model whose state
//! reveals lost, repeated, reordered or mixed-up frames, a small random
//! server lifter, and frames to feed them. Shared by the unit tests of
//! [`crate::batch`], [`crate::prepare`], [`crate::step`] and [`crate::pipeline`].

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use blapose_core::layouts::KeypointLayout;
use blapose_core::NUM_JOINTS;
use tokio::sync::oneshot;

use crate::backend::{Backend, BackendError, INPUT_DIM, OUTPUT_DIM, STATE_DIM};
use crate::batch::{Batcher, BatcherConfig};
use crate::frame::{FrameJob, StepResult};
use crate::models::LoadedLifter;
use crate::session::{Coordinates, InputFormat, Session, SessionConfig};
use crate::step::OnlineBackends;
use blapose_test_support::StepGate;

/// Start a batcher running `fake` alone (no camera-aware model, no
/// lifter).
pub(crate) fn start<B: Backend>(fake: B, config: BatcherConfig) -> Result<Batcher, BackendError> {
    start_with_lifter(fake, config, None)
}

/// [`start`] with a server lifter.
pub(crate) fn start_with_lifter<B: Backend>(
    fake: B,
    config: BatcherConfig,
    lifter: Option<Arc<LoadedLifter>>,
) -> Result<Batcher, BackendError> {
    let backends = OnlineBackends {
        default: fake,
        camera_aware: None,
    };
    crate::pipeline::start(backends, config, lifter)
}

/// A fake model: the new state is `h + x[0]` in every slot, the
/// prediction is the new `h[0]` for every bone. So after frames with
/// x[0] = a1, a2, ... a session's state is the running sum of its
/// inputs, which reveals lost, duplicated, reordered or mixed-up frames.
/// It also records batch sizes and the sessions (by first input slot 1)
/// in each batch. With a [`StepGate`] every step waits until it opens,
/// so a test controls what is queued while a step runs (no sleeps).
#[derive(Clone, Default)]
pub(crate) struct Fake {
    pub(crate) log: Log,
    pub(crate) gate: Option<Arc<StepGate>>,
    pub(crate) fail: Arc<AtomicBool>,
}

/// The fake's record: the tags of each step's rows.
pub(crate) type Log = Arc<Mutex<Vec<Vec<f32>>>>;

/// A fake whose steps wait at a gate that is closed once the batcher
/// has warmed up (the warm-up step passes an open gate).
pub(crate) fn gated_batcher(config: BatcherConfig) -> (Batcher, Arc<StepGate>, Log) {
    let gate = Arc::new(StepGate::new());
    gate.set_open(true);
    let fake = Fake {
        gate: Some(gate.clone()),
        ..Fake::default()
    };
    let log = fake.log.clone();
    let batcher = start(fake, config).unwrap();
    gate.close_and_reset();
    (batcher, gate, log)
}

/// A bound on how long a test waits for an answer, far beyond any
/// step: reaching it means the frame was never answered (a hang), not
/// that something was slow.
pub(crate) const HANG: Duration = Duration::from_secs(120);

pub(crate) async fn answer(rx: oneshot::Receiver<StepResult>) -> StepResult {
    tokio::time::timeout(HANG, rx)
        .await
        .expect("the frame is answered")
        .expect("the batcher answers")
}

impl Backend for Fake {
    fn step(
        &mut self,
        inputs: &[f32],
        hidden: &mut [f32],
        out: &mut [f32],
        batch: usize,
    ) -> Result<(), BackendError> {
        crate::backend::check_step_shapes(inputs, hidden, out, batch)?;
        if self.fail.load(Ordering::Relaxed) {
            return Err(BackendError::Model("fake failure".into()));
        }
        // x[2] = 999 makes the whole call fail, as the real engine does
        // when one row goes non-finite.
        if let Some(gate) = &self.gate {
            gate.pass();
        }
        if inputs.chunks_exact(INPUT_DIM).any(|x| x[2] == 999.0) {
            return Err(BackendError::Model("row refused".into()));
        }
        let mut tags = Vec::new();
        for b in 0..batch {
            let x = &inputs[b * INPUT_DIM..(b + 1) * INPUT_DIM];
            tags.push(x[1]);
            let h = &mut hidden[b * STATE_DIM..(b + 1) * STATE_DIM];
            for v in h.iter_mut() {
                *v += x[0];
            }
            // x[2] = NaN asks for a poisoned row.
            let p = if x[2].is_nan() { f32::NAN } else { h[0] };
            out[b * OUTPUT_DIM..(b + 1) * OUTPUT_DIM].fill(p);
        }
        self.log.lock().unwrap().push(tags);
        Ok(())
    }
}

pub(crate) fn config(max_batch: usize, delay_ms: u64, capacity: usize) -> BatcherConfig {
    BatcherConfig {
        max_batch,
        max_mixed_batch: max_batch,
        max_queue_delay: Duration::from_millis(delay_ms),
        queue_capacity: capacity,
    }
}

pub(crate) fn session_config() -> SessionConfig {
    SessionConfig {
        input: InputFormat {
            layout: KeypointLayout::H36m17,
            coordinates: Coordinates::Normalized,
        },
        label: String::new(),
        lifter_frames: None,
        camera: None,
        subject: None,
        motion: None,
    }
}

pub(crate) fn job(
    session: &Arc<Session>,
    epoch: u64,
    value: f32,
    tag: f32,
) -> (FrameJob, oneshot::Receiver<StepResult>) {
    let (tx, rx) = oneshot::channel();
    let mut input = [0.0; INPUT_DIM];
    input[0] = value;
    input[1] = tag;
    (
        FrameJob {
            session: session.clone(),
            epoch,
            input,
            present: [true; NUM_JOINTS],
            lift: false,
            pose: None,
            state_every: 0,
            reply: tx,
        },
        rx,
    )
}

pub(crate) fn test_lifter() -> Arc<LoadedLifter> {
    let arch = blapose_lifters::trained::VideoPoseArch {
        filter_width: 3,
        blocks: 1,
        channels: 16,
        dropout: 0.0,
        causal: true,
    };
    let bytes = blapose_lifters::trained::random_weights_file(arch, 11).unwrap();
    Arc::new(LoadedLifter {
        lifter: blapose_lifters::TrainedLifter::from_bytes(&bytes).unwrap(),
        origin: "test".into(),
        sha256: String::new(),
    })
}

pub(crate) fn lifting_config(frames: usize) -> SessionConfig {
    SessionConfig {
        lifter_frames: Some(frames),
        camera: None,
        ..session_config()
    }
}

/// A lifting frame: keypoints that vary with `t`, `tag` in x[1].
pub(crate) fn lift_job(
    session: &Arc<Session>,
    epoch: u64,
    t: usize,
    tag: f32,
) -> (FrameJob, oneshot::Receiver<StepResult>) {
    let (mut j, rx) = job(session, epoch, 1.0, tag);
    for (k, v) in j.input.iter_mut().enumerate().skip(2) {
        *v = (0.3 * t as f32 + 0.7 * k as f32).sin() * 0.5;
    }
    j.lift = true;
    (j, rx)
}

pub(crate) fn window_len(session: &Session) -> usize {
    session.lock().window.as_deref().map_or(0, |w| w.len())
}

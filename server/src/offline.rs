//! Offline adjustment of a whole sequence (the `AdjustSequence` RPC).
//!
//! A request goes through the stages a streamed frame goes through, on the
//! whole sequence at once: [`crate::validate`], [`crate::prepare`] (missing
//! joints held, the frames read through the request's camera as the
//! camera-aware models' input contract says), the model (the Bi-GRU over
//! the whole sequence, or the online GRU step by step), [`crate::answer`],
//! and when the request asks for it the offline [`crate::motion`] stage.
//!
//! The model runs on tokio's blocking pool, never on an async worker, and at
//! most `compute_threads` run at once (a semaphore) so offline work cannot
//! starve the online batcher of CPU. At most [`MAX_WAITING`] more may wait
//! for their turn; beyond that a request is refused with RESOURCE_EXHAUSTED
//! instead of queueing without bound. Backends are pooled: building one
//! re-lays-out the weights, which is worth doing once, not per request.

use std::sync::{Arc, Mutex, PoisonError};
use std::time::Instant;

use blapose_core::{BoneLengths, ModelKind, Pose};
use blapose_model::stature::StatureModel;
use blapose_proto::v1 as pb;
use tokio::sync::Semaphore;
use tonic::Status;

use crate::answer;
use crate::backend::{Backend, BackendError, INPUT_DIM, OUTPUT_DIM, STATE_DIM};
use crate::metrics;
use crate::models::ModelProvider;
use crate::motion;
use crate::prepare::{self, PreparedSequence};
use crate::session::RunningMean;
use crate::validate;

/// What the motion stage of a request reads (kept from validation).
struct MotionInput {
    rate: f64,
    spec: crate::session::InputFormat,
    view: Option<blapose_model::input::ViewCalibration>,
    keypoints: Vec<f32>,
    present: Vec<bool>,
}

/// Result of an offline request.
#[derive(Debug, Clone, PartialEq)]
pub struct AdjustedSequence {
    /// Adjusted poses, one per frame.
    pub poses: Vec<Pose>,
    /// Lengths applied to each frame.
    pub lengths: Vec<BoneLengths>,
}

type Pool<T> = Arc<Mutex<Vec<T>>>;

/// Offline requests that may wait for a compute slot.
pub const MAX_WAITING: usize = 64;

/// Pooled backends of one model family.
#[derive(Default, Clone)]
struct Pools {
    online: Pool<Box<dyn Backend>>,
    offline: Pool<Box<dyn crate::backend::SequenceBackend>>,
}

/// Runs offline requests with bounded concurrency.
pub struct OfflineRunner {
    provider: Arc<dyn ModelProvider>,
    permits: Arc<Semaphore>,
    admission: Arc<Semaphore>,
    /// Backends of the default models.
    default: Pools,
    /// Backends of the camera-aware models (requests with a camera).
    camera_aware: Pools,
}

impl std::fmt::Debug for OfflineRunner {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("OfflineRunner")
            .field("available_permits", &self.permits.available_permits())
            .finish()
    }
}

fn take<T>(pool: &Pool<T>) -> Option<T> {
    pool.lock().unwrap_or_else(PoisonError::into_inner).pop()
}

fn give<T>(pool: &Pool<T>, item: T) {
    pool.lock()
        .unwrap_or_else(PoisonError::into_inner)
        .push(item);
}

fn internal(e: BackendError) -> Status {
    Status::internal(format!("model failed: {e}"))
}

impl OfflineRunner {
    /// A runner allowing `concurrency` requests at once.
    pub fn new(provider: Arc<dyn ModelProvider>, concurrency: usize) -> Self {
        Self {
            provider,
            permits: Arc::new(Semaphore::new(concurrency.max(1))),
            admission: Arc::new(Semaphore::new(concurrency.max(1) + MAX_WAITING)),
            default: Pools::default(),
            camera_aware: Pools::default(),
        }
    }

    /// Answer an `AdjustSequence` request: validate it, answer a subject
    /// with its stature-regression lengths, or prepare the sequence and run
    /// the model on it (`stature`: the server's stature model).
    pub async fn respond(
        &self,
        req: &pb::AdjustSequenceRequest,
        stature: &StatureModel,
    ) -> Result<pb::AdjustSequenceResponse, Status> {
        let contract = self.provider.camera_aware().map(|m| m.model_input());
        let motion_rate = motion::options(req.motion.as_ref())?;
        let seq = validate::sequence(req, contract.as_ref()).map_err(|e| e.to_status())?;
        let subject = validate::subject(req.subject.as_ref()).map_err(|e| e.to_status())?;
        // What the motion stage reads: the keypoints as validated, before
        // the model's preparation changes them.
        let motion_input = match motion_rate {
            Some(rate) => Some(MotionInput {
                rate,
                spec: validate::input_format(req.input_format.as_ref())
                    .map_err(|e| e.to_status())?,
                view: seq.camera.as_ref().map(|c| c.view.clone()),
                keypoints: seq.inputs.clone(),
                present: seq.present.clone(),
            }),
            None => None,
        };
        let (model, done) = match subject {
            Some(subject) => {
                // Every frame gets the subject's lengths; no model needs to run.
                let subject = answer::subject(subject, stature);
                let poses = answer::subject_frames(&seq.poses, &subject)?;
                let lengths = vec![subject.lengths; poses.len()];
                (seq.model, AdjustedSequence { poses, lengths })
            }
            None => {
                let seq = prepare::sequence(seq);
                let model = seq.model;
                (model, self.adjust(seq).await?)
            }
        };
        let mut response =
            answer::sequence_response(model, &done.poses, done.lengths.as_flattened());
        if let Some(input) = motion_input {
            let moved = tokio::task::spawn_blocking(move || {
                motion::sequence(
                    &done.poses,
                    &done.lengths,
                    input.rate,
                    &input.spec,
                    input.view.as_ref(),
                    &input.keypoints,
                    &input.present,
                )
            })
            .await
            .map_err(|e| Status::internal(format!("motion worker failed: {e}")))??;
            motion::fill_response(&mut response, &moved);
        }
        Ok(response)
    }

    /// Predict lengths for a prepared sequence and adjust its poses.
    pub async fn adjust(&self, seq: PreparedSequence) -> Result<AdjustedSequence, Status> {
        let _admitted = self.admission.clone().try_acquire_owned().map_err(|_| {
            crate::metrics::limited("offline_waiting");
            Status::resource_exhausted(format!(
                "server busy: {MAX_WAITING} offline requests are already waiting; retry later"
            ))
        })?;
        let _permit = self
            .permits
            .clone()
            .acquire_owned()
            .await
            .map_err(|_| Status::unavailable("the server is shutting down"))?;
        let (provider, Pools { online, offline }) = if seq.camera_aware {
            let provider = self
                .provider
                .camera_aware()
                .ok_or_else(|| crate::validate::InvalidInput::NoCameraAwareModel.to_status())?;
            (provider, self.camera_aware.clone())
        } else {
            (self.provider.clone(), self.default.clone())
        };
        let started = Instant::now();
        let model = seq.model;
        let result = tokio::task::spawn_blocking(move || -> Result<AdjustedSequence, Status> {
            let frames = seq.poses.len();
            let lengths = match model {
                ModelKind::BiGru => {
                    let mut backend = match take(&offline) {
                        Some(b) => b,
                        None => provider.offline().map_err(internal)?,
                    };
                    let predicted = backend.predict(&seq.inputs, frames);
                    give(&offline, backend);
                    let predicted = predicted.map_err(internal)?;
                    if !predicted.iter().all(|v| v.is_finite()) {
                        return Err(Status::internal(
                            "the model produced non-finite bone lengths",
                        ));
                    }
                    vec![predicted; frames]
                }
                ModelKind::Gru => {
                    let mut backend = match take(&online) {
                        Some(b) => b,
                        None => provider.online().map_err(internal)?,
                    };
                    let result = online_lengths(backend.as_mut(), &seq.inputs, frames);
                    give(&online, backend);
                    result?
                }
            };
            let poses = answer::adjust_frames(&seq.poses, &lengths)?;
            Ok(AdjustedSequence { poses, lengths })
        })
        .await
        .map_err(|e| Status::internal(format!("offline worker failed: {e}")))?;
        metrics::offline(model.as_str(), started.elapsed());
        result
    }
}

/// The online model run causally over a sequence, one step per frame: row
/// `t` is the running mean of the predictions of frames `0..=t`, built as a
/// stream's estimate is ([`answer::commit`]). The engine's sums may round
/// differently in the last bits from a stream's, whose steps ran in other
/// batches and after other calls (see the proto's
/// `AdjustSequenceRequest.model`).
pub fn online_lengths(
    backend: &mut dyn Backend,
    inputs: &[f32],
    frames: usize,
) -> Result<Vec<BoneLengths>, Status> {
    let mut hidden = vec![0.0f32; STATE_DIM];
    let mut prediction = [0.0f32; OUTPUT_DIM];
    let mut running = RunningMean::new();
    let mut out = Vec::with_capacity(frames);
    for (t, x) in inputs.chunks_exact(INPUT_DIM).take(frames).enumerate() {
        backend
            .step(x, &mut hidden, &mut prediction, 1)
            .map_err(internal)?;
        if !hidden
            .iter()
            .chain(prediction.iter())
            .all(|v| v.is_finite())
        {
            return Err(Status::internal(format!(
                "the model produced a non-finite result at frame {t}"
            )));
        }
        out.push(running.push(&prediction));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::backend::SequenceBackend;
    use std::sync::Condvar;

    /// Online fake: prediction = number of frames seen so far (from the
    /// state), so running means are 1, 1.5, 2, ...
    struct Counting;
    impl Backend for Counting {
        fn step(
            &mut self,
            _: &[f32],
            h: &mut [f32],
            y: &mut [f32],
            _: usize,
        ) -> Result<(), BackendError> {
            h[0] += 1.0;
            y.fill(h[0]);
            Ok(())
        }
    }

    /// Offline fake that blocks until the gate opens.
    #[derive(Clone, Default)]
    struct Gate(Arc<(Mutex<bool>, Condvar)>);
    impl SequenceBackend for Gate {
        fn predict(&mut self, _: &[f32], _: usize) -> Result<BoneLengths, BackendError> {
            let (open, cv) = &*self.0;
            let mut g = open.lock().unwrap();
            while !*g {
                g = cv.wait(g).unwrap();
            }
            Ok([0.3; 16])
        }
    }

    struct Provider(Gate);
    impl ModelProvider for Provider {
        fn online(&self) -> Result<Box<dyn Backend>, BackendError> {
            Ok(Box::new(Counting))
        }
        fn offline(&self) -> Result<Box<dyn crate::backend::SequenceBackend>, BackendError> {
            Ok(Box::new(self.0.clone()))
        }
        fn describe(&self) -> Vec<pb::ModelDescription> {
            Vec::new()
        }
    }

    fn pose() -> Pose {
        std::array::from_fn(|j| [0.1 * j as f32, (j * j) as f32 * 0.01, 3.0])
    }

    #[test]
    fn online_lengths_are_running_means() {
        let inputs = vec![0.0; 4 * INPUT_DIM];
        let rows = online_lengths(&mut Counting, &inputs, 4).unwrap();
        let firsts: Vec<f32> = rows.iter().map(|r| r[0]).collect();
        assert_eq!(firsts, vec![1.0, 1.5, 2.0, 2.5]);
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn too_many_waiting_requests_are_refused_not_queued() {
        let gate = Gate::default();
        let runner = Arc::new(OfflineRunner::new(Arc::new(Provider(gate.clone())), 1));
        let seq = PreparedSequence {
            model: ModelKind::BiGru,
            inputs: vec![0.0; INPUT_DIM],
            poses: vec![pose()],
            camera_aware: false,
        };
        let mut tasks = Vec::new();
        for _ in 0..(MAX_WAITING + 6) {
            let (r, s) = (runner.clone(), seq.clone());
            tasks.push(tokio::spawn(async move { r.adjust(s).await }));
        }
        // Every task is admitted or refused before the gate opens: the
        // refused ones finish at once, and only once all MAX_WAITING + 1
        // admission slots are taken, so 5 finished means all have tried.
        // (Polled, not timed: the wait ends when the event happens.)
        let polls = std::iter::repeat_with(|| tasks.iter().filter(|t| t.is_finished()).count());
        for (poll, finished) in polls.enumerate() {
            if finished >= 5 {
                break;
            }
            assert!(poll < 120_000, "the refusals never came");
            tokio::time::sleep(std::time::Duration::from_millis(1)).await;
        }
        // One more, on this thread with a recorder of its own: counted.
        let recorder = crate::metrics::test_recorder();
        {
            let _local = ::metrics::set_default_local_recorder(&recorder);
            let refused = runner.adjust(seq.clone()).await.unwrap_err();
            assert_eq!(refused.code(), tonic::Code::ResourceExhausted);
        }
        assert_eq!(
            crate::metrics::limited_count(&recorder, "offline_waiting"),
            1
        );
        {
            let (open, cv) = &*gate.0;
            *open.lock().unwrap() = true;
            cv.notify_all();
        }
        let mut ok = 0;
        let mut refused = 0;
        for t in tasks {
            match t.await.unwrap() {
                Ok(done) => {
                    assert_eq!(done.lengths, vec![[0.3; 16]]);
                    ok += 1;
                }
                Err(s) => {
                    assert_eq!(s.code(), tonic::Code::ResourceExhausted);
                    refused += 1;
                }
            }
        }
        assert_eq!(ok, MAX_WAITING + 1);
        assert_eq!(refused, 5);
    }
}

//! What the two trainers share: the run directory, the learning-rate
//! schedule, the resume check, checkpoint metadata and timing, and the CSV
//! log with its throughput window.
//!
//! Why one module: the bone-length trainer ([`crate::train`]) and the
//! lifter trainer ([`crate::lifter::train`]) differ in their networks and
//! data but run the same bookkeeping, and a run directory must read the
//! same whichever wrote it (`blapose train --resume`, the curve plots, the
//! tests that read logs). A run directory holds:
//!
//! * `train_log.csv` ([`LOG_FILE`]): one row per validation, starting with
//!   the columns of [`LogWindow::row`] (`step,epoch,lr,train_loss_mm,
//!   grad_norm,<rate>`), then the trainer's validation columns and
//!   `elapsed_s`;
//! * `config.json` ([`CONFIG_FILE`]): the run's configuration;
//! * `checkpoint.safetensors` ([`CHECKPOINT_FILE`]): weights, optimizer
//!   moments and [`CheckpointMeta`], written atomically ([`write_atomic`]);
//! * `model.safetensors` ([`WEIGHTS_FILE`]): the final weights.
//!
//! **Schedule.** Samples are drawn on the fly, so there is no natural
//! epoch: one *epoch* is `epoch_steps` optimizer steps and the learning
//! rate is `lr * decay^floor(step / epoch_steps)` ([`Schedule`]).

use std::collections::HashMap;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;

use candle_core::{Device, Tensor};
use serde::{Deserialize, Serialize};

use crate::error::TrainError;

/// Name of the checkpoint file inside the run directory.
pub const CHECKPOINT_FILE: &str = "checkpoint.safetensors";
/// Name of the training log inside the run directory.
pub const LOG_FILE: &str = "train_log.csv";
/// Name of the final weights inside the run directory.
pub const WEIGHTS_FILE: &str = "model.safetensors";
/// Name of the run configuration inside the run directory.
pub const CONFIG_FILE: &str = "config.json";

/// Progress callback: `(step, total, loss_mm, items_per_s)` (items: frames
/// for the bone-length models, samples for the lifters).
pub type Progress<'a> = &'a mut dyn FnMut(u64, u64, f64, f64);

/// The step decay of every trainer: `lr * decay^floor(step / epoch_steps)`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Schedule {
    /// Initial learning rate.
    pub lr: f64,
    /// Factor per epoch.
    pub decay: f64,
    /// Steps per epoch (the decay period).
    pub epoch_steps: u64,
}

impl Schedule {
    /// The learning rate of step `step` (0-based).
    pub fn lr_at(&self, step: u64) -> f64 {
        self.lr * self.decay.powi((step / self.epoch_steps.max(1)) as i32)
    }

    /// Epochs done after `step` steps (fractional, as logged).
    pub fn epoch(&self, step: u64) -> f64 {
        step as f64 / self.epoch_steps.max(1) as f64
    }
}

/// Whether a run configured as `now` may continue a checkpoint written
/// with `checkpoint`: equal once `relax` has copied the fields a resume may
/// change (run length, logging) from the checkpoint's configuration into a
/// copy of `now`. The error shows both configurations.
pub fn check_resumable<T: Clone + PartialEq + Serialize>(
    now: &T,
    checkpoint: &T,
    relax: impl FnOnce(&mut T, &T),
) -> Result<(), String> {
    let mut relaxed = now.clone();
    relax(&mut relaxed, checkpoint);
    if relaxed == *checkpoint {
        Ok(())
    } else {
        Err(format!(
            "checkpoint was written by a different configuration:\n  checkpoint: {}\n  now:        {}",
            serde_json::to_string(checkpoint).unwrap_or_default(),
            serde_json::to_string(now).unwrap_or_default()
        ))
    }
}

/// What a checkpoint holds besides tensors (`C`: the trainer's
/// configuration).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct CheckpointMeta<C> {
    /// Steps done.
    pub step: u64,
    /// The optimizer's step count (bias correction).
    pub adam_steps: u64,
    /// Wall-clock seconds of every invocation so far.
    pub elapsed_s: f64,
    /// The run's configuration.
    pub config: C,
}

/// Write `bytes` to `path` so that a crash never leaves a torn file
/// (temporary file, fsync, rename).
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), TrainError> {
    let tmp = path.with_extension("tmp");
    {
        let mut f = std::fs::File::create(&tmp).map_err(|e| TrainError::io(&tmp, e))?;
        f.write_all(bytes).map_err(|e| TrainError::io(&tmp, e))?;
        f.sync_all().map_err(|e| TrainError::io(&tmp, e))?;
    }
    std::fs::rename(&tmp, path).map_err(|e| TrainError::io(path, e))
}

/// Keep the log's header and the rows up to `step` (for a resumed run).
pub fn truncate_log(path: &Path, step: u64) -> Result<(), TrainError> {
    let Ok(text) = std::fs::read_to_string(path) else {
        return Ok(());
    };
    let kept: Vec<&str> = text
        .lines()
        .enumerate()
        .filter(|(i, l)| {
            *i == 0
                || l.split(',')
                    .next()
                    .and_then(|s| s.parse::<u64>().ok())
                    .is_some_and(|s| s <= step)
        })
        .map(|(_, l)| l)
        .collect();
    std::fs::write(path, kept.join("\n") + "\n").map_err(|e| TrainError::io(path, e))
}

/// Column `name` of a training log as `(step, value)` pairs (NaN skipped).
pub fn read_log_column(path: &Path, name: &str) -> Result<Vec<(f64, f64)>, TrainError> {
    let text = std::fs::read_to_string(path).map_err(|e| TrainError::io(path, e))?;
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().unwrap_or("").split(',').collect();
    let col = header
        .iter()
        .position(|h| *h == name)
        .ok_or_else(|| TrainError::Data(format!("{}: no column {name}", path.display())))?;
    Ok(lines
        .filter_map(|l| {
            let f: Vec<&str> = l.split(',').collect();
            let x = f.first()?.parse::<f64>().ok()?;
            let y = f.get(col)?.parse::<f64>().ok()?;
            y.is_finite().then_some((x, y))
        })
        .collect())
}

/// A safetensors file read whole: its tensors and header metadata.
pub struct TensorFile {
    /// Tensors by name.
    pub tensors: HashMap<String, Tensor>,
    /// Header `__metadata__` entries.
    pub metadata: HashMap<String, String>,
}

/// Read a safetensors file (weights or checkpoint).
pub fn read_tensor_file(path: &Path) -> Result<TensorFile, TrainError> {
    let bad = |msg: String| TrainError::Checkpoint {
        path: path.into(),
        msg,
    };
    let bytes = std::fs::read(path).map_err(|e| TrainError::io(path, e))?;
    let (_, header) =
        safetensors::SafeTensors::read_metadata(&bytes).map_err(|e| bad(e.to_string()))?;
    let meta = header.metadata().clone().unwrap_or_default();
    let tensors = candle_core::safetensors::load_buffer(&bytes, &Device::Cpu)?;
    Ok(TensorFile {
        tensors,
        metadata: meta,
    })
}

/// A run directory (created if needed) and the paths inside it.
#[derive(Debug, Clone)]
pub struct RunDir {
    dir: PathBuf,
}

impl RunDir {
    /// Create `dir` if needed.
    pub fn create(dir: &Path) -> Result<Self, TrainError> {
        std::fs::create_dir_all(dir).map_err(|e| TrainError::io(dir, e))?;
        Ok(Self { dir: dir.into() })
    }

    /// The checkpoint's path.
    pub fn checkpoint(&self) -> PathBuf {
        self.dir.join(CHECKPOINT_FILE)
    }

    /// The log's path.
    pub fn log(&self) -> PathBuf {
        self.dir.join(LOG_FILE)
    }

    /// The final weights' path.
    pub fn weights(&self) -> PathBuf {
        self.dir.join(WEIGHTS_FILE)
    }

    /// The checkpoint to continue from: with `resume`, when there is one.
    pub fn checkpoint_to_resume(&self, resume: bool) -> Option<PathBuf> {
        let path = self.checkpoint();
        (resume && path.exists()).then_some(path)
    }

    /// Start the log: a fresh one with `header`, or, for a run resumed at
    /// step `resumed_at`, the old one without the rows after it.
    pub fn start_log(&self, header: &str, resumed_at: Option<u64>) -> Result<(), TrainError> {
        let log = self.log();
        match resumed_at {
            Some(step) => truncate_log(&log, step),
            None => {
                std::fs::write(&log, format!("{header}\n")).map_err(|e| TrainError::io(&log, e))
            }
        }
    }

    /// Write the run's configuration (pretty JSON).
    pub fn write_config<C: Serialize>(&self, config: &C) -> Result<(), TrainError> {
        std::fs::write(
            self.dir.join(CONFIG_FILE),
            serde_json::to_string_pretty(config)?,
        )
        .map_err(|e| TrainError::io(&self.dir, e))
    }

    /// Append one row (with its newline) to the log.
    pub fn append_log(&self, row: &str) -> Result<(), TrainError> {
        let log = self.log();
        std::fs::OpenOptions::new()
            .append(true)
            .open(&log)
            .and_then(|mut f| f.write_all(row.as_bytes()))
            .map_err(|e| TrainError::io(&log, e))
    }
}

/// The training steps since the last log row: mean loss and gradient norm,
/// and the throughput in items (frames or samples) per second.
#[derive(Debug, Clone)]
pub struct LogWindow {
    loss_sum: f64,
    grad_sum: f64,
    steps: usize,
    items: usize,
    since: Instant,
}

impl Default for LogWindow {
    fn default() -> Self {
        Self::new()
    }
}

impl LogWindow {
    /// An empty window starting now.
    pub fn new() -> Self {
        Self {
            loss_sum: 0.0,
            grad_sum: 0.0,
            steps: 0,
            items: 0,
            since: Instant::now(),
        }
    }

    /// Count one step of `items` items.
    pub fn add(&mut self, loss: f64, grad_norm: f64, items: usize) {
        self.loss_sum += loss;
        self.grad_sum += grad_norm;
        self.steps += 1;
        self.items += items;
    }

    /// Mean training loss of the window's steps.
    pub fn mean_loss(&self) -> f64 {
        self.loss_sum / self.steps as f64
    }

    /// Items per second since the window started.
    pub fn rate(&self) -> f64 {
        self.items as f64 / self.since.elapsed().as_secs_f64().max(1e-9)
    }

    /// The log row of step `step` (1-based count of steps done):
    /// `step,epoch,lr,train_loss_mm,grad_norm,rate` as every trainer logs
    /// them, then `validation` (3 decimals each) and `elapsed_s`. `lr` is
    /// the rate of the step just done, `rate` the throughput measured when
    /// it ended.
    pub fn row(
        &self,
        step: u64,
        schedule: &Schedule,
        rate: f64,
        validation: &[f64],
        elapsed_s: f64,
    ) -> String {
        let mut row = format!(
            "{step},{:.3},{:.3e},{:.3},{:.4},{rate:.0}",
            schedule.epoch(step),
            schedule.lr_at(step.saturating_sub(1)),
            self.mean_loss(),
            self.grad_sum / self.steps as f64,
        );
        for v in validation {
            row.push_str(&format!(",{v:.3}"));
        }
        row.push_str(&format!(",{elapsed_s:.1}\n"));
        row
    }
}

/// Wall-clock time of a run: this invocation and, for a resumed run, the
/// ones before it.
#[derive(Debug, Clone, Copy)]
pub struct RunClock {
    before_s: f64,
    start: Instant,
}

impl RunClock {
    /// A clock starting now, after `before_s` seconds of earlier
    /// invocations.
    pub fn start(before_s: f64) -> Self {
        Self {
            before_s,
            start: Instant::now(),
        }
    }

    /// Seconds of this invocation.
    pub fn this_run_s(&self) -> f64 {
        self.start.elapsed().as_secs_f64()
    }

    /// Seconds of every invocation.
    pub fn total_s(&self) -> f64 {
        self.before_s + self.this_run_s()
    }
}

/// When to write the next checkpoint: at the end, and whenever `secs`
/// seconds have passed since the last one.
#[derive(Debug, Clone, Copy)]
pub struct CheckpointTimer {
    secs: u64,
    last: Instant,
}

impl CheckpointTimer {
    /// A timer with period `secs`, starting now.
    pub fn new(secs: u64) -> Self {
        Self {
            secs,
            last: Instant::now(),
        }
    }

    /// Whether a checkpoint is due (always `at_end`); restarts the period
    /// when it is.
    pub fn due(&mut self, at_end: bool) -> bool {
        let due = at_end || self.last.elapsed().as_secs() >= self.secs;
        if due {
            self.last = Instant::now();
        }
        due
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_schedule_decays_per_epoch() {
        let s = Schedule {
            lr: 1e-3,
            decay: 0.5,
            epoch_steps: 10,
        };
        assert_eq!(s.lr_at(0), 1e-3);
        assert_eq!(s.lr_at(9), 1e-3);
        assert_eq!(s.lr_at(10), 5e-4);
        assert_eq!(s.epoch(15), 1.5);
        let no_period = Schedule {
            epoch_steps: 0,
            ..s
        };
        assert_eq!(no_period.lr_at(1), 5e-4);
    }

    #[test]
    fn a_log_row_has_the_shared_columns_then_the_trainers() {
        let s = Schedule {
            lr: 3e-4,
            decay: 0.9,
            epoch_steps: 500,
        };
        let mut w = LogWindow::new();
        w.add(10.0, 1.0, 64);
        w.add(12.0, 2.0, 64);
        let row = w.row(500, &s, 1234.4, &[1.23456, f64::NAN], 5.06);
        assert_eq!(row, "500,1.000,3.000e-4,11.000,1.5000,1234,1.235,NaN,5.1\n");
        // Step 501 ran at the second epoch's rate.
        assert!(w.row(501, &s, 0.0, &[], 0.0).contains(",2.700e-4,"));
    }

    #[test]
    fn a_resumed_log_keeps_its_rows_up_to_the_checkpoint() {
        let dir = std::env::temp_dir().join(format!("blapose-run-{}", std::process::id()));
        let run = RunDir::create(&dir).unwrap();
        run.start_log("step,x", None).unwrap();
        for step in 1..=4 {
            run.append_log(&format!("{step},{}\n", step * 10)).unwrap();
        }
        run.start_log("step,x", Some(2)).unwrap();
        assert_eq!(
            std::fs::read_to_string(run.log()).unwrap(),
            "step,x\n1,10\n2,20\n"
        );
        assert_eq!(
            read_log_column(&run.log(), "x").unwrap(),
            [(1.0, 10.0), (2.0, 20.0)]
        );
        assert!(run.checkpoint_to_resume(true).is_none());
        write_atomic(&run.checkpoint(), b"x").unwrap();
        assert_eq!(run.checkpoint_to_resume(true), Some(run.checkpoint()));
        assert!(run.checkpoint_to_resume(false).is_none());
        let _ = std::fs::remove_dir_all(&dir);
    }
}

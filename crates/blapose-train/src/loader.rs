//! Batches synthesized ahead of the training step.
//!
//! A producer thread builds batch `step` (in parallel with rayon) while the
//! optimizer works on batch `step - 1`, and hands it over through a bounded
//! channel: generation overlaps the GRU and memory stays bounded
//! (`depth` batches in flight). Batches depend only on `(seed, step)`, so
//! the sequence a consumer sees is the same for any thread count and for a
//! run resumed at any step.

use std::ops::Range;
use std::sync::mpsc::{sync_channel, Receiver};
use std::sync::Arc;
use std::thread::JoinHandle;

use crate::synth::{Batch, SynthConfig, SynthSource};

/// A running producer of batches for a range of steps.
pub struct Prefetcher {
    rx: Option<Receiver<(u64, Batch)>>,
    handle: Option<JoinHandle<()>>,
}

impl Prefetcher {
    /// Start producing batches for `steps` (at most `depth` ahead).
    pub fn spawn(
        source: Arc<SynthSource>,
        cfg: SynthConfig,
        seed: u64,
        batch: usize,
        steps: Range<u64>,
        depth: usize,
    ) -> Self {
        let (tx, rx) = sync_channel(depth.max(1));
        let handle = std::thread::Builder::new()
            .name("blapose-batches".into())
            .spawn(move || {
                for step in steps {
                    let b = source.batch(&cfg, seed, step, batch);
                    if tx.send((step, b)).is_err() {
                        break; // consumer gone
                    }
                }
            })
            .ok();
        Self {
            rx: Some(rx),
            handle,
        }
    }

    /// The next batch and its step; `None` when the range is exhausted or
    /// the producer could not start.
    pub fn next_batch(&mut self) -> Option<(u64, Batch)> {
        self.rx.as_ref()?.recv().ok()
    }
}

impl Drop for Prefetcher {
    fn drop(&mut self) {
        // Dropping the receiver makes the producer's next send fail.
        self.rx.take();
        if let Some(h) = self.handle.take() {
            let _ = h.join();
        }
    }
}

//! A gate that holds a fake model's steps.
//!
//! Tests of batching, backpressure and shutdown need frames provably
//! waiting inside the server at a chosen moment. Sleeping in a fake model
//! only makes that likely; a gate makes it certain: every step of a fake
//! that calls [`StepGate::pass`] blocks until the test opens the gate, and
//! the gate counts the steps that reached it, so a test waits for events,
//! never for time. The server's own unit tests and the integration tests
//! in `server/tests` share this one definition.

use std::sync::{Condvar, Mutex};

/// Holds model steps until opened and counts the steps that reached it.
#[derive(Debug, Default)]
pub struct StepGate {
    /// (open, steps entered)
    state: Mutex<(bool, usize)>,
    changed: Condvar,
}

impl StepGate {
    /// A closed gate that no step has reached.
    pub fn new() -> Self {
        Self::default()
    }

    /// Called by a fake model's step: count it, then wait until the gate
    /// is open.
    pub fn pass(&self) {
        let mut state = self.lock();
        state.1 += 1;
        self.changed.notify_all();
        while !state.0 {
            state = self
                .changed
                .wait(state)
                .unwrap_or_else(|poisoned| poisoned.into_inner());
        }
    }

    /// Open (let every waiting and later step through) or close the gate.
    pub fn set_open(&self, open: bool) {
        self.lock().0 = open;
        self.changed.notify_all();
    }

    /// Close the gate and forget the steps counted so far.
    pub fn close_and_reset(&self) {
        *self.lock() = (false, 0);
        self.changed.notify_all();
    }

    /// Steps that have reached the gate so far.
    pub fn entered(&self) -> usize {
        self.lock().1
    }

    /// Block the calling thread until `n` steps have reached the gate
    /// (from async code, call it inside `spawn_blocking`).
    pub fn wait_entered(&self, n: usize) {
        let mut state = self.lock();
        while state.1 < n {
            state = self
                .changed
                .wait(state)
                .unwrap_or_else(|poisoned| poisoned.into_inner());
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, (bool, usize)> {
        self.state
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Arc;

    #[test]
    fn steps_wait_until_the_gate_opens_and_are_counted() {
        let gate = Arc::new(StepGate::new());
        let worker = {
            let gate = gate.clone();
            std::thread::spawn(move || gate.pass())
        };
        gate.wait_entered(1);
        assert_eq!(gate.entered(), 1);
        assert!(!worker.is_finished() || gate.entered() == 1);
        gate.set_open(true);
        worker.join().unwrap();
        gate.pass(); // an open gate lets a step straight through
        assert_eq!(gate.entered(), 2);
        gate.close_and_reset();
        assert_eq!(gate.entered(), 0);
    }
}

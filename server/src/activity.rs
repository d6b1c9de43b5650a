//! One connection's activity, shared by the service that counts its
//! streams, the reader that counts its control frames and the watchdog
//! that closes it ([`crate::connection`]).
//!
//! Why its own type: HTTP/2 keepalive PINGs keep a TCP connection alive
//! but say nothing about whether anyone uses it, so "idle" here means *no
//! open stream* (gRPC's `MAX_CONNECTION_IDLE`), counted where streams
//! begin and end (the request reaches the service; its response body is
//! finished or dropped). A flood of control frames is seen below HTTP/2
//! (the bytes read) and raised here as an alarm the watchdog acts on at
//! once.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};

use tokio::sync::Notify;
use tokio::time::Instant;

/// Open streams and since when the connection has had none.
#[derive(Debug)]
struct Streams {
    open: usize,
    idle_since: Instant,
}

/// The shared activity record of one connection.
#[derive(Debug)]
pub struct Activity {
    born: Instant,
    streams: Mutex<Streams>,
    flood: AtomicBool,
    alarm: Notify,
}

impl Default for Activity {
    fn default() -> Self {
        Self::new()
    }
}

impl Activity {
    /// A connection that starts now with no stream.
    pub fn new() -> Self {
        let now = Instant::now();
        Self {
            born: now,
            streams: Mutex::new(Streams {
                open: 0,
                idle_since: now,
            }),
            flood: AtomicBool::new(false),
            alarm: Notify::new(),
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Streams> {
        self.streams
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner())
    }

    /// A stream began; it counts as open until the returned guard drops.
    pub fn stream(self: &Arc<Self>) -> StreamGuard {
        self.lock().open += 1;
        StreamGuard {
            activity: self.clone(),
        }
    }

    /// Streams open now.
    pub fn open_streams(&self) -> usize {
        self.lock().open
    }

    /// `None` while a stream is open, else since when none has been.
    pub fn idle_since(&self) -> Option<Instant> {
        let s = self.lock();
        (s.open == 0).then_some(s.idle_since)
    }

    /// When the connection started.
    pub fn born(&self) -> Instant {
        self.born
    }

    /// The connection floods control frames: close it now.
    pub fn raise_flood(&self) {
        if !self.flood.swap(true, Ordering::Relaxed) {
            self.alarm.notify_one();
        }
    }

    /// Whether [`Activity::raise_flood`] was called.
    pub fn flooding(&self) -> bool {
        self.flood.load(Ordering::Relaxed)
    }

    /// Resolves once a flood is raised (at once if it was).
    pub async fn flood_raised(&self) {
        while !self.flooding() {
            self.alarm.notified().await;
        }
    }
}

/// An open stream; closed when dropped.
#[derive(Debug)]
pub struct StreamGuard {
    activity: Arc<Activity>,
}

impl Drop for StreamGuard {
    fn drop(&mut self) {
        let mut s = self.activity.lock();
        s.open = s.open.saturating_sub(1);
        if s.open == 0 {
            s.idle_since = Instant::now();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test(start_paused = true)]
    async fn idle_means_no_open_stream() {
        let a = Arc::new(Activity::new());
        let born = a.idle_since().unwrap();
        let one = a.stream();
        let two = a.stream();
        assert_eq!(a.idle_since(), None);
        tokio::time::advance(std::time::Duration::from_secs(5)).await;
        drop(one);
        assert_eq!(a.idle_since(), None, "one still open");
        drop(two);
        assert_eq!(
            a.idle_since().unwrap() - born,
            std::time::Duration::from_secs(5)
        );
        assert!(!a.flooding());
        a.raise_flood();
        a.flood_raised().await;
        assert!(a.flooding());
    }
}

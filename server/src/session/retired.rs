//! What a session store remembers of sessions that ended, until their
//! session tokens would expire: a closed session so that its tokens cannot
//! revive it, an evicted one with the frames of the newest token issued for
//! it so that an older token cannot roll it back. Entries end after one
//! constant span (the token TTL), so insertion order is expiry order and a
//! queue prunes them in amortized constant time.

use std::collections::{HashMap, VecDeque};
use std::time::Duration;

use tokio::time::Instant;

use crate::metrics;
use crate::session::error::SessionError;
use crate::session::id::SessionId;

#[derive(Debug, Clone, Copy)]
struct Retired {
    until: Instant,
    closed: bool,
    /// Frames of the newest token issued for the session.
    newest_token: u64,
}

/// Ended sessions, remembered for the token TTL.
#[derive(Debug, Default)]
pub struct Memory {
    retired: HashMap<SessionId, Retired>,
    /// `retired`'s entries in the order they end.
    order: VecDeque<(Instant, SessionId)>,
}

impl Memory {
    /// Remember `id` (closed, or evicted with `newest_token`) for `span`
    /// (nothing for a zero span), forgetting whatever has run out.
    pub fn remember(&mut self, id: SessionId, closed: bool, newest_token: u64, span: Duration) {
        let now = Instant::now();
        while let Some(&(until, old)) = self.order.front() {
            if until > now {
                break;
            }
            self.order.pop_front();
            if self.retired.get(&old).is_some_and(|r| r.until == until) {
                self.retired.remove(&old);
            }
        }
        if span.is_zero() {
            return;
        }
        let until = now + span;
        self.retired.insert(
            id,
            Retired {
                until,
                closed,
                newest_token,
            },
        );
        self.order.push_back((until, id));
    }

    /// The session is held again: forget it.
    pub fn forget(&mut self, id: SessionId) {
        self.retired.remove(&id);
    }

    /// Whether a token as of `frames` frames may restore `id`.
    pub fn check(&self, id: SessionId, frames: u64) -> Result<(), SessionError> {
        match self.retired.get(&id) {
            Some(r) if r.until > Instant::now() => {
                if r.closed {
                    metrics::limited("closed_session");
                    Err(SessionError::Closed { id })
                } else if frames < r.newest_token {
                    metrics::limited("rollback");
                    Err(SessionError::Rollback {
                        id,
                        token: frames,
                        held: r.newest_token,
                    })
                } else {
                    Ok(())
                }
            }
            _ => Ok(()),
        }
    }
}

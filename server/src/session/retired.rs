//! What a session store remembers of sessions that ended, until their
//! session tokens would expire: a closed session so that its tokens cannot
//! revive it, an evicted one with the frames of the newest token issued for
//! it so that an older token cannot roll it back.
//!
//! Bounded in count, overall and per client: remembering every ended
//! session for the token TTL let one client within every quota, opening
//! and closing 19k sessions a second, grow the server by about 135 bytes a
//! session, gigabytes over the default hour. When an entry must go to make
//! room, its tokens must still not restore it, so instead of the entry a
//! *floor* is kept: the time it was remembered, after every token of its
//! session was issued. A token issued at or before the floor is refused
//! (FAILED_PRECONDITION) unless its session is held here. The floor is the
//! session owner's when the owner's share made room (tokens name the
//! client that held the session, so one client's churn only shortens the
//! restores of its own tokens), and the server's when the whole memory
//! did. Tokens are refreshed every `--token-every` frames, so a floor a few
//! seconds old refuses only tokens that live sessions have replaced.
//!
//! Entries end after one constant span (the token TTL), so insertion order
//! is expiry order: queues (global and per client) prune them in amortized
//! constant time, stale queue items (entries that went another way) are
//! skipped and compacted away.

use std::collections::{HashMap, VecDeque};
use std::time::Duration;

use tokio::time::Instant;

use crate::metrics;
use crate::quota::ClientId;
use crate::session::error::SessionError;
use crate::session::id::SessionId;
use crate::token::now_ms;

/// Default most ended sessions remembered at once.
pub const DEFAULT_MAX_ENDED: usize = 100_000;

#[derive(Debug, Clone, Copy)]
struct Retired {
    until: Instant,
    closed: bool,
    /// Frames of the newest token issued for the session.
    newest_token: u64,
    /// Who held it.
    client: ClientId,
    /// When it was remembered (ms since the Unix epoch): after every
    /// token of it was issued.
    at_ms: u64,
}

/// How many ended sessions are remembered.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct EndedLimits {
    /// All clients together.
    pub max: usize,
    /// One client.
    pub per_client: usize,
}

impl EndedLimits {
    /// `max` overall, and a sixteenth of it (at least 1,024, at most all)
    /// per client.
    pub fn with_max(max: usize) -> Self {
        let max = max.max(1);
        Self {
            max,
            per_client: (max / 16).max(1024).min(max),
        }
    }
}

impl Default for EndedLimits {
    fn default() -> Self {
        Self::with_max(DEFAULT_MAX_ENDED)
    }
}

/// A restored token's provenance, checked against the floors.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TokenStamp {
    /// When the token was issued (ms since the Unix epoch).
    pub issued_ms: u64,
    /// The client that held the session when it was issued.
    pub owner: Option<ClientId>,
}

/// Ended sessions, remembered for the token TTL, within [`EndedLimits`].
#[derive(Debug)]
pub struct Memory {
    limits: EndedLimits,
    retired: HashMap<SessionId, Retired>,
    /// `retired`'s entries in the order they end (with stale items).
    order: VecDeque<(Instant, SessionId)>,
    /// Each client's entries in the order they end (with stale items),
    /// and how many are live.
    by_client: HashMap<ClientId, (usize, VecDeque<(Instant, SessionId)>)>,
    /// Tokens issued at or before this are refused (the whole memory).
    floor_ms: u64,
    /// Per owner: tokens issued at or before the floor are refused, until
    /// the instant the evicted entry would have expired.
    client_floors: HashMap<ClientId, (u64, Instant)>,
}

impl Default for Memory {
    fn default() -> Self {
        Self::new(EndedLimits::default())
    }
}

impl Memory {
    /// An empty memory within `limits`.
    pub fn new(limits: EndedLimits) -> Self {
        Self {
            limits,
            retired: HashMap::new(),
            order: VecDeque::new(),
            by_client: HashMap::new(),
            floor_ms: 0,
            client_floors: HashMap::new(),
        }
    }

    /// Entries remembered now.
    pub fn remembered(&self) -> usize {
        self.retired.len()
    }

    /// Bytes the memory holds, about (entries, queue items, floors).
    pub fn approx_bytes(&self) -> usize {
        let entry = std::mem::size_of::<(SessionId, Retired)>() + 8;
        let item = std::mem::size_of::<(Instant, SessionId)>();
        let queued: usize = self.by_client.values().map(|(_, q)| q.capacity()).sum();
        self.retired.capacity() * entry
            + (self.order.capacity() + queued) * item
            + self.client_floors.capacity() * 48
    }

    fn live(&self, until: Instant, id: SessionId) -> bool {
        self.retired.get(&id).is_some_and(|r| r.until == until)
    }

    /// Drop `id`'s entry, keeping the per-client count.
    fn drop_entry(&mut self, id: SessionId) -> Option<Retired> {
        let r = self.retired.remove(&id)?;
        if let Some((n, queue)) = self.by_client.get_mut(&r.client) {
            *n -= 1;
            if *n == 0 {
                self.by_client.remove(&r.client);
            } else if queue.len() > 2 * *n + 64 {
                let retired = &self.retired;
                queue.retain(|&(until, id)| retired.get(&id).is_some_and(|r| r.until == until));
            }
        }
        Some(r)
    }

    /// Remember `id` (closed, or evicted with `newest_token`), held by
    /// `client`, for `span` (nothing for a zero span), forgetting whatever
    /// has run out and, past the limits, the oldest entry (its owner's or
    /// everyone's), whose tokens the floors then refuse.
    pub fn remember(
        &mut self,
        id: SessionId,
        closed: bool,
        newest_token: u64,
        span: Duration,
        client: ClientId,
    ) {
        let now = Instant::now();
        while let Some(&(until, old)) = self.order.front() {
            if until > now {
                break;
            }
            self.order.pop_front();
            if self.live(until, old) {
                self.drop_entry(old);
            }
        }
        self.client_floors.retain(|_, (_, until)| *until > now);
        if span.is_zero() {
            return;
        }
        self.drop_entry(id);
        let held = self.by_client.get(&client).map_or(0, |(n, _)| *n);
        if held >= self.limits.per_client {
            if let Some(evicted) = self.evict_oldest_of(client) {
                metrics::limited("ended_sessions_per_client");
                let floor = self.client_floors.entry(client).or_insert((0, now));
                *floor = (floor.0.max(evicted.at_ms), floor.1.max(evicted.until));
                if self.client_floors.len() > self.limits.max / self.limits.per_client * 4 + 16 {
                    // Too many owners' floors: fold them into the server's.
                    let highest = self.client_floors.values().map(|f| f.0).max();
                    self.floor_ms = self.floor_ms.max(highest.unwrap_or(0));
                    self.client_floors.clear();
                }
            }
        }
        if self.retired.len() >= self.limits.max {
            while let Some((until, old)) = self.order.pop_front() {
                if self.live(until, old) {
                    if let Some(evicted) = self.drop_entry(old) {
                        metrics::limited("ended_sessions");
                        self.floor_ms = self.floor_ms.max(evicted.at_ms);
                    }
                    break;
                }
            }
        }
        let until = now + span;
        self.retired.insert(
            id,
            Retired {
                until,
                closed,
                newest_token,
                client,
                at_ms: now_ms(),
            },
        );
        self.order.push_back((until, id));
        let (n, queue) = self.by_client.entry(client).or_default();
        *n += 1;
        queue.push_back((until, id));
        if self.order.len() > 2 * self.retired.len() + 1024 {
            let retired = &self.retired;
            self.order
                .retain(|&(until, id)| retired.get(&id).is_some_and(|r| r.until == until));
        }
    }

    fn evict_oldest_of(&mut self, client: ClientId) -> Option<Retired> {
        loop {
            let (until, id) = self.by_client.get_mut(&client)?.1.pop_front()?;
            if self.live(until, id) {
                return self.drop_entry(id);
            }
        }
    }

    /// The session is held again: forget it.
    pub fn forget(&mut self, id: SessionId) {
        self.drop_entry(id);
    }

    /// Whether a token as of `frames` frames, `stamp`ed, may restore `id`.
    pub fn check(&self, id: SessionId, frames: u64, stamp: TokenStamp) -> Result<(), SessionError> {
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
            _ => {
                let owner_floor = stamp
                    .owner
                    .and_then(|c| self.client_floors.get(&c))
                    .filter(|(_, until)| *until > Instant::now())
                    .map_or(0, |f| f.0);
                if stamp.issued_ms <= self.floor_ms.max(owner_floor) {
                    metrics::limited("ended_sessions_floor");
                    Err(SessionError::Forgotten { id })
                } else {
                    Ok(())
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn id(n: u32) -> SessionId {
        let mut b = [0u8; 16];
        b[..4].copy_from_slice(&n.to_le_bytes());
        SessionId::from_bytes(b)
    }

    fn stamp(issued_ms: u64, owner: ClientId) -> TokenStamp {
        TokenStamp {
            issued_ms,
            owner: Some(owner),
        }
    }

    #[tokio::test]
    async fn churn_keeps_the_memory_bounded_and_closed_sessions_closed() {
        let limits = EndedLimits {
            max: 5_000,
            per_client: 1_000,
        };
        let mut m = Memory::new(limits);
        let churner = ClientId::of("peer:churner");
        let other = ClientId::of("peer:other");
        let hour = Duration::from_secs(3600);
        // Another client's ended session, remembered before the churn.
        m.remember(id(u32::MAX), true, 0, hour, other);
        let before_churn = now_ms();
        let first_token = before_churn - 1;
        let mut peak = 0;
        for n in 0..200_000 {
            m.remember(id(n), true, 0, hour, churner);
            peak = peak.max(m.approx_bytes());
        }
        assert!(m.remembered() <= limits.max, "{}", m.remembered());
        assert!(peak < 2 << 20, "bounded memory: {peak} bytes");
        // Every churned session stays closed: the newest remembered ...
        let newest = m.check(id(199_999), 0, stamp(now_ms(), churner));
        assert!(
            matches!(newest, Err(SessionError::Closed { .. })),
            "{newest:?}"
        );
        // ... and the first, long forgotten, by the owner's floor.
        let first = m.check(id(0), 0, stamp(first_token, churner));
        assert!(
            matches!(first, Err(SessionError::Forgotten { .. })),
            "{first:?}"
        );
        // The other client's entry was not pushed out by the churn, and its
        // tokens are not held to the churner's floor.
        let kept = m.check(id(u32::MAX), 0, stamp(first_token, other));
        assert!(matches!(kept, Err(SessionError::Closed { .. })), "{kept:?}");
        assert!(m.check(id(7_000_000), 0, stamp(first_token, other)).is_ok());
        // A token issued after the floor restores.
        assert!(m.check(id(0), 0, stamp(now_ms() + 1, churner)).is_ok());
    }

    #[tokio::test]
    async fn the_whole_memory_full_raises_the_servers_floor() {
        let mut m = Memory::new(EndedLimits {
            max: 100,
            per_client: 100,
        });
        let hour = Duration::from_secs(3600);
        let token_ms = now_ms() - 1;
        for n in 0..300 {
            m.remember(id(n), false, 10, hour, ClientId::of(&format!("peer:{n}")));
        }
        assert_eq!(m.remembered(), 100);
        let anyone = TokenStamp {
            issued_ms: token_ms,
            owner: None,
        };
        assert!(matches!(
            m.check(id(0), 99, anyone),
            Err(SessionError::Forgotten { .. })
        ));
        // Remembered: the rollback rule as before.
        assert!(matches!(
            m.check(id(299), 5, anyone),
            Err(SessionError::Rollback { .. })
        ));
    }
}

//! The session store: the table of sessions, their idle TTL and its purge
//! task, per-client counts, and open, resume, restore and close.

use std::collections::{BTreeSet, HashMap};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};
use std::time::Duration;

use tokio::sync::Notify;
use tokio::time::Instant;

use crate::metrics;
use crate::quota::{ClientId, QuotaError};
use crate::session::error::SessionError;
use crate::session::id::SessionId;
use crate::session::retired::{EndedLimits, Memory, TokenStamp};
use crate::session::state::{load, Attachment, Session, SessionConfig, SessionSnapshot, StateCopy};

#[derive(Debug)]
struct Entry {
    session: Arc<Session>,
    /// `Some(deadline)` while detached.
    expires_at: Option<Instant>,
}

#[derive(Debug, Default)]
struct Inner {
    sessions: HashMap<SessionId, Entry>,
    expirations: BTreeSet<(Instant, SessionId)>,
    per_client: HashMap<ClientId, usize>,
    retired: Memory,
    shutdown: bool,
}

impl Inner {
    /// Refuse a new session of `client` beyond either limit.
    fn check_room(
        &self,
        client: ClientId,
        max: usize,
        per_client: usize,
    ) -> Result<(), SessionError> {
        if self.sessions.len() >= max {
            metrics::limited("max_sessions");
            return Err(SessionError::TooManySessions { max });
        }
        let held = self.per_client.get(&client).copied().unwrap_or(0);
        let (used, holders) = (self.sessions.len(), self.per_client.len());
        crate::quota::admit(per_client, max, used, holders, held).map_err(|limit| {
            metrics::limited("sessions_per_client");
            QuotaError::Sessions { limit }.into()
        })
    }

    /// Remove `id` from the table (closed or evicted) and remember it for
    /// `memory`.
    fn remove(&mut self, id: SessionId, closed: bool, memory: Duration) -> Option<Entry> {
        let entry = self.sessions.remove(&id)?;
        if let Some(when) = entry.expires_at {
            self.expirations.remove(&(when, id));
        }
        let client = entry.session.client();
        if let Some(n) = self.per_client.get_mut(&client) {
            *n = n.saturating_sub(1);
            if *n == 0 {
                self.per_client.remove(&client);
            }
        }
        let newest_token = entry.session.lock().newest_token;
        self.retired
            .remember(id, closed, newest_token, memory, entry.session.client());
        metrics::ended_sessions(self.retired.remembered());
        Some(entry)
    }

    /// Hold `session` under `id`, attached (opened, or restored from a
    /// token).
    fn admit(&mut self, id: SessionId, session: &Arc<Session>) {
        *self.per_client.entry(session.client()).or_default() += 1;
        self.retired.forget(id);
        self.sessions.insert(
            id,
            Entry {
                session: session.clone(),
                expires_at: None,
            },
        );
        metrics::session_opened(self.sessions.len());
    }
}

#[derive(Debug)]
struct Shared {
    inner: Mutex<Inner>,
    purge: Notify,
    ttl: Duration,
    max_sessions: usize,
    /// How long an ended session is remembered (the token TTL).
    memory: Duration,
    next_key: AtomicU64,
}

impl Shared {
    fn lock(&self) -> MutexGuard<'_, Inner> {
        self.inner.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Evict every session whose deadline has passed; return the next
    /// deadline, if any.
    fn purge_expired(&self) -> Option<Instant> {
        let mut inner = self.lock();
        if inner.shutdown {
            return None;
        }
        let now = Instant::now();
        while let Some(&(when, id)) = inner.expirations.iter().next() {
            if when > now {
                return Some(when);
            }
            inner.expirations.remove(&(when, id));
            if let Some(entry) = inner.remove(id, false, self.memory) {
                mark_closed(&entry.session);
                metrics::session_evicted(inner.sessions.len());
                tracing::info!(session = %id, "session evicted after its TTL");
            }
        }
        None
    }
}

fn mark_closed(session: &Session) -> SessionSnapshot {
    let mut st = session.lock();
    st.closed = true;
    session.publish(&st);
    SessionSnapshot {
        frames_seen: st.frames_seen(),
        bone_lengths: session.config().served(st.estimate()),
    }
}

/// The session store: bounded, with TTL eviction of detached sessions.
///
/// Cloning is cheap (shared handle). Dropping the last [`PurgeGuard`] stops
/// the purge task.
#[derive(Debug, Clone)]
pub struct SessionStore {
    shared: Arc<Shared>,
}

/// Stops the store's purge task when dropped.
#[derive(Debug)]
pub struct PurgeGuard {
    store: SessionStore,
}

impl Drop for PurgeGuard {
    fn drop(&mut self) {
        self.store.shared.lock().shutdown = true;
        self.store.shared.purge.notify_one();
    }
}

impl SessionStore {
    /// A store with the given limits, and its purge task spawned on the
    /// current tokio runtime. Keep the guard alive as long as the store.
    pub fn new(max_sessions: usize, ttl: Duration) -> (Self, PurgeGuard) {
        Self::with_memory(max_sessions, ttl, Duration::ZERO)
    }

    /// [`new`](Self::new), remembering each session that ends for
    /// `memory` (the session token TTL): a closed one is never restored
    /// from a token, an evicted one never from a token older than its state.
    pub fn with_memory(max_sessions: usize, ttl: Duration, memory: Duration) -> (Self, PurgeGuard) {
        Self::with_limits(max_sessions, ttl, memory, EndedLimits::default())
    }

    /// [`with_memory`](Self::with_memory), remembering at most `ended`
    /// ended sessions ([`crate::session::retired`]).
    pub fn with_limits(
        max_sessions: usize,
        ttl: Duration,
        memory: Duration,
        ended: EndedLimits,
    ) -> (Self, PurgeGuard) {
        let shared = Arc::new(Shared {
            inner: Mutex::new(Inner {
                retired: Memory::new(ended),
                ..Inner::default()
            }),
            purge: Notify::new(),
            ttl,
            max_sessions,
            memory,
            next_key: AtomicU64::new(1),
        });
        tokio::spawn(purge_task(shared.clone()));
        let store = Self { shared };
        (store.clone(), PurgeGuard { store })
    }

    /// TTL of detached sessions.
    pub fn ttl(&self) -> Duration {
        self.shared.ttl
    }

    /// Maximum sessions held.
    pub fn max_sessions(&self) -> usize {
        self.shared.max_sessions
    }

    /// Bytes the memory of ended sessions holds, about.
    pub fn ended_bytes(&self) -> usize {
        self.shared.lock().retired.approx_bytes()
    }

    /// Sessions currently held (attached or detached).
    pub fn len(&self) -> usize {
        self.shared.lock().sessions.len()
    }

    /// Whether the store holds no session.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Create a session, attached to the caller (no per-client limit).
    pub fn open(&self, config: SessionConfig) -> Result<Attachment, SessionError> {
        self.open_for(config, ClientId::default(), usize::MAX)
    }

    /// Create a session, attached to the caller, for a client holding fewer
    /// than `per_client` sessions.
    pub fn open_for(
        &self,
        config: SessionConfig,
        client: ClientId,
        per_client: usize,
    ) -> Result<Attachment, SessionError> {
        let id = SessionId::random().map_err(SessionError::Rng)?;
        let key = self.shared.next_key.fetch_add(1, Ordering::Relaxed);
        let session = Arc::new(Session::new(id, key, config, client));
        let mut inner = self.shared.lock();
        inner.check_room(client, self.shared.max_sessions, per_client)?;
        // 128 random bits: a collision is astronomically unlikely, but an id
        // must never silently replace another session.
        if inner.sessions.contains_key(&id) {
            return Err(SessionError::Rng("duplicate session id drawn".into()));
        }
        inner.admit(id, &session);
        drop(inner);
        Ok(Attachment {
            session,
            epoch: 1,
            snapshot: SessionSnapshot {
                frames_seen: 0,
                bone_lengths: None,
            },
        })
    }

    /// Re-create a session from a copy of its state (a session token) under
    /// its old id, attached to the caller as a resume. If this store holds
    /// the session, it is resumed (taking it over from any attached stream)
    /// and continues from `state`: the token names the state the client
    /// continues from (it may have lost answers after it).
    pub fn restore(
        &self,
        id: SessionId,
        config: SessionConfig,
        state: StateCopy,
        client: ClientId,
        per_client: usize,
        stamp: TokenStamp,
    ) -> Result<Attachment, SessionError> {
        if self.shared.lock().sessions.contains_key(&id) {
            // Take it over first: the old stream's frames are refused from
            // here on, so nothing changes the state after it is loaded.
            let mut attachment = self.resume(&id.to_string())?;
            let session = attachment.session.clone();
            let mut st = session.lock();
            if st.accepts(attachment.epoch) {
                load(&mut st, &state)?;
                attachment.snapshot = SessionSnapshot {
                    frames_seen: st.frames_seen(),
                    bone_lengths: session.config().served(st.estimate()),
                };
            }
            return Ok(attachment);
        }
        let key = self.shared.next_key.fetch_add(1, Ordering::Relaxed);
        let session = Arc::new(Session::new(id, key, config, client));
        let frames = state.frames_seen();
        {
            let mut st = session.lock();
            load(&mut st, &state)?;
            st.token_origin_ms = state.origin_ms;
            st.epoch = 2;
            session.publish(&st);
        }
        let mut inner = self.shared.lock();
        if inner.sessions.contains_key(&id) {
            // Another stream restored it meanwhile: resume that one.
            drop(inner);
            return self.resume(&id.to_string());
        }
        inner.retired.check(id, frames, stamp)?;
        inner.check_room(client, self.shared.max_sessions, per_client)?;
        inner.admit(id, &session);
        drop(inner);
        let st = session.lock();
        let snapshot = SessionSnapshot {
            frames_seen: st.frames_seen(),
            bone_lengths: session.config().served(st.estimate()),
        };
        drop(st);
        Ok(Attachment {
            session,
            epoch: 2,
            snapshot,
        })
    }

    /// Re-attach to a session by id, taking it over from any stream still
    /// attached (whose frames are refused from now on).
    pub fn resume(&self, id_text: &str) -> Result<Attachment, SessionError> {
        let not_found = || SessionError::NotFound {
            id: truncate(id_text, 64),
        };
        let id = SessionId::parse(id_text).ok_or_else(not_found)?;
        let mut inner = self.shared.lock();
        let entry = inner.sessions.get_mut(&id).ok_or_else(not_found)?;
        let previous_deadline = entry.expires_at.take();
        let session = entry.session.clone();
        if let Some(when) = previous_deadline {
            inner.expirations.remove(&(when, id));
        }
        let mut st = session.lock();
        st.epoch += 1;
        session.publish(&st);
        let attachment = Attachment {
            session: session.clone(),
            epoch: st.epoch,
            snapshot: SessionSnapshot {
                frames_seen: st.frames_seen(),
                bone_lengths: session.config().served(st.estimate()),
            },
        };
        drop(st);
        drop(inner);
        metrics::session_resumed();
        Ok(attachment)
    }

    /// The stream owning `epoch` is gone: start the session's TTL. No-op if
    /// another stream took the session over or it was closed.
    pub fn detach(&self, session: &Session, epoch: u64) {
        let mut inner = self.shared.lock();
        if !session.lock().accepts(epoch) {
            return;
        }
        let id = session.id();
        let when = Instant::now() + self.shared.ttl;
        let Some(entry) = inner.sessions.get_mut(&id) else {
            return;
        };
        if let Some(old) = entry.expires_at.replace(when) {
            inner.expirations.remove(&(old, id));
        }
        let earliest = inner.expirations.iter().next().map(|e| e.0);
        inner.expirations.insert((when, id));
        drop(inner);
        if earliest.is_none_or(|e| when < e) {
            self.shared.purge.notify_one();
        }
    }

    /// Close a session for good and return its final state.
    pub fn close(&self, id_text: &str) -> Result<SessionSnapshot, SessionError> {
        let not_found = || SessionError::NotFound {
            id: truncate(id_text, 64),
        };
        let id = SessionId::parse(id_text).ok_or_else(not_found)?;
        let mut inner = self.shared.lock();
        let memory = self.shared.memory;
        let entry = inner.remove(id, true, memory).ok_or_else(not_found)?;
        let remaining = inner.sessions.len();
        drop(inner);
        metrics::session_closed(remaining);
        Ok(mark_closed(&entry.session))
    }

    /// Whether a session with this id is held.
    pub fn contains(&self, id_text: &str) -> bool {
        SessionId::parse(id_text).is_some_and(|id| self.shared.lock().sessions.contains_key(&id))
    }
}

fn truncate(s: &str, max: usize) -> String {
    let mut end = s.len().min(max);
    while !s.is_char_boundary(end) {
        end -= 1;
    }
    s[..end].to_string()
}

async fn purge_task(shared: Arc<Shared>) {
    loop {
        if shared.lock().shutdown {
            return;
        }
        match shared.purge_expired() {
            Some(when) => {
                tokio::select! {
                    _ = tokio::time::sleep_until(when) => {}
                    _ = shared.purge.notified() => {}
                }
            }
            None => shared.purge.notified().await,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use blapose_core::NUM_BONES;

    use crate::fakes::session_config as config;

    #[test]
    fn only_lifting_sessions_hold_a_window() {
        let plain = Session::new(
            SessionId::from_bytes([2; 16]),
            1,
            config(),
            ClientId::default(),
        );
        assert!(plain.lock().window.is_none());
        let lifting = Session::new(
            SessionId::from_bytes([3; 16]),
            2,
            SessionConfig {
                lifter_frames: Some(27),
                camera: None,
                ..config()
            },
            ClientId::default(),
        );
        assert!(lifting.config().lifting());
        let st = lifting.lock();
        let window = st.window.as_deref().expect("a window");
        assert_eq!((window.frames(), window.len()), (27, 0));
    }

    #[test]
    fn ids_are_32_hex_chars_and_round_trip() {
        let id = SessionId::random().unwrap();
        let s = id.to_string();
        assert_eq!(s.len(), 32);
        assert!(s
            .bytes()
            .all(|c| c.is_ascii_hexdigit() && !c.is_ascii_uppercase()));
        assert_eq!(SessionId::parse(&s), Some(id));
        assert_eq!(SessionId::parse(&s.to_uppercase()), Some(id));
        assert_eq!(SessionId::parse(&s[..31]), None);
        assert_eq!(SessionId::parse(&format!("{}g", &s[..31])), None);
        assert_eq!(SessionId::parse(""), None);
        assert_eq!(SessionId::parse("ééééééééééééééééé"), None);
    }

    #[test]
    fn ids_look_uniformly_random() {
        // 2000 ids: all distinct, and every one of the 128 bit positions is
        // set in roughly half of them (a constant or counter-like generator,
        // or one with fewer random bits, fails this).
        let ids: Vec<SessionId> = (0..2000).map(|_| SessionId::random().unwrap()).collect();
        let distinct: std::collections::HashSet<_> = ids.iter().collect();
        assert_eq!(distinct.len(), ids.len());
        for bit in 0..128 {
            let ones = ids
                .iter()
                .filter(|id| id.as_bytes()[bit / 8] >> (bit % 8) & 1 == 1)
                .count();
            // Binomial(2000, 0.5): mean 1000, sd ~22; 6 sd either side.
            assert!(
                (866..=1134).contains(&ones),
                "bit {bit} set in {ones}/2000 ids"
            );
        }
    }

    #[tokio::test(start_paused = true)]
    async fn capacity_is_enforced_and_freed_by_close() {
        let (store, _guard) = SessionStore::new(2, Duration::from_secs(10));
        let a = store.open(config()).unwrap();
        let _b = store.open(config()).unwrap();
        let recorder = crate::metrics::test_recorder();
        let refused = ::metrics::with_local_recorder(&recorder, || store.open(config()));
        assert_eq!(
            refused.unwrap_err(),
            SessionError::TooManySessions { max: 2 }
        );
        assert_eq!(crate::metrics::limited_count(&recorder, "max_sessions"), 1);
        // Detached sessions still count.
        store.detach(&a.session, a.epoch);
        assert!(matches!(
            store.open(config()),
            Err(SessionError::TooManySessions { .. })
        ));
        store.close(&a.session.id().to_string()).unwrap();
        assert!(store.open(config()).is_ok());
        assert_eq!(store.len(), 2);
    }

    #[tokio::test(start_paused = true)]
    async fn detached_sessions_expire_after_ttl_and_attached_ones_never() {
        let ttl = Duration::from_secs(30);
        let (store, _guard) = SessionStore::new(10, ttl);
        let detached = store.open(config()).unwrap();
        let attached = store.open(config()).unwrap();
        let id = detached.session.id().to_string();
        store.detach(&detached.session, detached.epoch);
        let mut watch = detached.session.watch();

        tokio::time::sleep(ttl - Duration::from_millis(10)).await;
        assert!(store.contains(&id), "evicted before its TTL");
        tokio::time::sleep(Duration::from_millis(20)).await;
        assert!(!store.contains(&id), "not evicted after its TTL");
        assert!(watch.borrow_and_update().closed, "eviction is published");
        assert_eq!(
            store.resume(&id).unwrap_err(),
            SessionError::NotFound { id: id.clone() }
        );

        tokio::time::sleep(ttl * 10).await;
        assert!(store.contains(&attached.session.id().to_string()));
        assert_eq!(store.len(), 1);
    }

    #[tokio::test(start_paused = true)]
    async fn resume_within_ttl_keeps_state_and_cancels_expiry() {
        let ttl = Duration::from_secs(5);
        let (store, _guard) = SessionStore::new(10, ttl);
        let a = store.open(config()).unwrap();
        {
            let mut st = a.session.lock();
            st.hidden[7] = 0.25;
            for v in [0.2, 0.3, 0.4] {
                st.lengths.push(&[v; NUM_BONES]);
            }
        }
        store.detach(&a.session, a.epoch);
        tokio::time::sleep(ttl / 2).await;
        let id = a.session.id().to_string();
        let b = store.resume(&id).unwrap();
        assert!(Arc::ptr_eq(&a.session, &b.session));
        assert_eq!(b.snapshot.frames_seen, 3);
        assert!((b.snapshot.bone_lengths.unwrap()[3] - 0.3).abs() < 1e-6);
        assert_eq!(b.session.lock().hidden[7], 0.25);
        // The old epoch no longer owns it.
        assert!(!b.session.lock().accepts(a.epoch));
        assert!(b.session.lock().accepts(b.epoch));
        // Its old deadline is gone: it survives well past the original TTL.
        tokio::time::sleep(ttl * 3).await;
        assert!(store.contains(&id));
        // A stale detach (from the taken-over stream) does not start a TTL.
        store.detach(&a.session, a.epoch);
        tokio::time::sleep(ttl * 3).await;
        assert!(store.contains(&id));
        // The owner detaching does.
        store.detach(&b.session, b.epoch);
        tokio::time::sleep(ttl + Duration::from_millis(1)).await;
        assert!(!store.contains(&id));
    }

    #[tokio::test(start_paused = true)]
    async fn sessions_expire_in_deadline_order() {
        let (store, _guard) = SessionStore::new(10, Duration::from_secs(100));
        let long = store.open(config()).unwrap();
        store.detach(&long.session, long.epoch);
        tokio::time::sleep(Duration::from_secs(50)).await;
        let short = store.open(config()).unwrap();
        store.detach(&short.session, short.epoch);
        tokio::time::sleep(Duration::from_secs(51)).await;
        assert!(!store.contains(&long.session.id().to_string()));
        assert!(store.contains(&short.session.id().to_string()));
        tokio::time::sleep(Duration::from_secs(50)).await;
        assert!(store.is_empty());
    }

    #[tokio::test(start_paused = true)]
    async fn unknown_malformed_and_closed_ids_are_not_found() {
        let (store, _guard) = SessionStore::new(10, Duration::from_secs(5));
        let guess = SessionId::random().unwrap().to_string();
        assert!(matches!(
            store.resume(&guess),
            Err(SessionError::NotFound { .. })
        ));
        assert!(matches!(
            store.resume("not-an-id"),
            Err(SessionError::NotFound { .. })
        ));
        assert!(matches!(
            store.close(&guess),
            Err(SessionError::NotFound { .. })
        ));
        let a = store.open(config()).unwrap();
        let id = a.session.id().to_string();
        let snap = store.close(&id).unwrap();
        assert_eq!(snap.frames_seen, 0);
        assert!(a.session.lock().closed);
        assert!(!a.session.lock().accepts(a.epoch));
        assert!(matches!(
            store.resume(&id),
            Err(SessionError::NotFound { .. })
        ));
        assert!(matches!(
            store.close(&id),
            Err(SessionError::NotFound { .. })
        ));
    }

    #[test]
    fn estimate_is_the_running_mean() {
        let s = Session::new(
            SessionId::from_bytes([1; 16]),
            1,
            config(),
            ClientId::default(),
        );
        let mut g = s.lock();
        assert!(g.estimate().is_none());
        for v in [0.5, 1.0, 0.25, 1.25] {
            g.lengths.push(&[v; NUM_BONES]);
        }
        assert_eq!(g.frames_seen(), 4);
        assert_eq!(g.estimate(), Some([0.75; NUM_BONES]));
    }
}

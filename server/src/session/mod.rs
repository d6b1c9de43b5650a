//! Sessions: the per-stream state the online model carries between frames,
//! and the store that owns them.
//!
//! A session is the GRU's hidden state (2 x 512 floats), the running sum of
//! the per-frame length predictions, the number of frames seen and the input
//! format fixed at open. A session whose poses the server lifts also holds
//! the lifter's window of recent normalized keypoints; it is allocated only
//! for such sessions, so the others cost (almost) what they always did.
//!
//! A session outlives its stream on purpose: when a connection drops, the
//! session is *detached* and kept for the TTL so the client can resume it by
//! id with its state (the lifter's window included) intact. Expiry follows
//! mini-redis's `Db`: detached sessions sit in an ordered set of deadlines,
//! and one purge task sleeps until the earliest deadline (woken early when an
//! earlier one appears) instead of scanning the whole store on a timer.
//!
//! Ownership of a session by a stream is an *epoch*: every open or resume
//! bumps it, and work stamped with an older epoch (frames of a stream that
//! was taken over) is refused. The epoch lives in the same mutex as the
//! hidden state, so "resume" and "a batch finishing" can never interleave
//! halfway. A `watch` channel tells the attached stream when its epoch is no
//! longer current.
//!
//! Ids are 128 random bits from the operating system's CSPRNG, rendered as
//! 32 lowercase hex characters: knowing an id is the only credential needed
//! to resume a session, so it must be unguessable.
//!
//! Each session counts against the client that opened it
//! ([`crate::quota`]), so one client filling its share of the table leaves
//! the rest to the others. A session that ends (closed, or evicted after
//! its TTL) is *remembered* for the session token TTL: a closed one so its
//! tokens cannot revive it, an evicted one with the frames it had seen so
//! that an older token cannot roll it back (see `server/README.md`,
//! "Session tokens").
//!
//! The module's parts: [`state`] (one session: its configuration, model
//! state and owner), [`store`] (the table, TTL and purge, open, resume,
//! restore, close), [`retired`] (what is remembered of ended sessions),
//! [`id`] and [`error`].

mod error;
mod id;
mod retired;
mod state;
mod store;

pub use error::SessionError;
pub use id::SessionId;
pub use retired::{EndedLimits, TokenStamp, DEFAULT_MAX_ENDED};
pub use state::{
    Attachment, Coordinates, InputFormat, Ownership, RunningMean, Session, SessionCamera,
    SessionConfig, SessionSnapshot, SessionState, SessionSubject, StateCopy, MAX_LABEL_BYTES,
    STATE_DIM,
};
pub use store::{PurgeGuard, SessionStore};

//! Why a session store operation failed, each with what to do.

use crate::quota::QuotaError;
use crate::session::id::SessionId;

/// Why a store operation failed.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum SessionError {
    /// The store is full.
    #[error("the server already holds its maximum of {max} sessions; close unused sessions or retry later")]
    TooManySessions {
        /// The limit.
        max: usize,
    },
    /// No such session (never existed, expired, closed, or malformed id).
    #[error("no session {id:?} (unknown, expired or closed)")]
    NotFound {
        /// The id as given.
        id: String,
    },
    /// The OS random source failed.
    #[error("cannot draw a random session id: {0}")]
    Rng(String),
    /// A session token's state does not fit the session it describes.
    #[error("cannot restore the session: {0}")]
    Restore(String),
    /// A per-client limit.
    #[error(transparent)]
    Quota(#[from] QuotaError),
    /// The session was closed here: its tokens ended with it.
    #[error("session {id} was closed: its session tokens ended with it; open a new session")]
    Closed {
        /// The session.
        id: SessionId,
    },
    /// The token was issued before this server's memory of ended sessions
    /// reaches (it made room by forgetting older ones).
    #[error("the session token for {id} was issued before the oldest ended session this server still remembers (it keeps a bounded number): it may belong to a session that ended here, so it is refused; resume with a newer token or open a new session")]
    Forgotten {
        /// The session.
        id: SessionId,
    },
    /// The token is older than the newest this server issued for it.
    #[error("the session token for {id} is as of {token} frames, older than the newest token this server issued for it ({held} frames): a session is never rolled back; resume with its latest token")]
    Rollback {
        /// The session.
        id: SessionId,
        /// Frames seen in the token.
        token: u64,
        /// Frames this server last held.
        held: u64,
    },
}

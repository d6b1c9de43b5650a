//! End-to-end tests: a blapose server in this process on an ephemeral
//! loopback port, driven through the blapose-client library.
//!
//! One test binary (one link of the server and the model) with a module per
//! concern:
//! - [`streaming`]: many concurrent sessions, ordering, exactly-once
//!   answers, equality with the library path, offline RPC;
//! - [`sessions`]: TTL eviction, resume, takeover, guessed/foreign ids,
//!   session limits;
//! - [`errors`]: every status code the server defines, bad frames that do
//!   not corrupt a session, message size limits;
//! - [`lifter`]: the server lifter: keypoint-only sessions, refused frames
//!   that leave the lifter's window alone, resume, ModelInfo, start-up
//!   errors, client-pose sessions beside lifting ones;
//! - [`security`]: the bearer token and TLS;
//! - [`shutdown`]: graceful shutdown answers frames already received;
//! - [`example`]: replaying the shipped example improves its accuracy;
//! - [`failover`]: a replay resumed on another replica from its session
//!   token, directly and behind a switching proxy.
//!
//! The HTML report of `replay --html` belongs to the `blapose-client`
//! binary, so its end-to-end test runs that binary
//! (`client/tests/integration/html_report.rs`).

mod errors;
mod example;
mod failover;
mod lifter;
mod security;
mod sessions;
mod shutdown;
mod streaming;

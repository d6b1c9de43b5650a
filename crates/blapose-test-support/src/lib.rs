//! What blapose's tests share across crates, as one dev-only crate (the
//! pattern of tokio's `tokio-test` and tonic's integration-test crate).
//!
//! Why a crate: test helpers included into other crates' tests by file
//! path compile once per includer, warn as dead code wherever an includer
//! uses a part, and tie the crates' directory layouts together; helpers
//! shipped in a library's public API (the server's, before) are API nobody
//! should call. Here they are one crate that only `[dev-dependencies]`
//! name, and that is never published.
//!
//! Features keep each user's build small: the crates below the server
//! need only the always-built parts.
//!
//! - [`fuzz`]: the fixed-seed proptest configuration and byte mutations of
//!   the fuzz tests (blapose-core, blapose-data, blapose-server);
//! - [`gate`]: a gate that holds a fake model's steps (the server's unit
//!   and integration tests);
//! - with the `server` feature, [`model`] (a constant model), [`certs`]
//!   (self-signed certificates made by openssl, and a server behind them;
//!   the server's and the client's TLS tests) and [`h2raw`] (raw HTTP/2
//!   frames for the server's transport-limit tests);
//! - with the `train` feature, [`trials`] (random evaluation trials for
//!   the online estimator's tests, the trainer's and the lab's).

#[cfg(feature = "server")]
pub mod certs;
pub mod fuzz;
pub mod gate;
#[cfg(feature = "server")]
pub mod h2raw;
#[cfg(feature = "server")]
pub mod model;
#[cfg(feature = "train")]
pub mod trials;

pub use gate::StepGate;
#[cfg(feature = "server")]
pub use model::{spawn_constant, ConstantModel};

//! Replay files, as the client reads and writes them.
//!
//! The format is `blapose_data::replay`'s (the example generator writes the
//! same files, and must not depend on the client); this module re-exports
//! it under the client's name for it, so `blapose_client::sequence` and
//! `blapose_client::Sequence` keep meaning the replay file. See
//! [`blapose_data::replay`] for the keys, shapes and checks.

pub use blapose_data::replay::*;

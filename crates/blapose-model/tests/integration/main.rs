//! blapose-model's integration tests in one test binary (one link instead
//! of one per file). Two keep their own: `tests/no_alloc.rs` counts
//! allocations with a global allocator (any other test's would count), and
//! `tests/fast_agreement.rs` makes candle single-threaded before candle
//! reads its thread count, once per process.

mod bf16;
mod reference_models;
mod weights_files;

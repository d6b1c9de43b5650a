//! blapose-data's integration tests in one test binary (one link instead
//! of one per file). `tests/replay_bomb.rs` keeps its own: it measures
//! peak allocation with a global allocator that counts every thread's.

mod ansur_real;
mod fuzz_npz;
mod h36m_real;

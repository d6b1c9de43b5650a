//! blapose-lab's integration tests in one test binary (one link instead
//! of one per file).

mod bodies;
mod state_frames;

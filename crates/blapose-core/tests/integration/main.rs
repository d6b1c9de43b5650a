//! blapose-core's integration tests in one test binary (one link instead
//! of one per file).

mod fuzz_layouts;
mod metrics_fixture;
mod properties;

//! The client's integration tests in one test binary (one link of the
//! server they start).

// It runs the `blapose-client` binary, which needs the `cli` feature.
#[cfg(feature = "cli")]
mod html_report;
mod tls;

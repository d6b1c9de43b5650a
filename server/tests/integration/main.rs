//! The server's integration tests, one module per concern, in one test
//! binary: each binary links the whole server and the models, so one link
//! instead of a dozen is most of the workspace's test build time.
//!
//! Three stay in binaries of their own, because they need the process to
//! themselves: `tests/memory.rs` measures this process's resident set, and
//! `tests/metrics.rs` and `tests/transport_metrics.rs` install the
//! process-global Prometheus recorder (every server in the process would
//! then count into it).

mod budget;
mod connections;
mod fuzz_token;
mod fuzz_validate;
mod grpc;
mod haproxy;
mod limits;
mod motion;
mod quota;
mod support;
mod tls;
mod tokens;
mod web;

//! blapose-bench: measurements of blapose's hot paths and of the service.
//!
//! The binaries (`gru-step`, `fps-table`, `loadtest`) stay thin; what they
//! share or what deserves unit tests lives here. [`loadtest`] is the gRPC
//! load generator: N concurrent sessions through the client library against
//! an in-process or running server, with latency percentiles, error counts
//! and the server's own batch-size histogram. [`online`] is the per-frame
//! work `fps-table` times (a lifter stream, the adjustment) and [`timing`]
//! how it times it.

pub mod failover;
pub mod loadtest;
pub mod machine;
pub mod online;
pub mod timing;

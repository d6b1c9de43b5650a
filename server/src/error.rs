//! The library's error type: everything that can stop a server from starting
//! or running.

use crate::backend::BackendError;
use crate::metrics::MetricsError;
use crate::models::WeightsError;

/// Why the server could not start or stopped with an error.
#[derive(Debug, thiserror::Error)]
pub enum ServerError {
    /// Weights missing or invalid.
    #[error(transparent)]
    Weights(#[from] WeightsError),
    /// The model backend failed to build or warm up.
    #[error("model backend: {0}")]
    Backend(#[from] BackendError),
    /// The metrics exporter could not start.
    #[error(transparent)]
    Metrics(#[from] MetricsError),
    /// TLS files unreadable or invalid.
    #[error("TLS: {0}")]
    Tls(String),
    /// Listener or socket error.
    #[error("I/O: {0}")]
    Io(#[from] std::io::Error),
    /// Reflection service could not be built.
    #[error("reflection: {0}")]
    Reflection(String),
    /// The gRPC transport failed.
    #[error("transport: {0}")]
    Transport(#[from] tonic::transport::Error),
    /// A background task failed.
    #[error("server task failed: {0}")]
    Task(String),
}

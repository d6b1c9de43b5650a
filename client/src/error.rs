//! The one error type of the client library.
//!
//! Callers need to tell apart three kinds of failure: the server could not be
//! reached (retrying later may help), the server refused a request (a gRPC
//! status with the server's own explanation), and the local input was wrong
//! (a replay file with a missing key or a misshaped array). Each has its own
//! variant so the CLI can print a message that says which it was.

use std::time::Duration;

/// Everything the client library can fail with.
#[derive(Debug, thiserror::Error)]
pub enum ClientError {
    /// The server URL could not be parsed or used (bad scheme, bad TLS setup).
    #[error("invalid server endpoint {endpoint:?}: {reason}")]
    InvalidEndpoint {
        /// The URL as given.
        endpoint: String,
        /// What is wrong with it.
        reason: String,
    },
    /// Every connection attempt failed.
    #[error("could not connect to {endpoint} after {attempts} attempt(s): {last_error}")]
    Connect {
        /// The server URL.
        endpoint: String,
        /// How many attempts were made.
        attempts: u32,
        /// The last transport error seen.
        last_error: String,
    },
    /// The bearer token cannot be sent as an HTTP header value.
    #[error("the bearer token contains characters not allowed in an HTTP header")]
    InvalidToken,
    /// The server (or the transport) ended a call with a gRPC status. A
    /// transport failure's causes follow the message (tonic's message
    /// alone says "h2 protocol error: http2 error"; the cause says why,
    /// e.g. that the server speaks TLS).
    #[error("server returned {}: {}{}", .0.code(), .0.message(), causes(.0))]
    Status(#[from] tonic::Status),
    /// A whole-sequence request over the server's message size limit
    /// (OUT_OF_RANGE): says which limit and what to do.
    #[error(
        "the {frames}-frame sequence is one message too large for the server ({detail}): \
         raise the server's --max-message-bytes (BLAPOSE_MAX_MESSAGE_BYTES; ModelInfo reports \
         it), or stream the file with `blapose-client replay`, which sends one frame per message"
    )]
    MessageTooLarge {
        /// Frames in the request.
        frames: u32,
        /// The server's message (the request's size and the limit).
        detail: String,
    },
    /// A call did not finish within its deadline.
    #[error("{what} timed out after {after:?}")]
    Timeout {
        /// Which call.
        what: &'static str,
        /// The deadline.
        after: Duration,
    },
    /// The server answered something the protocol does not allow here
    /// (e.g. a frame answer before the session was opened).
    #[error("protocol violation by the server: {0}")]
    Protocol(String),
    /// The server rejected one frame (the session itself is unharmed).
    #[error("frame {frame_index} rejected by the server ({code}): {message}")]
    FrameRejected {
        /// The rejected frame's index.
        frame_index: u64,
        /// The gRPC status code the server gave.
        code: tonic::Code,
        /// The server's explanation.
        message: String,
    },
    /// The session's stream ended before every frame was answered.
    #[error("the stream ended after {answered} of {sent} frames were answered")]
    StreamEnded {
        /// Frames answered.
        answered: u64,
        /// Frames sent.
        sent: u64,
    },
    /// Local input (a frame or a sequence) is malformed.
    #[error("invalid input: {0}")]
    InvalidInput(String),
    /// A replay file could not be read or has the wrong content.
    #[error(transparent)]
    Sequence(#[from] blapose_data::replay::SequenceError),
    /// Metrics could not be computed (mismatched lengths).
    #[error("metrics: {0}")]
    Metric(#[from] blapose_core::metrics::MetricError),
}

/// `": cause: cause..."` for the source chain of `status`, leaving out
/// what its message already says.
fn causes(status: &tonic::Status) -> String {
    let mut out = String::new();
    let mut next = std::error::Error::source(status);
    while let Some(cause) = next {
        let text = cause.to_string();
        if !status.message().contains(&text) && !out.contains(&text) {
            out.push_str(": ");
            out.push_str(&text);
        }
        next = cause.source();
    }
    out
}

impl ClientError {
    /// The gRPC status code when the server ended a call with one.
    pub fn code(&self) -> Option<tonic::Code> {
        match self {
            ClientError::Status(s) => Some(s.code()),
            ClientError::FrameRejected { code, .. } => Some(*code),
            ClientError::MessageTooLarge { .. } => Some(tonic::Code::OutOfRange),
            _ => None,
        }
    }
}

//! Checks on a session token's state before it is restored: a valid
//! signature says a replica holding the key wrote the token, not that its
//! state is one a session can be in (a leaked key, a bug in another
//! release, or a replica's corrupted memory would all sign garbage). So a
//! restored state is checked as an open's input is: every value finite and
//! in its range, counts that cannot overflow on the next frame, an input
//! format an open would accept, and the token's age within the token TTL.
//!
//! Each refusal names the field (INVALID_ARGUMENT), or the expiry
//! (FAILED_PRECONDITION: the token was fine once, the client must open a
//! new session).

use std::time::Duration;

use crate::token::PortableState;
use crate::validate::{self, MAX_KEYPOINT_ABS};

/// Largest magnitude of a GRU hidden-state value: the state is a convex
/// combination of `tanh` outputs and the zero start, so within [-1, 1]
/// (with room for f32 rounding).
pub const MAX_HIDDEN_ABS: f32 = 1.0 + 1e-3;
/// Largest mean bone-length prediction accepted, in metres.
pub const MAX_MEAN_LENGTH_M: f64 = 10.0;
/// Most frames a restored session may have seen: 2^53, where an f64 still
/// counts exactly, far from overflowing on the next frame.
pub const MAX_FRAMES: u64 = 1 << 53;
/// How far in the future a token's issue time may be (replicas' clocks
/// differ a little).
pub const CLOCK_SKEW: Duration = Duration::from_secs(300);

/// Why a token's state is not restored.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RestoreError {
    /// A field holds a value no session can have.
    #[error("the session token's {field} is not a state a session can be in: {reason}")]
    Field {
        /// The field.
        field: String,
        /// What is wrong with it.
        reason: String,
    },
    /// The token is older than the token TTL.
    #[error("the session token expired: it (or the first token of the chain of restores it comes from) was issued {age_s} s ago and tokens are accepted for {ttl_s} s (--token-ttl); open a new session")]
    Expired {
        /// Its age in seconds.
        age_s: u64,
        /// The TTL in seconds.
        ttl_s: u64,
    },
}

impl RestoreError {
    /// The status a resume with such a token ends with.
    pub fn to_status(&self) -> tonic::Status {
        match self {
            Self::Field { .. } => tonic::Status::invalid_argument(self.to_string()),
            Self::Expired { .. } => tonic::Status::failed_precondition(self.to_string()),
        }
    }
}

fn field(field: impl Into<String>, reason: impl Into<String>) -> RestoreError {
    RestoreError::Field {
        field: field.into(),
        reason: reason.into(),
    }
}

/// Check `state` (from a token opened at `now_ms`) against the TTL and the
/// ranges a session's state keeps.
pub fn check(state: &PortableState, now_ms: u64, ttl: Duration) -> Result<(), RestoreError> {
    let ttl_ms = u64::try_from(ttl.as_millis()).unwrap_or(u64::MAX);
    let skew_ms = u64::try_from(CLOCK_SKEW.as_millis()).unwrap_or(u64::MAX);
    if state.issued_at_ms > now_ms.saturating_add(skew_ms) {
        return Err(field(
            "issue time",
            format!(
                "issued {} s in the future",
                (state.issued_at_ms - now_ms) / 1000
            ),
        ));
    }
    if state.origin_ms.is_some_and(|o| o > state.issued_at_ms) {
        return Err(field(
            "chain origin",
            "after the token's own issue time (a chain starts before its tokens)",
        ));
    }
    // A restored session's tokens age from the first token of the chain.
    let age_ms = now_ms.saturating_sub(state.expiry_origin_ms());
    if age_ms > ttl_ms {
        return Err(RestoreError::Expired {
            age_s: age_ms / 1000,
            ttl_s: ttl.as_secs(),
        });
    }
    validate::input_format(Some(&validate::input_format_to_proto(&state.input)))
        .map_err(|e| field("input format", e.to_string()))?;
    for (i, &v) in state.hidden.iter().enumerate() {
        if !v.is_finite() || v.abs() > MAX_HIDDEN_ABS {
            return Err(field(
                format!("hidden state [{i}]"),
                format!("{v} (a GRU state lies within +-1)"),
            ));
        }
    }
    if let Some(m) = &state.motion {
        let values = m.state.directions.iter().chain(&m.state.root);
        if let Some((i, v)) = values.enumerate().find(|(_, v)| !v.is_finite()) {
            return Err(field(format!("motion filter state [{i}]"), format!("{v}")));
        }
    }
    let count = state.lengths.count();
    for (name, n) in [
        ("frames read", count),
        ("frames without a joint", state.skipped),
    ] {
        if n > MAX_FRAMES {
            return Err(field(name, format!("{n}, more than {MAX_FRAMES}")));
        }
    }
    if count + state.skipped > MAX_FRAMES {
        return Err(field(
            "frames seen",
            format!("{}, more than {MAX_FRAMES}", count + state.skipped),
        ));
    }
    for (b, &s) in state.lengths.sum().iter().enumerate() {
        let bad = if !s.is_finite() {
            Some(format!("{s}"))
        } else if count == 0 && s != 0.0 {
            Some(format!("{s} with no frame read"))
        } else if count > 0 && (s / count as f64).abs() > MAX_MEAN_LENGTH_M {
            Some(format!(
                "a mean of {} m, beyond +-{MAX_MEAN_LENGTH_M} m",
                s / count as f64
            ))
        } else {
            None
        };
        if let Some(reason) = bad {
            return Err(field(format!("running sum [bone {b}]"), reason));
        }
    }
    for (j, p) in state.held.last().iter().enumerate() {
        if let Some(p) = p {
            check_point(&format!("held joint [{j}]"), p)?;
        }
    }
    if let Some(w) = &state.window {
        if w.frames.len() > w.receptive_field {
            return Err(field(
                "lifter window",
                format!(
                    "{} frames for a receptive field of {}",
                    w.frames.len(),
                    w.receptive_field
                ),
            ));
        }
        for (f, frame) in w.frames.iter().enumerate() {
            for (j, p) in frame.iter().enumerate() {
                check_point(&format!("lifter window [frame {f}, joint {j}]"), p)?;
            }
        }
    }
    Ok(())
}

fn check_point(name: &str, p: &[f32; 2]) -> Result<(), RestoreError> {
    for v in p {
        if !v.is_finite() || v.abs() > MAX_KEYPOINT_ABS {
            return Err(field(name, format!("{v}")));
        }
    }
    Ok(())
}

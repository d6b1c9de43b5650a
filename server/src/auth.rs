//! Optional bearer-token check for the blapose.v1 service.
//!
//! A shared secret is the simplest credential that works with every gRPC
//! client (it is just an `authorization: Bearer <token>` header); use it
//! together with TLS, or the token travels in the clear. The comparison
//! takes the same time wherever the first difference is, so the token cannot
//! be recovered byte by byte from response timing. Health and reflection are
//! deliberately left open so probes and tooling work without the secret.
//!
//! The browser transport ([`crate::web`]) checks the same token with
//! [`BearerAuth::check`]: browsers cannot set headers on a WebSocket, so
//! there it may also arrive as a subprotocol or a query parameter.

use std::sync::Arc;

use tonic::service::Interceptor;
use tonic::{Request, Status};

/// Checks `authorization: Bearer <token>` when a token is configured.
#[derive(Debug, Clone, Default)]
pub struct BearerAuth {
    token: Option<Arc<[u8]>>,
}

impl BearerAuth {
    /// Require `token` (`None` lets every request through).
    pub fn new(token: Option<&str>) -> Self {
        Self {
            token: token.map(|t| Arc::from(t.as_bytes())),
        }
    }
}

/// Equality in time independent of where the inputs differ.
fn constant_time_eq(a: &[u8], b: &[u8]) -> bool {
    if a.len() != b.len() {
        return false;
    }
    a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

impl BearerAuth {
    /// Whether a token is required at all.
    pub fn required(&self) -> bool {
        self.token.is_some()
    }

    /// Check a presented token (the part after `Bearer `; `None`: none
    /// presented, `missing` says where it was expected). Refusals are
    /// counted in `blapose_errors_total{rpc="auth"}`.
    pub fn check(&self, presented: Option<&[u8]>, missing: &str) -> Result<(), Status> {
        let Some(token) = &self.token else {
            return Ok(());
        };
        let refused = match presented {
            None => Status::unauthenticated(missing.to_string()),
            Some(p) if constant_time_eq(p, token) => return Ok(()),
            Some(_) => Status::unauthenticated("invalid bearer token"),
        };
        crate::metrics::error(tonic::Code::Unauthenticated, "auth");
        Err(refused)
    }
}

/// The token of an `authorization` header value, `Bearer <token>` (the
/// scheme in any case); `None` for another scheme.
pub fn bearer_token(value: &[u8]) -> Option<&[u8]> {
    (value.len() > 7 && value[..7].eq_ignore_ascii_case(b"bearer ")).then(|| &value[7..])
}

impl Interceptor for BearerAuth {
    fn call(&mut self, request: Request<()>) -> Result<Request<()>, Status> {
        let presented = match request.metadata().get("authorization") {
            // Another scheme is a wrong token, not a missing one.
            Some(value) => Some(bearer_token(value.as_bytes()).unwrap_or(b"")),
            None => None,
        };
        self.check(
            presented,
            "missing authorization header (expected: Bearer <token>)",
        )?;
        Ok(request)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn request(header: Option<&str>) -> Request<()> {
        let mut r = Request::new(());
        if let Some(h) = header {
            r.metadata_mut().insert("authorization", h.parse().unwrap());
        }
        r
    }

    #[test]
    fn no_token_lets_everything_through() {
        let mut auth = BearerAuth::new(None);
        assert!(auth.call(request(None)).is_ok());
        assert!(auth.call(request(Some("Bearer whatever"))).is_ok());
    }

    #[test]
    fn token_is_required_and_compared_exactly() {
        let mut auth = BearerAuth::new(Some("s3cret"));
        assert!(auth.call(request(Some("Bearer s3cret"))).is_ok());
        assert!(auth.call(request(Some("bearer s3cret"))).is_ok());
        for bad in [
            None,
            Some("Bearer s3cre"),
            Some("Bearer s3cret2"),
            Some("Basic s3cret"),
            Some("s3cret"),
            Some("Bearer "),
        ] {
            let err = auth.call(request(bad)).unwrap_err();
            assert_eq!(err.code(), tonic::Code::Unauthenticated, "{bad:?}");
        }
    }

    #[test]
    fn constant_time_eq_is_equality() {
        assert!(constant_time_eq(b"abc", b"abc"));
        assert!(!constant_time_eq(b"abc", b"abd"));
        assert!(!constant_time_eq(b"abc", b"ab"));
        assert!(constant_time_eq(b"", b""));
    }
}

//! How to reach a server: the settings, the endpoint they build, and the
//! metadata sent with every call.
//!
//! Both the unary calls ([`Client`](crate::Client)) and the streams
//! ([`Session`](crate::Session)) go through the stub built here, so the
//! settings sit below both: a session starts from a stub and these
//! settings, not from the client that made them.

use std::time::Duration;

use blapose_proto::v1::pose_adjustment_client::PoseAdjustmentClient;
use tonic::metadata::{AsciiMetadataValue, MetadataValue};
use tonic::service::interceptor::InterceptedService;
use tonic::transport::{Channel, ClientTlsConfig, Endpoint};

use crate::error::ClientError;

/// Default server address (the server's own default `--addr`).
pub const DEFAULT_SERVER: &str = "http://127.0.0.1:50051";

/// TLS settings; TLS is used when the URL is `https://` or a CA is given.
#[derive(Debug, Clone, Default)]
pub struct TlsOptions {
    /// PEM of the CA that signed the server's certificate, or of the
    /// server's self-signed certificate itself (accepted even when marked
    /// CA:TRUE, as `openssl req -x509` makes it: it is pinned, see
    /// `blapose_tls`). Without it the operating system's trust store is
    /// used.
    pub ca_cert_pem: Option<Vec<u8>>,
    /// Name to verify the server certificate against (default: the URL host).
    pub domain: Option<String>,
}

/// How to reach the server.
#[derive(Debug, Clone)]
pub struct ClientConfig {
    /// Server URL, e.g. `http://127.0.0.1:50051` or `https://pose.example:443`.
    pub endpoint: String,
    /// Deadline for establishing one connection.
    pub connect_timeout: Duration,
    /// Connection attempts before giving up (at least 1).
    pub connect_attempts: u32,
    /// Pause after the first failed attempt; doubles after each further
    /// failure, capped at 5 s.
    pub retry_backoff: Duration,
    /// Deadline for unary calls and for opening a session.
    pub request_timeout: Duration,
    /// Optional bearer token, sent as `authorization: Bearer <token>`.
    pub token: Option<String>,
    /// TLS settings.
    pub tls: TlsOptions,
    /// Largest message this client encodes or decodes (a whole offline
    /// sequence travels in one message).
    pub max_message_bytes: usize,
    /// Frames a session may queue locally before `send` waits.
    pub session_buffer: usize,
}

impl ClientConfig {
    /// Defaults for `endpoint`: 5 s connect timeout, 5 attempts starting at
    /// 200 ms backoff, 60 s request deadline, no token, 256 MiB messages.
    pub fn new(endpoint: impl Into<String>) -> Self {
        ClientConfig {
            endpoint: endpoint.into(),
            connect_timeout: Duration::from_secs(5),
            connect_attempts: 5,
            retry_backoff: Duration::from_millis(200),
            request_timeout: Duration::from_secs(60),
            token: None,
            tls: TlsOptions::default(),
            max_message_bytes: 256 * 1024 * 1024,
            session_buffer: 256,
        }
    }

    /// Builder-style setter for the bearer token.
    pub fn with_token(mut self, token: impl Into<String>) -> Self {
        self.token = Some(token.into());
        self
    }
}

impl Default for ClientConfig {
    fn default() -> Self {
        ClientConfig::new(DEFAULT_SERVER)
    }
}

/// The gRPC metadata key that ties a session's streams and calls together
/// for a load balancer: `deploy/haproxy.cfg` hashes on it (consistent
/// hashing), so every stream of one session reaches the same replica while
/// it is up.
pub const AFFINITY_HEADER: &str = "blapose-affinity";

/// A fresh affinity key (32 random hex digits) for one session.
pub fn new_affinity_key() -> String {
    format!("{:032x}", rand::random::<u128>())
}

/// Metadata added to every request: the bearer token, and the session's
/// affinity key on a [`Client::with_affinity`](crate::Client::with_affinity)
/// handle.
#[derive(Debug, Clone)]
pub struct CallMetadata {
    authorization: Option<AsciiMetadataValue>,
    affinity: Option<AsciiMetadataValue>,
}

impl CallMetadata {
    /// The metadata of a connection with `token` (no affinity key).
    pub(crate) fn new(token: Option<&str>) -> Result<Self, ClientError> {
        let authorization = token
            .map(|t| {
                MetadataValue::try_from(format!("Bearer {t}"))
                    .map_err(|_| ClientError::InvalidToken)
            })
            .transpose()?;
        Ok(CallMetadata {
            authorization,
            affinity: None,
        })
    }

    /// The same metadata, also sending `key` as the [`AFFINITY_HEADER`].
    pub(crate) fn with_affinity(self, key: &str) -> Result<Self, ClientError> {
        let affinity = MetadataValue::try_from(key).map_err(|_| {
            ClientError::InvalidInput(format!(
                "the affinity key {key:?} is not a valid gRPC metadata value"
            ))
        })?;
        Ok(CallMetadata {
            affinity: Some(affinity),
            ..self
        })
    }
}

impl tonic::service::Interceptor for CallMetadata {
    fn call(&mut self, mut req: tonic::Request<()>) -> Result<tonic::Request<()>, tonic::Status> {
        if let Some(h) = &self.authorization {
            req.metadata_mut().insert("authorization", h.clone());
        }
        if let Some(key) = &self.affinity {
            req.metadata_mut().insert(AFFINITY_HEADER, key.clone());
        }
        Ok(req)
    }
}

/// The generated stub with authentication applied.
pub(crate) type Stub = PoseAdjustmentClient<InterceptedService<Channel, CallMetadata>>;

/// The stub on `channel` sending `metadata`, with `config`'s message limits.
pub(crate) fn new_stub(channel: Channel, metadata: CallMetadata, config: &ClientConfig) -> Stub {
    PoseAdjustmentClient::with_interceptor(channel, metadata)
        .max_decoding_message_size(config.max_message_bytes)
        .max_encoding_message_size(config.max_message_bytes)
}

/// How to open a channel to the server: tonic's endpoint, and with a CA
/// given, blapose-tls's connector (which pins a self-signed certificate
/// and says when the server speaks plaintext).
#[derive(Debug, Clone)]
pub(crate) struct Target {
    endpoint: Endpoint,
    tls: Option<blapose_tls::TlsConnector>,
}

impl Target {
    /// Connect now.
    pub(crate) async fn connect(&self) -> Result<Channel, tonic::transport::Error> {
        match &self.tls {
            Some(tls) => self.endpoint.connect_with_connector(tls.clone()).await,
            None => self.endpoint.connect().await,
        }
    }

    /// A channel that connects at its first call.
    pub(crate) fn connect_lazy(&self) -> Channel {
        match &self.tls {
            Some(tls) => self.endpoint.connect_with_connector_lazy(tls.clone()),
            None => self.endpoint.connect_lazy(),
        }
    }
}

/// The endpoint `config` describes: URL, timeouts, keep-alive and TLS.
pub(crate) fn build_endpoint(config: &ClientConfig) -> Result<Target, ClientError> {
    let invalid = |reason: String| ClientError::InvalidEndpoint {
        endpoint: config.endpoint.clone(),
        reason,
    };
    let uri: tonic::codegen::http::Uri = config
        .endpoint
        .parse()
        .map_err(|e: tonic::codegen::http::uri::InvalidUri| invalid(e.to_string()))?;
    let scheme = uri.scheme_str().unwrap_or("").to_ascii_lowercase();
    match scheme.as_str() {
        "http" | "https" => {}
        other => {
            return Err(invalid(format!(
                "unsupported scheme {other:?} (use http:// or https://)"
            )))
        }
    }
    // With a CA, blapose-tls's connector does TLS: tonic must then see a
    // plain http:// URI.
    let tls = config
        .tls
        .ca_cert_pem
        .as_ref()
        .map(|pem| blapose_tls::TlsConnector::new(pem, config.tls.domain.clone()))
        .transpose()
        .map_err(|e| invalid(e.to_string()))?;
    let url = match tls {
        Some(_) => blapose_tls::plain_scheme(&config.endpoint),
        None => config.endpoint.clone(),
    };
    let mut endpoint = Endpoint::from_shared(url)
        .map_err(|e| invalid(e.to_string()))?
        .connect_timeout(config.connect_timeout)
        .tcp_nodelay(true)
        .http2_keep_alive_interval(Duration::from_secs(30))
        .keep_alive_while_idle(true);
    if scheme == "https" && tls.is_none() {
        let mut native = ClientTlsConfig::new().with_native_roots();
        if let Some(domain) = &config.tls.domain {
            native = native.domain_name(domain.clone());
        }
        endpoint = endpoint
            .tls_config(native)
            .map_err(|e| invalid(e.to_string()))?;
    }
    Ok(Target { endpoint, tls })
}

/// Longest pause between connection attempts.
const MAX_BACKOFF: Duration = Duration::from_secs(5);

/// The pause after `backoff`: doubled, at most [`MAX_BACKOFF`].
pub(crate) fn next_backoff(backoff: Duration) -> Duration {
    (backoff * 2).min(MAX_BACKOFF)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rejects_unknown_schemes_and_bad_urls() {
        let err = build_endpoint(&ClientConfig::new("ftp://127.0.0.1:1")).unwrap_err();
        assert!(err.to_string().contains("unsupported scheme"), "{err}");
        assert!(build_endpoint(&ClientConfig::new("not a url")).is_err());
        assert!(build_endpoint(&ClientConfig::new("http://127.0.0.1:50051")).is_ok());
    }

    #[test]
    fn token_with_newline_is_refused() {
        assert!(matches!(
            CallMetadata::new(Some("a\nb")),
            Err(ClientError::InvalidToken)
        ));
        assert!(CallMetadata::new(Some("secret"))
            .unwrap()
            .authorization
            .is_some());
        assert!(CallMetadata::new(None).unwrap().authorization.is_none());
        let key = new_affinity_key();
        assert_eq!(key.len(), 32);
        assert!(key.chars().all(|c| c.is_ascii_hexdigit()));
        assert_ne!(key, new_affinity_key());
    }

    #[test]
    fn backoff_doubles_up_to_its_cap() {
        let mut b = Duration::from_millis(200);
        let mut pauses = Vec::new();
        for _ in 0..7 {
            pauses.push(b);
            b = next_backoff(b);
        }
        let ms: Vec<u128> = pauses.iter().map(Duration::as_millis).collect();
        assert_eq!(ms, [200, 400, 800, 1600, 3200, 5000, 5000]);
    }
}

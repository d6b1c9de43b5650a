//! TLS for blapose's clients (`blapose-client --tls-ca`, the library's
//! `TlsOptions`, and `blapose-server --health-check`), made to work with the
//! certificates people actually make, and to say what is wrong when a
//! client and a port disagree about TLS.
//!
//! * **Self-signed certificates marked CA:TRUE.** `openssl req -x509 ...`
//!   marks its certificate `basicConstraints=CA:TRUE` unless told
//!   otherwise. webpki (behind rustls and tonic) then refuses it as the
//!   server's own certificate (`CaUsedAsEndEntity`), while grpcio and
//!   browsers-with-an-exception accept it when it is the very certificate
//!   the user trusted. [`client_config`] does what grpcio does: the normal
//!   path first; when that fails with exactly `CaUsedAsEndEntity` and the
//!   server's certificate is byte for byte one of the trusted PEM's
//!   certificates, it is accepted, still checked for the server name (its
//!   SAN) and for its validity period (webpki checks the dates before the
//!   CA flag, so a certificate that reached that error is within them), and
//!   the handshake signature still proves the server holds its key. Nothing
//!   else is relaxed: another certificate signed by that one, an expired
//!   one or one for another name fails as before.
//! * **The wrong protocol.** A plaintext client on a TLS port sees "frame
//!   with invalid size"; a TLS client on a plaintext port sees a bare
//!   handshake error. After such a failure [`probe`] asks the port what it
//!   speaks (an HTTP/2 preface, then a look at the first bytes back), so
//!   the caller can say "the server speaks TLS: pass --tls-ca" or "the
//!   server speaks plaintext HTTP/2".
//!
//! * **An untrusted certificate.** [`untrusted`] finds why a certificate
//!   was refused in a connection error and [`Untrusted::advice`] says it in
//!   words, with the flag that fixes it (not webpki's `CaUsedAsEndEntity`).
//!
//! [`TlsConnector`] is the tonic connector that applies [`client_config`]:
//! TCP, the TLS handshake with ALPN `h2`, and the diagnosis on failure.

mod trust;

pub use trust::{untrusted, Untrusted};

use std::future::Future;
use std::io;
use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::Duration;

use hyper_util::rt::TokioIo;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;
use tokio_rustls::rustls;
use tonic::codegen::http::Uri;

use rustls::client::danger::{HandshakeSignatureValid, ServerCertVerified, ServerCertVerifier};
use rustls::client::WebPkiServerVerifier;
use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, ServerName, UnixTime};
use rustls::{CertificateError, DigitallySignedStruct, SignatureScheme};

/// Why a TLS setting cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum TlsError {
    /// The CA file holds no PEM certificate.
    #[error("the CA file holds no PEM certificate")]
    NoCertificate,
    /// The CA file is not PEM.
    #[error("cannot read the CA certificates (PEM): {0}")]
    Pem(String),
    /// rustls refused the configuration.
    #[error("TLS configuration: {0}")]
    Config(String),
    /// The name to verify is not a DNS name or an IP address.
    #[error("{0:?} is not a valid TLS server name")]
    ServerName(String),
}

/// A rustls client configuration that trusts the certificates in
/// `ca_pem` as roots and pins them as server certificates (see the crate
/// documentation), offering HTTP/2 by ALPN.
pub fn client_config(ca_pem: &[u8]) -> Result<rustls::ClientConfig, TlsError> {
    let certs = CertificateDer::pem_slice_iter(ca_pem)
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| TlsError::Pem(e.to_string()))?;
    if certs.is_empty() {
        return Err(TlsError::NoCertificate);
    }
    let mut roots = rustls::RootCertStore::empty();
    let (added, _ignored) = roots.add_parsable_certificates(certs.iter().cloned());
    if added == 0 {
        return Err(TlsError::Pem(
            "no certificate in the CA file could be parsed".into(),
        ));
    }
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let inner = WebPkiServerVerifier::builder_with_provider(Arc::new(roots), provider.clone())
        .build()
        .map_err(|e| TlsError::Config(e.to_string()))?;
    let verifier = PinningVerifier {
        inner,
        pinned: certs,
    };
    let mut config = rustls::ClientConfig::builder_with_provider(provider)
        .with_safe_default_protocol_versions()
        .map_err(|e| TlsError::Config(e.to_string()))?
        .dangerous()
        .with_custom_certificate_verifier(Arc::new(verifier))
        .with_no_client_auth();
    config.alpn_protocols = vec![b"h2".to_vec()];
    Ok(config)
}

/// webpki's verification, and a pinned self-signed certificate accepted
/// where webpki refuses it only for being a CA.
#[derive(Debug)]
struct PinningVerifier {
    inner: Arc<WebPkiServerVerifier>,
    pinned: Vec<CertificateDer<'static>>,
}

fn ca_used_as_end_entity(error: &rustls::Error) -> bool {
    match error {
        rustls::Error::InvalidCertificate(CertificateError::Other(other)) => matches!(
            other.0.downcast_ref::<webpki::Error>(),
            Some(webpki::Error::CaUsedAsEndEntity)
        ),
        _ => false,
    }
}

impl ServerCertVerifier for PinningVerifier {
    fn verify_server_cert(
        &self,
        end_entity: &CertificateDer<'_>,
        intermediates: &[CertificateDer<'_>],
        server_name: &ServerName<'_>,
        ocsp_response: &[u8],
        now: UnixTime,
    ) -> Result<ServerCertVerified, rustls::Error> {
        match self.inner.verify_server_cert(
            end_entity,
            intermediates,
            server_name,
            ocsp_response,
            now,
        ) {
            Err(e)
                if ca_used_as_end_entity(&e)
                    && self
                        .pinned
                        .iter()
                        .any(|p| p.as_ref() == end_entity.as_ref()) =>
            {
                let cert = rustls::server::ParsedCertificate::try_from(end_entity)?;
                rustls::client::verify_server_name(&cert, server_name)?;
                Ok(ServerCertVerified::assertion())
            }
            other => other,
        }
    }

    fn verify_tls12_signature(
        &self,
        message: &[u8],
        cert: &CertificateDer<'_>,
        dss: &DigitallySignedStruct,
    ) -> Result<HandshakeSignatureValid, rustls::Error> {
        self.inner.verify_tls12_signature(message, cert, dss)
    }

    fn verify_tls13_signature(
        &self,
        message: &[u8],
        cert: &CertificateDer<'_>,
        dss: &DigitallySignedStruct,
    ) -> Result<HandshakeSignatureValid, rustls::Error> {
        self.inner.verify_tls13_signature(message, cert, dss)
    }

    fn supported_verify_schemes(&self) -> Vec<SignatureScheme> {
        self.inner.supported_verify_schemes()
    }
}

/// What a port answered to an HTTP/2 preface.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Speaks {
    /// A TLS record (an alert), or blapose-server's "speaks TLS" GOAWAY.
    Tls,
    /// An HTTP/2 SETTINGS frame: plaintext HTTP/2.
    PlaintextHttp2,
    /// Nothing recognizable (closed, silent, another protocol).
    Unknown,
}

/// Ask `host:port` what it speaks: connect, send the HTTP/2 client preface
/// and an empty SETTINGS frame, and look at what comes back (at most about
/// two seconds). For error messages only: it opens a connection of its own.
pub async fn probe(host: &str, port: u16) -> Speaks {
    let answer = tokio::time::timeout(Duration::from_secs(2), async {
        let mut s = TcpStream::connect((host, port)).await.ok()?;
        let mut hello = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n".to_vec();
        hello.extend_from_slice(&[0, 0, 0, 0x4, 0, 0, 0, 0, 0]);
        s.write_all(&hello).await.ok()?;
        let mut got = Vec::new();
        let mut buf = [0u8; 512];
        loop {
            // Once something arrived, wait only briefly for the rest (a
            // plaintext server keeps the connection open).
            let wait = if got.is_empty() { 1500 } else { 200 };
            match tokio::time::timeout(Duration::from_millis(wait), s.read(&mut buf)).await {
                Ok(Ok(n)) if n > 0 && got.len() < 4096 => got.extend_from_slice(&buf[..n]),
                _ => return Some(got),
            }
        }
    })
    .await;
    classify(&answer.ok().flatten().unwrap_or_default())
}

fn classify(answer: &[u8]) -> Speaks {
    let says_tls = answer.windows(10).any(|w| w == b"speaks TLS");
    match answer {
        _ if says_tls => Speaks::Tls,
        [0x15 | 0x16, 0x03, ..] => Speaks::Tls,
        [_, _, _, 0x4, ..] => Speaks::PlaintextHttp2,
        _ => Speaks::Unknown,
    }
}

/// The tonic connector for TLS with [`client_config`]: give it to
/// `Endpoint::connect_with_connector` on an `http://` endpoint (tonic must
/// not add TLS of its own). A failed handshake is probed: an error then
/// says when the server speaks plaintext HTTP/2.
#[derive(Clone)]
pub struct TlsConnector {
    config: Arc<rustls::ClientConfig>,
    domain: Option<String>,
}

impl std::fmt::Debug for TlsConnector {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TlsConnector")
            .field("domain", &self.domain)
            .finish()
    }
}

impl TlsConnector {
    /// Trust (and pin) the certificates in `ca_pem`; verify the name
    /// `domain`, or else the URI's host.
    pub fn new(ca_pem: &[u8], domain: Option<String>) -> Result<Self, TlsError> {
        if let Some(d) = &domain {
            ServerName::try_from(d.clone()).map_err(|_| TlsError::ServerName(d.clone()))?;
        }
        Ok(Self {
            config: Arc::new(client_config(ca_pem)?),
            domain,
        })
    }
}

/// `uri` with the `http` scheme (what an endpoint for [`TlsConnector`]
/// must have); other URIs are returned unchanged.
pub fn plain_scheme(uri: &str) -> String {
    match uri.get(..8) {
        Some(scheme) if scheme.eq_ignore_ascii_case("https://") => format!("http://{}", &uri[8..]),
        _ => uri.to_string(),
    }
}

type Connecting = Pin<Box<dyn Future<Output = io::Result<TokioIo<Tls>>> + Send>>;
type Tls = tokio_rustls::client::TlsStream<TcpStream>;

impl tonic::codegen::Service<Uri> for TlsConnector {
    type Response = TokioIo<Tls>;
    type Error = io::Error;
    type Future = Connecting;

    fn poll_ready(&mut self, _: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
        Poll::Ready(Ok(()))
    }

    fn call(&mut self, uri: Uri) -> Self::Future {
        let config = self.config.clone();
        let domain = self.domain.clone();
        Box::pin(async move {
            let host = uri
                .host()
                .ok_or_else(|| io::Error::other(format!("{uri}: no host")))?
                .trim_start_matches('[')
                .trim_end_matches(']')
                .to_string();
            let port = uri.port_u16().unwrap_or(443);
            let name = domain.unwrap_or_else(|| host.clone());
            let server_name = ServerName::try_from(name.clone())
                .map_err(|_| io::Error::other(TlsError::ServerName(name)))?;
            let tcp = TcpStream::connect((host.as_str(), port)).await?;
            tcp.set_nodelay(true)?;
            let connector = tokio_rustls::TlsConnector::from(config);
            let tls = match connector.connect(server_name, tcp).await {
                Ok(tls) => tls,
                Err(e) => {
                    if probe(&host, port).await == Speaks::PlaintextHttp2 {
                        return Err(io::Error::other(format!(
                            "the server at {host}:{port} speaks plaintext HTTP/2, not TLS: use \
                             http:// and no --tls-ca (the TLS handshake failed: {e})"
                        )));
                    }
                    return Err(e);
                }
            };
            if tls.get_ref().1.alpn_protocol() != Some(b"h2") {
                return Err(io::Error::other(format!(
                    "the server at {host}:{port} did not agree to HTTP/2 over TLS (ALPN h2)"
                )));
            }
            Ok(TokioIo::new(tls))
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn answers_are_classified() {
        assert_eq!(classify(&[0x15, 0x03, 0x03, 0, 2]), Speaks::Tls);
        assert_eq!(
            classify(&[0, 0, 0, 0x4, 0, 0, 0, 0, 0]),
            Speaks::PlaintextHttp2
        );
        let mut goaway = vec![0, 0, 0, 0x4, 0, 0, 0, 0, 0, 0, 0, 20, 0x7];
        goaway.extend_from_slice(b"....this server speaks TLS");
        assert_eq!(classify(&goaway), Speaks::Tls);
        assert_eq!(classify(b""), Speaks::Unknown);
        assert_eq!(classify(b"HTTP/1.1 400"), Speaks::Unknown);
    }

    #[test]
    fn schemes_become_plain_and_bad_inputs_are_refused() {
        assert_eq!(plain_scheme("https://a:1"), "http://a:1");
        assert_eq!(plain_scheme("HTTPS://a:1"), "http://a:1");
        assert_eq!(plain_scheme("http://a:1"), "http://a:1");
        assert!(matches!(
            client_config(b"not pem"),
            Err(TlsError::NoCertificate)
        ));
        assert!(TlsConnector::new(b"", None).is_err());
    }
}

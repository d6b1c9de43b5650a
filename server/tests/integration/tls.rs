//! TLS as people set it up: a self-signed certificate from `openssl req
//! -x509` (CA:TRUE) served with `--tls-cert`, checked by `--health-check`
//! (`probe_health`, what the container's HEALTHCHECK runs) trusting that
//! same file; and clear errors when the health check and the port disagree
//! about TLS. The client library's side is in `client/tests/integration/tls.rs`.

use blapose_test_support::certs;

use std::time::Duration;

use blapose_server::{probe_health, HealthCheckTls};
use tokio::io::AsyncReadExt;

fn trusting(cert: &certs::SelfSigned, domain: &str) -> HealthCheckTls {
    HealthCheckTls {
        ca: cert.cert.clone(),
        domain: domain.into(),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn health_check_trusts_a_self_signed_ca_true_certificate() {
    let Some(cert) = certs::self_signed() else {
        return;
    };
    let server = certs::serve(Some(&cert)).await;
    let addr = server.local_addr();
    assert!(probe_health(addr, Some(&trusting(&cert, "localhost")))
        .await
        .expect("the pinned certificate is accepted"));
    // Still verified: another name than the certificate's, or another
    // self-signed certificate, is refused.
    let err = probe_health(addr, Some(&trusting(&cert, "pose.example.com")))
        .await
        .unwrap_err();
    let chain = format!("{:#}", anyhow::Error::from(err));
    assert!(chain.contains("not valid for name"), "{chain}");
    let other = certs::self_signed().unwrap();
    assert!(probe_health(addr, Some(&trusting(&other, "localhost")))
        .await
        .is_err());
    // Plaintext against the TLS port: said plainly.
    let err = probe_health(addr, None).await.unwrap_err().to_string();
    assert!(err.contains("the server speaks TLS"), "{err}");
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tls_health_check_against_a_plaintext_server_says_so() {
    let Some(cert) = certs::self_signed() else {
        return;
    };
    let server = certs::serve(None).await;
    let err = probe_health(server.local_addr(), Some(&trusting(&cert, "localhost")))
        .await
        .unwrap_err();
    let text = format!("{:#}", anyhow::Error::from(err));
    assert!(text.contains("speaks plaintext HTTP/2"), "{text}");
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_silent_connection_to_the_tls_port_is_closed_after_the_handshake_timeout() {
    let Some(cert) = certs::self_signed() else {
        return;
    };
    let server = certs::serve(Some(&cert)).await;
    let mut silent = tokio::net::TcpStream::connect(server.local_addr())
        .await
        .unwrap();
    let mut buf = [0u8; 16];
    let read = tokio::time::timeout(Duration::from_secs(3), silent.read(&mut buf)).await;
    assert!(
        matches!(read, Ok(Ok(0) | Err(_))),
        "closed within the deadline: {read:?}"
    );
    server.shutdown().await.unwrap();
}

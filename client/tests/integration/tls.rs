//! The client library over TLS as people set it up: a self-signed
//! certificate from `openssl req -x509` (CA:TRUE) given as the CA
//! (`blapose-client --tls-ca`), and clear errors when the client and the
//! server disagree about TLS.

use blapose_test_support::certs;

use std::time::Duration;

use blapose_client::{Client, ClientConfig};

fn config(url: String, ca: Option<&certs::SelfSigned>) -> ClientConfig {
    let mut config = ClientConfig::new(url);
    config.connect_attempts = 1;
    config.connect_timeout = Duration::from_secs(3);
    config.request_timeout = Duration::from_secs(3);
    config.tls.ca_cert_pem = ca.map(|c| std::fs::read(&c.cert).unwrap());
    config
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_self_signed_ca_true_certificate_works_as_the_ca() {
    let Some(cert) = certs::self_signed() else {
        return;
    };
    let server = certs::serve(Some(&cert)).await;
    let port = server.local_addr().port();
    for url in [
        format!("https://localhost:{port}"),
        format!("https://127.0.0.1:{port}"),
    ] {
        let client = Client::connect(config(url.clone(), Some(&cert)))
            .await
            .unwrap_or_else(|e| panic!("{url}: {e}"));
        client
            .model_info()
            .await
            .unwrap_or_else(|e| panic!("{url}: {e}"));
    }
    // Another certificate as the CA: refused.
    let other = certs::self_signed().unwrap();
    let refused = async {
        Client::connect(config(format!("https://localhost:{port}"), Some(&other)))
            .await?
            .model_info()
            .await
    };
    assert!(refused.await.is_err());
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_plaintext_client_on_the_tls_port_is_told_the_server_speaks_tls() {
    let Some(cert) = certs::self_signed() else {
        return;
    };
    let server = certs::serve(Some(&cert)).await;
    let url = format!("http://127.0.0.1:{}", server.local_addr().port());
    let outcome = async { Client::connect(config(url, None)).await?.model_info().await };
    let err = outcome.await.unwrap_err().to_string();
    assert!(err.contains("speaks TLS"), "{err}");
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_tls_client_on_a_plaintext_port_is_told_the_server_speaks_plaintext() {
    let Some(cert) = certs::self_signed() else {
        return;
    };
    let server = certs::serve(None).await;
    let url = format!("https://127.0.0.1:{}", server.local_addr().port());
    let outcome = async {
        Client::connect(config(url, Some(&cert)))
            .await?
            .model_info()
            .await
    };
    let err = outcome.await.unwrap_err().to_string();
    assert!(err.contains("speaks plaintext HTTP/2"), "{err}");
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_untrusted_self_signed_certificate_is_named_with_the_flag_that_fixes_it() {
    let Some(cert) = certs::self_signed() else {
        return;
    };
    let server = certs::serve(Some(&cert)).await;
    let port = server.local_addr().port();
    // https:// without --tls-ca: the system's roots do not trust it.
    let mut untrusting = config(format!("https://localhost:{port}"), None);
    untrusting.connect_attempts = 3;
    let err = Client::connect(untrusting).await.unwrap_err().to_string();
    assert!(
        err.contains("self-signed") && err.contains("--tls-ca"),
        "{err}"
    );
    assert!(
        err.contains("after 1 attempt"),
        "no retry of a certificate: {err}"
    );
    assert!(!err.starts_with("CaUsedAsEndEntity"), "{err}");
    // Another certificate given as the CA.
    let other = certs::self_signed().unwrap();
    let err = Client::connect(config(format!("https://localhost:{port}"), Some(&other)))
        .await
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("not the certificate given with --tls-ca"),
        "{err}"
    );
    server.shutdown().await.unwrap();
}

//! Security: the bearer-token check and TLS, end to end through the client.

use blapose_client::{Client, ClientConfig, KeypointLayout, TlsOptions};
use blapose_server::{HealthCheckTls, ServerConfig, TlsFiles};
use blapose_tests::{synthetic_sequence, test_config, TestServer};
use tonic::Code;

#[tokio::test]
async fn bearer_token_is_required_when_configured() {
    let config = blapose_server::ServerConfig {
        auth_token: Some("s3cret-token".into()),
        ..test_config()
    };
    let server = TestServer::start(config).await;
    let format = synthetic_sequence(38, 1, KeypointLayout::H36m17).input_format;

    let anonymous = server.client().await;
    assert_eq!(
        anonymous.model_info().await.expect_err("no token").code(),
        Some(Code::Unauthenticated)
    );
    assert_eq!(
        anonymous
            .open_session(format, None)
            .await
            .expect_err("no token")
            .code(),
        Some(Code::Unauthenticated)
    );
    let wrong = anonymous.with_token(Some("s3cret-tokeN")).expect("token");
    assert_eq!(
        wrong.model_info().await.expect_err("wrong token").code(),
        Some(Code::Unauthenticated)
    );
    assert_eq!(
        wrong
            .close_session("x")
            .await
            .expect_err("wrong token")
            .code(),
        Some(Code::Unauthenticated)
    );

    let right = anonymous.with_token(Some("s3cret-token")).expect("token");
    right.model_info().await.expect("right token");
    let session = right
        .open_session(format, None)
        .await
        .expect("right token opens");
    session.close().await.expect("close");

    // Health stays reachable without a token (probes have none).
    let health = tonic_health::pb::health_client::HealthClient::new(anonymous.channel())
        .check(tonic_health::pb::HealthCheckRequest {
            service: String::new(),
        })
        .await;
    assert!(health.is_ok(), "{health:?}");
    server.shutdown().await;
}

#[tokio::test]
async fn tls_with_a_private_ca() {
    let certified =
        rcgen::generate_simple_self_signed(vec!["localhost".to_string()]).expect("certificate");
    let cert_pem = certified.cert.pem();
    let dir = std::env::temp_dir().join(format!("blapose-tests-tls-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("temp dir");
    let (cert, key) = (dir.join("cert.pem"), dir.join("key.pem"));
    std::fs::write(&cert, &cert_pem).expect("write cert");
    std::fs::write(&key, certified.signing_key.serialize_pem()).expect("write key");

    let config = ServerConfig {
        tls: Some(TlsFiles { cert, key }),
        ..test_config()
    };
    let server = TestServer::start(config).await;
    let port = server.addr.port();

    // Trusting the server's certificate, verified against "localhost".
    let mut config = ClientConfig::new(format!("https://127.0.0.1:{port}"));
    config.tls = TlsOptions {
        ca_cert_pem: Some(cert_pem.into_bytes()),
        domain: Some("localhost".into()),
    };
    let client = Client::connect(config.clone()).await.expect("TLS connect");
    let seq = synthetic_sequence(51, 3, KeypointLayout::H36m17);
    let mut session = client
        .open_session(seq.input_format, None)
        .await
        .expect("open over TLS");
    let answer = session.adjust(&seq.frame(0)).await.expect("frame over TLS");
    assert_eq!(answer.frames_seen, 1);
    session.close().await.expect("close");

    // The wrong name, or no trust in the certificate, fails.
    let mut wrong_name = config.clone();
    wrong_name.tls.domain = Some("example.invalid".into());
    wrong_name.connect_attempts = 1;
    assert!(
        is_refused(wrong_name).await,
        "a certificate for another name was accepted"
    );
    let mut untrusted = ClientConfig::new(format!("https://localhost:{port}"));
    untrusted.connect_attempts = 1;
    assert!(
        is_refused(untrusted).await,
        "an untrusted certificate was accepted"
    );
    // Plain HTTP/2 to a TLS port does not work either.
    let mut plain = ClientConfig::new(format!("http://127.0.0.1:{port}"));
    plain.connect_attempts = 1;
    assert!(is_refused(plain).await, "plaintext reached a TLS server");
    server.shutdown().await;
    std::fs::remove_dir_all(&dir).ok();
}

/// `blapose-server --health-check` reaches a TLS server over TLS, as
/// [`blapose_server::Cli::health_check_tls`] configures it from the flags
/// that started the server: trusting the server's own certificate for
/// `localhost` by default, or `--tls-ca` for `--tls-domain` (a private CA's
/// certificate for another name).
#[tokio::test]
async fn health_check_reaches_a_tls_server() {
    let dir = std::env::temp_dir().join(format!("blapose-tests-health-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("temp dir");
    let path = |name: &str| dir.join(name);
    let check = |addr, ca: &str, domain: &str| {
        let tls = HealthCheckTls {
            ca: path(ca),
            domain: domain.to_string(),
        };
        async move {
            blapose_server::probe_health(addr, Some(&tls))
                .await
                .map_err(|e| e.to_string())
        }
    };

    // 1. A self-signed certificate for localhost: the defaults (trust the
    // certificate file, check "localhost") work.
    let certified =
        rcgen::generate_simple_self_signed(vec!["localhost".to_string()]).expect("certificate");
    std::fs::write(path("self.pem"), certified.cert.pem()).expect("write cert");
    std::fs::write(path("self.key"), certified.signing_key.serialize_pem()).expect("write key");
    let server = TestServer::start(ServerConfig {
        tls: Some(TlsFiles {
            cert: path("self.pem"),
            key: path("self.key"),
        }),
        ..test_config()
    })
    .await;
    assert_eq!(check(server.addr, "self.pem", "localhost").await, Ok(true));
    // What failed before: a plaintext check of a TLS server.
    assert!(blapose_server::probe_health(server.addr, None)
        .await
        .is_err());
    server.shutdown().await;

    // 2. A private CA's certificate for another name, the file holding the
    // server's certificate only.
    let ca_key = rcgen::KeyPair::generate().expect("CA key");
    let mut ca_params = rcgen::CertificateParams::new(Vec::<String>::new()).expect("CA params");
    ca_params.is_ca = rcgen::IsCa::Ca(rcgen::BasicConstraints::Unconstrained);
    let ca = rcgen::CertifiedIssuer::self_signed(ca_params, ca_key).expect("CA");
    let leaf_key = rcgen::KeyPair::generate().expect("key");
    let leaf = rcgen::CertificateParams::new(vec!["pose.example.test".to_string()])
        .expect("params")
        .signed_by(&leaf_key, &ca)
        .expect("certificate");
    std::fs::write(path("ca.pem"), ca.pem()).expect("write CA");
    std::fs::write(path("leaf.pem"), leaf.pem()).expect("write cert");
    std::fs::write(path("leaf.key"), leaf_key.serialize_pem()).expect("write key");
    let server = TestServer::start(ServerConfig {
        tls: Some(TlsFiles {
            cert: path("leaf.pem"),
            key: path("leaf.key"),
        }),
        ..test_config()
    })
    .await;
    // Without the CA, or for the wrong name, the certificate is refused.
    assert!(check(server.addr, "leaf.pem", "localhost").await.is_err());
    assert!(check(server.addr, "ca.pem", "localhost").await.is_err());
    assert!(check(server.addr, "leaf.pem", "pose.example.test")
        .await
        .is_err());
    assert_eq!(
        check(server.addr, "ca.pem", "pose.example.test").await,
        Ok(true)
    );
    server.shutdown().await;
    std::fs::remove_dir_all(&dir).ok();
}

/// True when a client with `config` cannot use the server (the failure may
/// show at connect time or at the first call).
async fn is_refused(mut config: ClientConfig) -> bool {
    config.request_timeout = std::time::Duration::from_secs(5);
    match Client::connect(config).await {
        Err(_) => true,
        Ok(client) => client.model_info().await.is_err(),
    }
}

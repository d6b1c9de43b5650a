//! Self-signed certificates made the way people make them:
//! `openssl req -x509 -newkey rsa:2048 -nodes -days 1 -subj /CN=localhost
//! -addext "subjectAltName=DNS:localhost,IP:127.0.0.1"`, which marks the
//! certificate CA:TRUE. Made at run time into a temporary directory; without
//! openssl the test is skipped with a message, except under `CI=true`,
//! where that is a failure.

use std::path::PathBuf;
use std::process::Command;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::Duration;

use crate::model::ConstantModel;
use blapose_server::transport::ConnectionLimits;
use blapose_server::{ServerConfig, ServerHandle, TlsFiles};

/// A certificate and its key in a directory removed on drop.
#[derive(Debug)]
pub struct SelfSigned {
    pub dir: PathBuf,
    pub cert: PathBuf,
    pub key: PathBuf,
}

impl Drop for SelfSigned {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

static MADE: AtomicUsize = AtomicUsize::new(0);

/// A fresh self-signed certificate for localhost and 127.0.0.1, or `None`
/// (with a message) when openssl is missing outside CI.
pub fn self_signed() -> Option<SelfSigned> {
    if Command::new("openssl").arg("version").output().is_err() {
        assert!(
            std::env::var("CI").as_deref() != Ok("true"),
            "openssl is needed for the TLS tests (CI=true)"
        );
        eprintln!("skipping: openssl not found");
        return None;
    }
    let dir = std::env::temp_dir().join(format!(
        "blapose-tls-test-{}-{}",
        std::process::id(),
        MADE.fetch_add(1, Ordering::Relaxed)
    ));
    std::fs::create_dir_all(&dir).unwrap();
    let (cert, key) = (dir.join("cert.pem"), dir.join("key.pem"));
    let made = Command::new("openssl")
        .args([
            "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "1",
        ])
        .args(["-subj", "/CN=localhost"])
        .args(["-addext", "subjectAltName=DNS:localhost,IP:127.0.0.1"])
        .arg("-keyout")
        .arg(&key)
        .arg("-out")
        .arg(&cert)
        .output()
        .expect("run openssl");
    assert!(
        made.status.success(),
        "openssl req failed: {}",
        String::from_utf8_lossy(&made.stderr)
    );
    let text = Command::new("openssl")
        .args(["x509", "-noout", "-text", "-in"])
        .arg(&cert)
        .output()
        .expect("run openssl x509");
    assert!(
        String::from_utf8_lossy(&text.stdout).contains("CA:TRUE"),
        "the certificate the tests are about is marked CA:TRUE"
    );
    Some(SelfSigned { dir, cert, key })
}

/// A server with a constant model on a loopback port: TLS with `tls`'s
/// certificate, or plaintext; a 500 ms handshake deadline.
pub async fn serve(tls: Option<&SelfSigned>) -> ServerHandle {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let config = ServerConfig {
        tls: tls.map(|c| TlsFiles {
            cert: c.cert.clone(),
            key: c.key.clone(),
        }),
        connection_limits: ConnectionLimits {
            handshake_timeout: Duration::from_millis(500),
            ..ServerConfig::default().connection_limits
        },
        ..ServerConfig::default()
    };
    blapose_server::spawn_with_provider(config, listener, Arc::new(ConstantModel))
        .await
        .unwrap()
}

//! Why a server's certificate was not trusted, in words a user can act on.
//!
//! rustls reports a refused certificate as a webpki error name at the end
//! of a transport error's chain: a self-signed certificate made with
//! `openssl req -x509` fails with `CaUsedAsEndEntity`, one without the CA
//! flag with `UnknownIssuer`, which say nothing about what to do. The
//! commonest cause by far is a self-signed (or private-CA) certificate the
//! client was not given, and the fix is one flag. [`untrusted`] finds the
//! rustls error in a chain (tonic wraps it in an `io::Error`, whose
//! `source()` skips it, so each `io::Error` is opened too) and
//! [`Untrusted::advice`] says what is wrong and which flag fixes it.

use std::error::Error;

use tokio_rustls::rustls::{self, CertificateError};

/// Why the server's certificate was refused.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Untrusted {
    /// Self-signed and marked as a CA (`openssl req -x509`), not pinned.
    SelfSigned,
    /// Not signed by a trusted CA (a self-signed one without the CA flag,
    /// or a private CA).
    UnknownIssuer,
    /// Valid, but not for the name connected to.
    WrongName,
    /// Expired, or not yet valid (or the clocks differ).
    Expired,
}

/// The certificate problem in `error`'s chain, if any.
pub fn untrusted(error: &(dyn Error + 'static)) -> Option<Untrusted> {
    // The chain with each io::Error's payload as a second way down (its
    // `source()` is the payload's source, not the payload); bounded.
    let mut pending = vec![error];
    let mut seen = 0;
    while let Some(e) = pending.pop() {
        seen += 1;
        if seen > 64 {
            break;
        }
        if let Some(found) = e.downcast_ref::<rustls::Error>().and_then(classify) {
            return Some(found);
        }
        pending.extend(e.source());
        if let Some(payload) = e
            .downcast_ref::<std::io::Error>()
            .and_then(|io| io.get_ref())
        {
            pending.push(payload as &(dyn Error + 'static));
        }
    }
    None
}

fn classify(error: &rustls::Error) -> Option<Untrusted> {
    let rustls::Error::InvalidCertificate(cert) = error else {
        return None;
    };
    match cert {
        CertificateError::Other(other)
            if matches!(
                other.0.downcast_ref::<webpki::Error>(),
                Some(webpki::Error::CaUsedAsEndEntity)
            ) =>
        {
            Some(Untrusted::SelfSigned)
        }
        CertificateError::UnknownIssuer => Some(Untrusted::UnknownIssuer),
        CertificateError::NotValidForName | CertificateError::NotValidForNameContext { .. } => {
            Some(Untrusted::WrongName)
        }
        CertificateError::Expired
        | CertificateError::ExpiredContext { .. }
        | CertificateError::NotValidYet
        | CertificateError::NotValidYetContext { .. } => Some(Untrusted::Expired),
        _ => None,
    }
}

impl Untrusted {
    /// What is wrong and what to do; `ca_given`: the client was given a
    /// certificate to trust (`--tls-ca`).
    pub fn advice(self, ca_given: bool) -> String {
        match (self, ca_given) {
            (Untrusted::SelfSigned, false) => "the server's certificate is self-signed, and this \
                 client does not trust it: pass that certificate (its PEM file) with --tls-ca \
                 (env BLAPOSE_TLS_CA; TlsOptions::ca_cert_pem in the library)"
                .into(),
            (Untrusted::SelfSigned, true) => "the server's certificate is self-signed and is not \
                 the certificate given with --tls-ca: pass the server's own certificate (PEM) \
                 with --tls-ca"
                .into(),
            (Untrusted::UnknownIssuer, false) => "the server's certificate is not trusted: it is \
                 self-signed or signed by a private CA; pass that certificate or its CA's (PEM) \
                 with --tls-ca (env BLAPOSE_TLS_CA; TlsOptions::ca_cert_pem in the library)"
                .into(),
            (Untrusted::UnknownIssuer, true) => "the server's certificate is not signed by the \
                 certificate given with --tls-ca: pass the server's certificate or its CA's (PEM)"
                .into(),
            (Untrusted::WrongName, _) => "the server's certificate is not valid for the host \
                 name connected to: connect by a name it lists, or name one with --tls-domain"
                .into(),
            (Untrusted::Expired, _) => "the server's certificate has expired or is not valid \
                 yet (or this machine's clock is wrong)"
                .into(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn wrapped(e: rustls::Error) -> std::io::Error {
        // As tonic hands it over: an io::Error around the rustls error,
        // inside another error.
        std::io::Error::other(std::io::Error::new(std::io::ErrorKind::InvalidData, e))
    }

    #[test]
    fn certificate_errors_are_found_in_the_chain_and_explained() {
        let ca_as_leaf = rustls::Error::InvalidCertificate(CertificateError::Other(
            rustls::OtherError(std::sync::Arc::new(webpki::Error::CaUsedAsEndEntity)),
        ));
        let e = wrapped(ca_as_leaf);
        assert_eq!(untrusted(&e), Some(Untrusted::SelfSigned));
        let advice = Untrusted::SelfSigned.advice(false);
        assert!(
            advice.contains("self-signed") && advice.contains("--tls-ca"),
            "{advice}"
        );
        assert!(!advice.contains("CaUsedAsEndEntity"));
        let e = wrapped(rustls::Error::InvalidCertificate(
            CertificateError::UnknownIssuer,
        ));
        assert_eq!(untrusted(&e), Some(Untrusted::UnknownIssuer));
        assert!(Untrusted::UnknownIssuer
            .advice(true)
            .contains("given with --tls-ca"));
        let e = wrapped(rustls::Error::InvalidCertificate(
            CertificateError::NotValidForName,
        ));
        assert_eq!(untrusted(&e), Some(Untrusted::WrongName));
        assert!(Untrusted::WrongName.advice(false).contains("--tls-domain"));
        assert_eq!(untrusted(&std::io::Error::other("refused")), None);
        assert_eq!(
            untrusted(&wrapped(rustls::Error::HandshakeNotComplete)),
            None
        );
    }
}

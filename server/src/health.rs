//! The `--health-check` probe: ask a running server's `grpc.health.v1`
//! whether it serves (the container's HEALTHCHECK runs the server binary
//! this way, so the image needs no other tool).

use std::net::SocketAddr;
use std::time::Duration;

use crate::config::HealthCheckTls;
use crate::error::ServerError;

/// Query `grpc.health.v1` at `addr` (overall status). `Ok(true)` when
/// SERVING. With `tls`, connect over TLS and verify the server's certificate
/// against `tls.ca` for the name `tls.domain` (see
/// [`crate::Cli::health_check_tls`]).
pub async fn probe_health(
    addr: SocketAddr,
    tls: Option<&HealthCheckTls>,
) -> Result<bool, ServerError> {
    use tonic_health::pb::{
        health_check_response::ServingStatus as S, health_client::HealthClient, HealthCheckRequest,
    };
    let host = if addr.ip().is_unspecified() {
        SocketAddr::new(
            if addr.is_ipv4() {
                std::net::Ipv4Addr::LOCALHOST.into()
            } else {
                std::net::Ipv6Addr::LOCALHOST.into()
            },
            addr.port(),
        )
    } else {
        addr
    };
    // TLS goes through blapose-tls's connector (a pinned self-signed
    // certificate is accepted even when marked CA:TRUE), on an http://
    // endpoint so that tonic adds no TLS of its own.
    let endpoint = tonic::transport::Endpoint::from_shared(format!("http://{host}"))
        .map_err(ServerError::from)?
        .connect_timeout(Duration::from_secs(3))
        .timeout(Duration::from_secs(3));
    let checked = async {
        let channel = match tls {
            Some(tls) => {
                let pem = std::fs::read(&tls.ca).map_err(|e| {
                    ServerError::Tls(format!("cannot read {}: {e}", tls.ca.display()))
                })?;
                let connector = blapose_tls::TlsConnector::new(&pem, Some(tls.domain.clone()))
                    .map_err(|e| ServerError::Tls(format!("{}: {e}", tls.ca.display())))?;
                endpoint.connect_with_connector(connector).await?
            }
            None => endpoint.connect().await?,
        };
        HealthClient::new(channel)
            .check(HealthCheckRequest {
                service: String::new(),
            })
            .await
            .map_err(|s| ServerError::Task(format!("health check failed: {s}")))
    }
    .await;
    match checked {
        Ok(response) => Ok(response.into_inner().status == S::Serving as i32),
        Err(e)
            if tls.is_none()
                && blapose_tls::probe(&host.ip().to_string(), host.port()).await
                    == blapose_tls::Speaks::Tls =>
        {
            Err(ServerError::Tls(format!(
                "the server speaks TLS: run --health-check with the server's TLS settings \
                 (--tls-cert / BLAPOSE_TLS_CERT, and --tls-ca, --tls-domain if its certificate \
                 needs them) ({e})"
            )))
        }
        Err(e) => Err(e),
    }
}

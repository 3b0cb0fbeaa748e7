//! Asking a running server whether it is ready to serve, through the standard gRPC health service
//! (`posefuse health`; the container's HEALTHCHECK uses it, so the image needs no HTTP client).

use std::net::{IpAddr, Ipv4Addr, Ipv6Addr, SocketAddr};
use std::time::Duration;

use posefuse_core::error::{Error, Result};
use tonic_health::pb::health_check_response::ServingStatus;
use tonic_health::pb::health_client::HealthClient;
use tonic_health::pb::HealthCheckRequest;

/// The address to connect to for a listening address (a wildcard is reached on loopback).
pub fn connect_addr(listen: SocketAddr) -> SocketAddr {
    match listen.ip() {
        IpAddr::V4(ip) if ip.is_unspecified() => SocketAddr::new(IpAddr::V4(Ipv4Addr::LOCALHOST), listen.port()),
        IpAddr::V6(ip) if ip.is_unspecified() => SocketAddr::new(IpAddr::V6(Ipv6Addr::LOCALHOST), listen.port()),
        _ => listen,
    }
}

/// The overall status ("" service) of the server at `addr` (a connectable address, see
/// [`connect_addr`]): SERVING once the bundle is loaded and warmed up, NOT_SERVING while it warms
/// up or shuts down.
pub async fn check(addr: SocketAddr, timeout: Duration) -> Result<ServingStatus> {
    let channel = tonic::transport::Endpoint::from_shared(format!("http://{addr}"))
        .map_err(|e| Error::Unavailable(format!("no endpoint for {addr}: {e}")))?
        .connect_timeout(timeout)
        .timeout(timeout)
        .connect()
        .await
        .map_err(|e| Error::Unavailable(format!("cannot connect to {addr}: {e}")))?;
    let response = HealthClient::new(channel)
        .check(HealthCheckRequest { service: String::new() })
        .await
        .map_err(|e| Error::Unavailable(format!("health check at {addr} failed: {}", e.message())))?;
    Ok(ServingStatus::try_from(response.into_inner().status).unwrap_or(ServingStatus::Unknown))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_wildcard_address_is_checked_on_loopback() {
        let at = |s: &str| connect_addr(s.parse().unwrap()).to_string();
        assert_eq!(at("0.0.0.0:8080"), "127.0.0.1:8080");
        assert_eq!(at("[::]:9000"), "[::1]:9000");
        assert_eq!(at("10.1.2.3:8080"), "10.1.2.3:8080");
    }
}

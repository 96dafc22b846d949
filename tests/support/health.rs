//! The daemon's gRPC health service as a probe asks it: one service's status, and a wait until
//! services report the status a test expects.

use std::time::Duration;

use tonic_health::pb::health_check_response::ServingStatus;
use tonic_health::pb::health_client::HealthClient;
use tonic_health::pb::HealthCheckRequest;

use crate::service::connect;

/// The name the daemon reports `JobService`'s health under.
pub const JOB_SERVICE: &str = "pointfarm.v1.JobService";

/// The health of `service` ("" for the daemon as a whole) on the daemon at `address`.
pub async fn health(address: &str, service: &str) -> i32 {
    HealthClient::new(connect(address).await)
        .check(HealthCheckRequest {
            service: service.into(),
        })
        .await
        .expect("health")
        .into_inner()
        .status
}

/// Waits up to `timeout` until every one of `services` on the daemon at `address` reports
/// `status`, failing with what they report otherwise.
pub async fn wait_for_health(
    address: &str,
    services: &[&str],
    status: ServingStatus,
    timeout: Duration,
) {
    let deadline = tokio::time::Instant::now() + timeout;
    loop {
        let mut reported = Vec::with_capacity(services.len());
        for service in services {
            reported.push(health(address, service).await);
        }
        if reported.iter().all(|&each| each == status as i32) {
            return;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "health of {services:?} is {reported:?}, not {status:?}, after {timeout:?}"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

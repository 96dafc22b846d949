//! Keeping a lease, a frame's or a video's, while its work runs: renewed well within its
//! timeout, dropped when the daemon says stop.

use std::future::Future;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

use pointfarm_proto::v1 as pb;
use tonic::{Response, Status};

/// A third of the lease timeout keeps the lease through a lost renewal; at most 5 s apart,
/// so that a cancel reaches the worker soon.
pub(crate) fn renewal_interval(lease_timeout: Duration) -> Duration {
    (lease_timeout / 3).clamp(Duration::from_millis(50), Duration::from_secs(5))
}

/// Renews the lease on `what` (a frame, a video) with `renew` every `interval` until aborted;
/// sets `abandoned` and returns when the daemon says stop.
pub(crate) async fn keep_lease<F, Fut>(
    what: &'static str,
    interval: Duration,
    abandoned: Arc<AtomicBool>,
    mut renew: F,
) where
    F: FnMut() -> Fut,
    Fut: Future<Output = Result<Response<pb::HeartbeatResponse>, Status>>,
{
    loop {
        tokio::time::sleep(interval).await;
        match renew().await {
            Ok(response) => {
                let answer = response.into_inner();
                if answer.action == pb::LeaseAction::Stop as i32 {
                    tracing::info!(reason = %answer.reason, "the daemon says to drop the {what}");
                    abandoned.store(true, Ordering::SeqCst);
                    return;
                }
            }
            Err(status) => tracing::warn!(
                code = ?status.code(),
                message = status.message(),
                "renewing the {what}'s lease failed; it runs out unless the next renewal succeeds"
            ),
        }
    }
}

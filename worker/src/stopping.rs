//! Waiting between a loop's tries so that the worker's stop cuts the wait short.

use std::time::Duration;

use tokio::sync::watch;

/// Waits `wait`, or less if `stop` changes (or its sender is gone) first: true when the
/// worker is stopping and the loop should end rather than try again.
pub(crate) async fn stopped_during(stop: &mut watch::Receiver<bool>, wait: Duration) -> bool {
    tokio::select! {
        _ = stop.changed() => true,
        _ = tokio::time::sleep(wait) => false,
    }
}

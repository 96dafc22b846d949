//! The `pointfarm.v1` gRPC services: validate and convert requests, call [`Daemon`], convert
//! results. No domain logic lives here.
//!
//! - `conversions`: messages to domain types and back (`From`/`TryFrom`); the frame-task
//!   conversions are public, for the worker's side of the wire (the `pointfarm-worker`
//!   crate), and so are those of dataset descriptions, which `pointfarm info` builds from
//!   local files too, and a job's, which the dashboard answers with.
//! - `status`: the one map from [`crate::error::DaemonError`] to status codes.
//! - `datasets`, `jobs`, `workers`: one file per service.
//! - `lease_guard`: gives back the frame of an abandoned long-polling lease request.
//! - `streaming`: the one chunk size and the helpers for every stream of bytes.

use std::sync::Arc;
use std::time::Duration;

use tonic::Status;

use crate::error::DaemonError;
use crate::service::Daemon;

mod conversions;
mod datasets;
mod encodes;
mod jobs;
mod lease_guard;
mod request;
mod status;
pub mod streaming;
mod video;
mod workers;

pub use conversions::{
    copc_chunks, copc_description, dataset_description, export_summary, file_description,
    frame_cut_message, frame_cut_of_message, frame_task, frame_task_message,
    job_with_frames_message, node_key_message, point_attributes_message, preview_sample_bounds,
    stage_timings, store_elevation, timings_message, workers_message,
};
pub use request::{camera_path_message, render_options_message, render_request};
pub use video::{video_settings, video_spec_message};
pub use workers::EmbeddedWorkerCall;

/// The three services over one daemon.
#[derive(Clone)]
pub struct Api {
    daemon: Arc<Daemon>,
}

impl Api {
    pub fn new(daemon: Arc<Daemon>) -> Self {
        Self { daemon }
    }

    /// Runs `work` as [`Api::run`] does, and answers with the empty message `R`.
    async fn done<R: Default>(
        &self,
        work: impl FnOnce(&Arc<Daemon>) -> Result<(), DaemonError> + Send + 'static,
    ) -> Result<tonic::Response<R>, Status> {
        self.run(work).await?;
        Ok(tonic::Response::new(R::default()))
    }

    /// Runs `work` as [`Api::run`] does, and answers with its result as the message `M`.
    async fn answer<T: Send + 'static, M: for<'a> From<&'a T>>(
        &self,
        work: impl FnOnce(&Arc<Daemon>) -> Result<T, DaemonError> + Send + 'static,
    ) -> Result<tonic::Response<M>, Status> {
        let value = self.run(work).await?;
        Ok(tonic::Response::new(M::from(&value)))
    }

    /// Runs `work` on the daemon off the async executor (state database work and
    /// filesystem calls block), within [`BLOCKING_CALL_BOUND`].
    async fn run<T: Send + 'static>(
        &self,
        work: impl FnOnce(&Arc<Daemon>) -> Result<T, DaemonError> + Send + 'static,
    ) -> Result<T, Status> {
        let daemon = self.daemon.clone();
        blocking_within(BLOCKING_CALL_BOUND, move || work(&daemon))
            .await?
            .map_err(|e| self.client_status(e))
    }

    /// The status a client is told for `error`, without the server's folders in its message
    /// (an error of a store build quotes its files' paths; the log has them whole).
    fn client_status(&self, error: DaemonError) -> Status {
        let status = Status::from(error);
        let message = self.daemon.without_server_folders(status.message());
        Status::new(status.code(), message)
    }

    /// Runs `work` as [`Api::run`] does, for work that takes as long as the data is large
    /// (hashing a registration's files, reading every point of a dataset, building its store
    /// for an export): its bound grows with the `bytes` it reads ([`scaled_bound`]). It reads
    /// regular files only, each opened without blocking
    /// (`pointfarm_render::ingest::open_dataset_file`).
    async fn run_scaled<T: Send + 'static>(
        &self,
        bytes: u64,
        work: impl FnOnce(&Arc<Daemon>) -> Result<T, DaemonError> + Send + 'static,
    ) -> Result<T, Status> {
        let daemon = self.daemon.clone();
        blocking_within(scaled_bound(bytes), move || work(&daemon))
            .await?
            .map_err(|e| self.client_status(e))
    }

    /// The bytes of dataset `id`'s files, from its record (NOT_FOUND for an unknown one).
    async fn dataset_bytes(&self, id: &str) -> Result<u64, Status> {
        let id = id.to_string();
        self.run(move |daemon| {
            let dataset = daemon.dataset(&id)?;
            Ok(dataset.files().iter().map(|file| file.size_bytes).sum())
        })
        .await
    }
}

/// The slowest a dataset's files are read before the daemon takes the disk for hung: a
/// tenth of a hard disk's speed, and below the slowest decoding or store build per byte.
const SLOWEST_READ_BYTES_PER_SECOND: f64 = 10.0 * 1024.0 * 1024.0;

/// The bound of work that reads `bytes` of a dataset's files: [`BLOCKING_CALL_BOUND`] and the
/// time to read them at [`SLOWEST_READ_BYTES_PER_SECOND`].
fn scaled_bound(bytes: u64) -> Duration {
    BLOCKING_CALL_BOUND + Duration::from_secs_f64(bytes as f64 / SLOWEST_READ_BYTES_PER_SECOND)
}

/// How long a request waits for its blocking work (a state transaction, a folder's walk, a
/// file's open): each takes milliseconds on a working disk, so a minute means a hung one (a
/// network filesystem gone away), and the client is answered rather than held forever.
pub const BLOCKING_CALL_BOUND: Duration = Duration::from_secs(60);

/// `io`, an asynchronous filesystem call (tokio runs it on a blocking thread), within
/// [`BLOCKING_CALL_BOUND`]: past it an error of kind `TimedOut`, the thread left behind.
pub(crate) async fn io_within<T>(
    io: impl std::future::Future<Output = std::io::Result<T>>,
) -> std::io::Result<T> {
    tokio::time::timeout(BLOCKING_CALL_BOUND, io)
        .await
        .unwrap_or_else(|_| {
            Err(std::io::Error::new(
                std::io::ErrorKind::TimedOut,
                format!(
                    "the daemon's disk did not answer within {} s",
                    BLOCKING_CALL_BOUND.as_secs_f64()
                ),
            ))
        })
}

/// Runs `work` on tokio's blocking threads; DEADLINE_EXCEEDED when it has not finished
/// within `bound`, its thread left behind to finish (or stay stuck) on its own.
pub(crate) async fn blocking_within<T: Send + 'static>(
    bound: Duration,
    work: impl FnOnce() -> T + Send + 'static,
) -> Result<T, Status> {
    match tokio::time::timeout(bound, tokio::task::spawn_blocking(work)).await {
        Ok(done) => done.map_err(|e| Status::internal(e.to_string())),
        Err(_) => {
            tracing::error!(
                bound_s = bound.as_secs_f64(),
                "a request's blocking work has not finished in time: the disk or filesystem \
                 under the daemon's data or data roots may hang"
            );
            Err(Status::deadline_exceeded(format!(
                "the daemon's disk did not answer within {} s; the call may still take \
                 effect",
                bound.as_secs_f64()
            )))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn blocking_work_past_its_bound_is_answered_deadline_exceeded() {
        let (release, stuck) = std::sync::mpsc::channel::<()>();
        let started = std::time::Instant::now();
        let status = blocking_within(Duration::from_millis(50), move || {
            let _ = stuck.recv_timeout(Duration::from_secs(30));
        })
        .await
        .expect_err("past its bound");
        assert_eq!(status.code(), tonic::Code::DeadlineExceeded);
        assert!(started.elapsed() < Duration::from_secs(10));
        let _ = release.send(());
        let done = blocking_within(Duration::from_secs(10), || 7)
            .await
            .expect("in time");
        assert_eq!(done, 7);
    }

    #[test]
    fn work_on_a_dataset_is_bounded_by_its_size() {
        assert_eq!(scaled_bound(0), BLOCKING_CALL_BOUND);
        let ten_gib = scaled_bound(10 << 30);
        assert_eq!(ten_gib, BLOCKING_CALL_BOUND + Duration::from_secs(1024));
    }
}

//! The `pointfarm.v1` gRPC services: validate and convert requests, call [`Daemon`], convert
//! results. No domain logic lives here.
//!
//! - `conversions`: messages to domain types and back (`From`/`TryFrom`); the frame-task
//!   conversions are public, for the remote worker's side of the wire, and so are those of
//!   dataset descriptions, which `pointfarm info` builds from local files too.
//! - `status`: the one map from [`crate::error::DaemonError`] to status codes.
//! - `datasets`, `jobs`, `workers`: one file per service.
//! - `lease_guard`: gives back the frame of an abandoned long-polling lease request.
//! - `streaming`: the one chunk size and the helpers for every stream of bytes.

use std::sync::Arc;

use tonic::Status;

use crate::error::DaemonError;
use crate::service::Daemon;

mod conversions;
mod datasets;
mod jobs;
mod lease_guard;
mod request;
mod status;
pub mod streaming;
mod workers;

pub use conversions::{
    copc_chunks, dataset_description, file_description, frame_cut_message, frame_cut_of_message,
    frame_task, frame_task_message, node_key_message, preview_sample_bounds, stage_timings,
    timings_message,
};
pub use request::{camera_path_message, render_options_message, render_request};
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

    /// Runs `work` on the daemon off the async executor: store work blocks.
    async fn run<T: Send + 'static>(
        &self,
        work: impl FnOnce(&Arc<Daemon>) -> Result<T, DaemonError> + Send + 'static,
    ) -> Result<T, Status> {
        let daemon = self.daemon.clone();
        tokio::task::spawn_blocking(move || work(&daemon))
            .await
            .map_err(|e| Status::internal(e.to_string()))?
            .map_err(Status::from)
    }
}

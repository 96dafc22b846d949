//! Object storage's figures, against a real S3-compatible server (`s3s-fs`) on loopback:
//!
//! - [`copc_s3`] (`--copc POINTS --copc-s3`): a COPC file's first frame from the S3 server
//!   against the same file on the local disk, both from cold caches, and the bytes fetched
//!   against those of the nodes drawn;
//! - [`published`] (`--published-store POINTS`): two worker processes rendering a cold
//!   turntable of a store the daemon published with `serve --store-url`, and the daemon's CPU
//!   time against theirs;
//! - [`s3_server`]: the server, started over a folder whose files are the bucket's objects.

pub mod copc_s3;
pub mod published;
pub mod s3_server;

use pointfarm_render::copc::CopcError;
use pointfarm_render::gpu::GpuError;
use pointfarm_render::remote::RemoteError;

use crate::BenchError;

/// Why an object-storage benchmark failed.
#[derive(Debug, thiserror::Error)]
pub enum ObjectStorageError {
    #[error(transparent)]
    Bench(#[from] BenchError),
    #[error(transparent)]
    Gpu(#[from] GpuError),
    #[error(transparent)]
    Copc(#[from] CopcError),
    #[error(transparent)]
    Remote(#[from] RemoteError),
    /// Starting or driving the server, the daemon, the workers or a command; the message says
    /// which.
    #[error("{0}")]
    Setup(String),
}

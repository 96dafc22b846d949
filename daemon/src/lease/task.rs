//! What a lease hands a worker and what the worker answers: the frame task with its dataset,
//! the outcome of a finished frame, the kind of a failure and the answer to a heartbeat.

use std::time::Duration;

use pointfarm_render::request::RenderRequest;

use crate::lease_record::Lease;
pub use crate::model::PublishedStore;
use crate::model::{FrameCut, RemoteSource, StageTiming};

/// The dataset of a task, as a worker's cache knows it.
#[derive(Debug, Clone, PartialEq)]
pub struct TaskDataset {
    pub id: String,
    /// The content's hash: the key of the worker's cache.
    pub sha256: String,
    pub size_bytes: u64,
    /// Its files in order, fetched one by one; none for a dataset by URL.
    pub files: Vec<TaskFile>,
    /// The object of a dataset by URL, which the worker reads itself.
    pub remote: Option<RemoteSource>,
    /// Its level-of-detail store where the daemon published it, which the worker reads
    /// itself; `None` keeps the daemon-served path.
    pub published: Option<PublishedStore>,
}

/// One file of a task's dataset.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TaskFile {
    pub sha256: String,
    pub size_bytes: u64,
}

/// One leased frame with everything needed to render it.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameTask {
    pub lease: Lease,
    pub lease_timeout: Duration,
    pub dataset: TaskDataset,
    /// The job's request; the frame is `lease.index` of its camera path.
    pub request: RenderRequest,
    /// Attempts at this frame that ended without a result.
    pub failed_attempts: u32,
}

impl FrameTask {
    /// Set when the job asks for previews and the frame has none yet, or one older than the
    /// build's version: while the daemon builds the dataset's store, the worker renders it
    /// from the preview sample, of this version at least.
    pub fn preview(&self) -> Option<u32> {
        self.lease.preview_version
    }
}

/// What a worker reports with a finished frame's PNG.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameOutcome {
    pub timings: Vec<StageTiming>,
    pub dataset_cache_hit: Option<bool>,
    pub cut: Option<FrameCut>,
    /// Set on a preview: its completeness (0 to 1).
    pub preview: Option<f64>,
}

/// Whether a failed frame is worth another attempt.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FailureKind {
    /// May succeed next time: a lost GPU, an I/O error, a dead worker.
    Transient,
    /// Fails the same way every time: an unreadable dataset, a request that cannot render.
    Permanent,
}

/// The answer to a heartbeat.
#[derive(Debug, Clone, PartialEq)]
pub enum HeartbeatAnswer {
    Continue {
        expires_unix_ms: i64,
    },
    /// Drop the frame, for this reason.
    Stop(String),
}

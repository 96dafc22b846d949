//! The benchmark's errors.

use pointfarm_render::cache::CacheError;
use pointfarm_render::cut::CutError;
use pointfarm_render::ingest::IngestError;
use pointfarm_render::lod::LodError;
use pointfarm_render::raster::RenderError;

/// Why a run failed.
#[derive(Debug, thiserror::Error)]
pub enum BenchError {
    #[error(transparent)]
    Render(#[from] RenderError),
    #[error(transparent)]
    Ingest(#[from] IngestError),
    #[error(transparent)]
    Lod(#[from] LodError),
    #[error(transparent)]
    Cut(#[from] CutError),
    #[error("the benchmark needs at least one measured frame")]
    NoFrames,
    #[error("no workload matches --only {0}")]
    NothingSelected(String),
    #[error(transparent)]
    DatasetCache(#[from] CacheError),
    #[error("{0}")]
    CacheMismatch(String),
    /// Writing or reading the COPC benchmark's file; the message names it.
    #[error("{0}")]
    Copc(String),
    #[error("the scheduler's daemon: {0}")]
    Scheduler(String),
    #[error("benchmark scratch space: {0}")]
    Scratch(String),
    #[error("the benchmark's JSON: {0}")]
    Json(String),
    /// Drawing the plot or finding its font failed; the message says which.
    #[error("{0}")]
    Plot(String),
    #[error("writing {}", path.display())]
    Write {
        path: std::path::PathBuf,
        source: std::io::Error,
    },
}

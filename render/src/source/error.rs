//! Why a frame source could not open or render.

use std::path::PathBuf;

use thiserror::Error;

use crate::cache::CacheError;
use crate::copc::CopcError;
use crate::cut::CutError;
use crate::filter::FilterError;
use crate::ingest::IngestError;
use crate::raster::RenderError;

/// Why a frame source could not open or render.
#[derive(Debug, Error)]
pub enum SourceError {
    #[error(transparent)]
    Ingest(#[from] IngestError),
    #[error(transparent)]
    Cache(#[from] CacheError),
    #[error(transparent)]
    Copc(#[from] CopcError),
    #[error(transparent)]
    Cut(#[from] CutError),
    #[error(transparent)]
    Render(#[from] RenderError),
    #[error(transparent)]
    Filter(#[from] FilterError),
    #[error("{}: {error}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        error: std::io::Error,
    },
    /// A store failed its checks again after this opening had built it again.
    #[error(
        "the levels of detail in {} failed their checks again after they were rebuilt: {damage}",
        folder.display()
    )]
    DamagedAgain { folder: PathBuf, damage: CutError },
}

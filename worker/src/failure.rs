//! Why a worker could not render a frame, and whether another attempt may succeed: what
//! cannot be read or rendered fails the same way every time, while lost GPUs, I/O errors and
//! cut downloads may not.

use pointfarm_daemon::lease::FailureKind;
use pointfarm_render::cache::CacheError;
use pointfarm_render::copc::CopcError;
use pointfarm_render::cut::CutError;
use pointfarm_render::ingest::IngestError;
use pointfarm_render::raster::RenderError;
use pointfarm_render::source::SourceError;

/// A frame's failure as the worker reports it.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameFailure {
    pub reason: String,
    pub kind: FailureKind,
}

impl FrameFailure {
    pub fn transient(reason: impl Into<String>) -> Self {
        Self {
            reason: reason.into(),
            kind: FailureKind::Transient,
        }
    }

    pub fn permanent(reason: impl Into<String>) -> Self {
        Self {
            reason: reason.into(),
            kind: FailureKind::Permanent,
        }
    }

    /// The same failure with `context` before its reason (e.g. the dataset).
    pub fn context(self, context: &str) -> Self {
        Self {
            reason: format!("{context}: {}", self.reason),
            kind: self.kind,
        }
    }
}

/// A file that cannot be opened or read may be readable next time; a file that is not
/// LAS/LAZ, is cut short or corrupt never will be.
impl From<&IngestError> for FrameFailure {
    fn from(e: &IngestError) -> Self {
        match e {
            IngestError::Io { .. } => Self::transient(e.to_string()),
            _ => Self::permanent(e.to_string()),
        }
    }
}

/// Only the file's contents are permanent; the cache's own troubles are not the frame's.
impl From<&CacheError> for FrameFailure {
    fn from(e: &CacheError) -> Self {
        match e {
            CacheError::Ingest(ingest) => ingest.into(),
            _ => Self::transient(e.to_string()),
        }
    }
}

/// A bad file fails every time; a damaged store is rebuilt by the next attempt, the GPU may
/// come back.
impl From<&CutError> for FrameFailure {
    fn from(e: &CutError) -> Self {
        match e {
            CutError::Ingest(ingest) => ingest.into(),
            CutError::Render(render) => render.into(),
            CutError::Options(_) | CutError::DiskTooSmall { .. } => Self::permanent(e.to_string()),
            CutError::Store(_) | CutError::Cache(_) => Self::transient(e.to_string()),
        }
    }
}

/// A request that fails validation (sizes, options, camera, an empty cloud) fails every time;
/// the GPU may come back.
impl From<&RenderError> for FrameFailure {
    fn from(e: &RenderError) -> Self {
        match e {
            RenderError::Gpu(_) => Self::transient(e.to_string()),
            _ => Self::permanent(e.to_string()),
        }
    }
}

/// A frame source's failure is its part's: the files, the cache, the store, the GPU. A store
/// that failed its checks again, or could not be read or built again, is built anew by the
/// next attempt.
impl From<&SourceError> for FrameFailure {
    fn from(e: &SourceError) -> Self {
        match e {
            SourceError::Ingest(ingest) => ingest.into(),
            SourceError::Cache(cache) => cache.into(),
            SourceError::Cut(cut) => cut.into(),
            SourceError::Render(render) => render.into(),
            SourceError::Copc(CopcError::Ingest(ingest)) => ingest.into(),
            // A dataset by URL's server may answer the next attempt.
            SourceError::Copc(CopcError::Remote(remote)) => remote.into(),
            SourceError::Copc(CopcError::Io { .. })
            | SourceError::Io { .. }
            | SourceError::DamagedAgain { .. } => Self::transient(e.to_string()),
            SourceError::Copc(_) | SourceError::Filter(_) => Self::permanent(e.to_string()),
        }
    }
}

#[cfg(test)]
mod tests {
    use std::path::PathBuf;

    use super::*;

    #[test]
    fn unreadable_contents_and_invalid_requests_are_permanent_io_and_gpu_errors_not() {
        let path = PathBuf::from("scan.las");
        let cases = [
            (
                FrameFailure::from(&IngestError::NoPoints { path: path.clone() }),
                FailureKind::Permanent,
            ),
            (
                FrameFailure::from(&CacheError::Ingest(IngestError::NotLas {
                    path: path.clone(),
                    found: "PK".into(),
                })),
                FailureKind::Permanent,
            ),
            (
                FrameFailure::from(&IngestError::Io {
                    path,
                    error: std::io::Error::other("device gone"),
                }),
                FailureKind::Transient,
            ),
            (
                FrameFailure::from(&CacheError::Corrupt("x".into())),
                FailureKind::Transient,
            ),
            (
                FrameFailure::from(&RenderError::PointSize(99)),
                FailureKind::Permanent,
            ),
            (
                FrameFailure::from(&RenderError::Gpu("device lost".into())),
                FailureKind::Transient,
            ),
        ];
        for (failure, kind) in cases {
            assert_eq!(failure.kind, kind, "{}", failure.reason);
        }
    }
}

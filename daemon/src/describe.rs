//! What a dataset's files hold (`DescribeDataset`, `pointfarm info`): each file's header
//! facts and, when asked, a summary of its points, read with the render crate's
//! [`FileInfo`], and a COPC file's octree. A dataset of tiles by URL is described tile by tile
//! from each one's header and records, read by range at the version its registration recorded
//! (never its points, which would download it whole). A file that cannot be read is reported
//! with its error and the others still are. More `Daemon` methods.

use std::path::PathBuf;

use pointfarm_render::copc::{self, CopcError, CopcSummary};
use pointfarm_render::ingest::{FileInfo, IngestError, PointSummary};
use pointfarm_render::remote::{ListedObject, RemoteClient};
use pointfarm_render::source::{describe_tile, SourceError};

use crate::error::DaemonError;
use crate::model::Dataset;
use crate::service::Daemon;

/// One file's report: its header facts and, when read, its points; or why it could not be read.
pub struct FileReport {
    pub path: PathBuf,
    pub outcome: Result<(FileInfo, Option<PointSummary>), IngestError>,
    /// For a COPC file: its octree, or why its hierarchy cannot be read.
    pub copc: Option<Result<CopcSummary, CopcError>>,
}

impl FileReport {
    /// Reads `path`'s header and records and, with `read_points`, every point once, telling
    /// `progress` the header's facts and then the points read so far.
    pub fn read(
        path: PathBuf,
        read_points: bool,
        progress: impl FnOnce(&FileInfo) -> Box<dyn FnMut(u64)>,
    ) -> Self {
        let outcome = FileInfo::read(&path).and_then(|info| {
            if !read_points {
                return Ok((info, None));
            }
            let summary = info.read_points(progress(&info))?;
            Ok((info, Some(summary)))
        });
        let copc = match (&outcome, copc::is_copc(&path)) {
            (Ok(_), Ok(true)) => Some(copc::describe(&path)),
            _ => None,
        };
        Self {
            path,
            outcome,
            copc,
        }
    }

    /// Reads the header and records of `tile` by range, held to its listed version: a tile
    /// replaced since is reported changed, naming it.
    pub fn read_tile(client: &RemoteClient, tile: &ListedObject) -> Self {
        let outcome = client
            .open_listed(&tile.url, tile.version.as_deref())
            .map_err(IngestError::Remote)
            .and_then(|object| describe_tile(object).map_err(|e| ingest_error(tile, e)))
            .map(|info| (info, None));
        Self {
            path: tile.url.to_string().into(),
            outcome,
            copc: None,
        }
    }
}

/// A tile's error as a file's: each names the tile already.
fn ingest_error(tile: &ListedObject, error: SourceError) -> IngestError {
    match error {
        SourceError::Ingest(error) | SourceError::Copc(CopcError::Ingest(error)) => error,
        SourceError::Copc(CopcError::Remote(error)) => IngestError::Remote(error),
        SourceError::Copc(CopcError::Io { path, error }) => IngestError::Io { path, error },
        other => IngestError::Io {
            path: tile.url.to_string().into(),
            error: std::io::Error::other(other.to_string()),
        },
    }
}

impl Daemon {
    /// The reports of every file of dataset `id`, in its order. Blocks for as long as the
    /// files take to read.
    pub fn describe_dataset(
        &self,
        id: &str,
        read_points: bool,
    ) -> Result<Vec<FileReport>, DaemonError> {
        let dataset = self.dataset(id)?;
        if !dataset.tiles.is_empty() {
            return self.describe_tiles(&dataset);
        }
        dataset.check_local("describing")?;
        Ok(dataset
            .files()
            .into_iter()
            .map(|file| match self.open_dataset_file(&file.path) {
                // Read only while it still is the regular file inside the data roots it was.
                Ok(_) => FileReport::read(file.path, read_points, |_| Box::new(|_: u64| {})),
                Err(error) => FileReport {
                    outcome: Err(IngestError::Io {
                        path: file.path.clone(),
                        error,
                    }),
                    path: file.path,
                    copc: None,
                },
            })
            .collect())
    }

    /// The reports of every tile of `dataset`, a dataset of tiles by URL, in its order: each
    /// one's header and records read by range at its recorded version, never its points.
    fn describe_tiles(&self, dataset: &Dataset) -> Result<Vec<FileReport>, DaemonError> {
        let (client, tiles) = self.stores.tiles_of(dataset)?;
        Ok(tiles
            .iter()
            .map(|tile| FileReport::read_tile(&client, tile))
            .collect())
    }
}

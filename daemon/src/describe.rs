//! What a dataset's files hold (`DescribeDataset`, `pointfarm info`): each file's header
//! facts and, when asked, a summary of its points, read with the render crate's
//! [`FileInfo`], and a COPC file's octree. A dataset of tiles by URL is described tile by tile
//! from each one's header and records, read by range at the version its registration recorded,
//! and, when asked, its points streamed by range in bounded blocks at that version, as many
//! tiles at once as the remote client sends requests, in the dataset's order. A COPC object by
//! URL is described from its header, records and hierarchy read by range at its recorded
//! version, and its points, when asked, streamed the same way. A file that cannot be read is
//! reported with its error and the others still are. More `Daemon` methods.
//!
//! Memory while points stream: each tile's reader holds at most four blocks of
//! `remote::STREAM_BLOCK_BYTES` (8 MiB; three kept and one read ahead) and one decoded batch,
//! and at most the client's `parallel_requests` tiles (8 by default) are read at once: 256 MiB
//! of blocks at the defaults, whatever the tiles' sizes.

use std::path::PathBuf;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Mutex;

use pointfarm_render::copc::{self, CopcError, CopcSummary};
use pointfarm_render::ingest::{FileInfo, IngestError, PointSummary};
use pointfarm_render::remote::{ListedObject, RemoteClient, RemoteObject};
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

    /// Reads the header and records of `tile` by range, held to its listed version, and with
    /// `read_points` every point streamed in bounded blocks at that version: a tile replaced
    /// since, or while it is read, is reported changed, naming it.
    pub fn read_tile(client: &RemoteClient, tile: &ListedObject, read_points: bool) -> Self {
        let path: PathBuf = tile.url.to_string().into();
        let outcome = client
            .open_listed(&tile.url, tile.version.as_deref())
            .map_err(IngestError::Remote)
            .and_then(|object| describe_tile(object).map_err(|e| ingest_error(&path, e)))
            .and_then(|info| points_of(info, read_points));
        Self {
            path,
            outcome,
            copc: None,
        }
    }

    /// Reads a COPC object, opened at the version its dataset was registered at, as
    /// [`Self::read`] reads a file: its header, records and hierarchy by range and, with
    /// `read_points`, every point streamed in bounded blocks, each read pinned to that version.
    pub fn read_copc_object(object: RemoteObject, read_points: bool) -> Self {
        let path: PathBuf = object.url().to_string().into();
        let outcome = describe_tile(object.clone())
            .map_err(|e| ingest_error(&path, e))
            .and_then(|info| points_of(info, read_points));
        let copc = outcome.is_ok().then(|| copc::describe_object(object));
        Self {
            path,
            outcome,
            copc,
        }
    }
}

/// `info` with, when `read_points`, the summary of its points, streamed from its object.
fn points_of(
    info: FileInfo,
    read_points: bool,
) -> Result<(FileInfo, Option<PointSummary>), IngestError> {
    if !read_points {
        return Ok((info, None));
    }
    let summary = info.read_points(|_| {})?;
    Ok((info, Some(summary)))
}

/// An object's error as a file's: each names the object already.
fn ingest_error(path: &std::path::Path, error: SourceError) -> IngestError {
    match error {
        SourceError::Ingest(error) | SourceError::Copc(CopcError::Ingest(error)) => error,
        SourceError::Copc(CopcError::Remote(error)) => IngestError::Remote(error),
        SourceError::Copc(CopcError::Io { path, error }) => IngestError::Io { path, error },
        other => IngestError::Io {
            path: path.to_owned(),
            error: std::io::Error::other(other.to_string()),
        },
    }
}

/// `read` of each of `items` on up to `threads` threads at once, in `items`' order: reads of
/// objects each wait on round trips, which the connections overlap.
pub(crate) fn read_in_parallel<T: Sync, R: Send>(
    items: &[T],
    threads: usize,
    read: impl Fn(&T) -> R + Sync,
) -> Vec<R> {
    let next = AtomicUsize::new(0);
    let slots: Vec<Mutex<Option<R>>> = items.iter().map(|_| Mutex::new(None)).collect();
    std::thread::scope(|scope| {
        for _ in 0..threads.clamp(1, items.len().max(1)) {
            scope.spawn(|| loop {
                let index = next.fetch_add(1, Ordering::Relaxed);
                let Some(item) = items.get(index) else {
                    break;
                };
                let read = read(item);
                *slots[index].lock().unwrap_or_else(|e| e.into_inner()) = Some(read);
            });
        }
    });
    slots
        .into_iter()
        .filter_map(|slot| slot.into_inner().unwrap_or_else(|e| e.into_inner()))
        .collect()
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
            return self.describe_tiles_reading(&dataset, read_points);
        }
        if dataset.remote.is_some() {
            let object = self.open_registered_copc(&dataset)?;
            return Ok(vec![FileReport::read_copc_object(object, read_points)]);
        }
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
    pub(crate) fn describe_tiles(&self, dataset: &Dataset) -> Result<Vec<FileReport>, DaemonError> {
        self.describe_tiles_reading(dataset, false)
    }

    /// [`Self::describe_tiles`] and, with `read_points`, each tile's points streamed at its
    /// recorded version, as many tiles at once as the client sends requests in parallel.
    fn describe_tiles_reading(
        &self,
        dataset: &Dataset,
        read_points: bool,
    ) -> Result<Vec<FileReport>, DaemonError> {
        let (client, tiles) = self.stores.tiles_of(dataset)?;
        let threads = client.settings().parallel_requests;
        Ok(read_in_parallel(&tiles, threads, |tile| {
            FileReport::read_tile(&client, tile, read_points)
        }))
    }
}

#[cfg(test)]
mod tests {
    use std::sync::atomic::{AtomicUsize, Ordering};
    use std::time::Duration;

    use super::read_in_parallel;

    #[test]
    fn reads_run_at_most_so_many_at_once_and_answer_in_order() {
        let (running, most) = (AtomicUsize::new(0), AtomicUsize::new(0));
        let items: Vec<u32> = (0..40).collect();
        let read = |item: &u32| {
            let now = running.fetch_add(1, Ordering::SeqCst) + 1;
            most.fetch_max(now, Ordering::SeqCst);
            std::thread::sleep(Duration::from_millis(5));
            running.fetch_sub(1, Ordering::SeqCst);
            item * 2
        };
        let read = read_in_parallel(&items, 8, read);
        assert_eq!(read, items.iter().map(|i| i * 2).collect::<Vec<_>>());
        let most = most.load(Ordering::SeqCst);
        assert!((2..=8).contains(&most), "{most} at once");
        // One thread at least, and none for nothing.
        assert_eq!(read_in_parallel(&items[..3], 0, |i| *i), vec![0, 1, 2]);
        assert!(read_in_parallel(&[] as &[u32], 8, |i| *i).is_empty());
    }
}

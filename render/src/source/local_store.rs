//! Level-of-detail stores in folders of this machine: where they are kept and under which
//! name, and a store opened for frames with what builds it again when its bytes fail their
//! checks. A damaged store is never left behind: it is built again once from the dataset's
//! files, or removed so that the next opening builds it.

use std::path::{Path, PathBuf};
use std::sync::mpsc::Receiver;
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::UNIX_EPOCH;

use sha2::{Digest, Sha256};

use super::events::SourceEvent;
use super::tile_store::{open_or_build_tiles, StoreInput};
use super::SourceError;
use crate::cut::{CutError, StoreBuild, StoredLod};
use crate::lod::BuildProgress;
use crate::remote::{ListedObject, RemoteClient};

/// Where a machine keeps its stores, one folder each, and the most disk they may take
/// together (before a build, the least recently used others are removed until it fits).
#[derive(Debug, Clone)]
pub struct StoreCache {
    pub dir: PathBuf,
    pub disk_budget: Option<u64>,
}

impl StoreCache {
    /// The folder of the store of a dataset known by its content hash (a worker's datasets).
    pub fn folder_of_dataset(&self, sha256: &str) -> PathBuf {
        self.dir.join(sha256)
    }

    /// The folder of the store of local `files`: named by a digest of each file's absolute
    /// path, size and modification time, so later renders of the same files open it and a
    /// changed file gets a new one.
    pub fn folder_of_files(&self, files: &[PathBuf]) -> Result<PathBuf, SourceError> {
        Ok(self.dir.join(files_digest(files)?))
    }
}

/// A digest of each file's absolute path, size and modification time.
fn files_digest(files: &[PathBuf]) -> Result<String, SourceError> {
    let mut digest = Sha256::new();
    for file in files {
        let read = |error| SourceError::Io {
            path: file.clone(),
            error,
        };
        let path = std::fs::canonicalize(file).map_err(read)?;
        let meta = std::fs::metadata(&path).map_err(read)?;
        let modified = meta
            .modified()
            .ok()
            .and_then(|t| t.duration_since(UNIX_EPOCH).ok())
            .map_or(0, |d| d.as_nanos());
        digest.update(path.as_os_str().as_encoded_bytes());
        digest.update([0]);
        digest.update(meta.len().to_le_bytes());
        digest.update(modified.to_le_bytes());
    }
    Ok(digest
        .finalize()
        .iter()
        .take(12)
        .map(|b| format!("{b:02x}"))
        .collect())
}

/// A store of this machine opened for frames, with what builds it again when its bytes fail
/// their checks: once, from its dataset's files, after which a second failure is the error.
pub struct LocalStore {
    pub stored: StoredLod,
    /// The dataset's files; none when the store was opened without them (built before).
    files: Vec<PathBuf>,
    memory_budget: u64,
    disk_budget: Option<u64>,
    /// Whether this opening has built the store again already.
    rebuilt: bool,
}

impl LocalStore {
    /// Opens the store of `files` in `folder`, building it first when there is none, within
    /// `memory_budget` bytes of build buffers and `disk_budget` for the stores beside it. A
    /// store whose bytes fail their checks as it opens is built again, once. Without `files`
    /// a finished store is opened, or nothing.
    pub fn open_or_build(
        files: &[PathBuf],
        folder: &Path,
        memory_budget: u64,
        disk_budget: Option<u64>,
        events: &dyn Fn(SourceEvent<'_>),
    ) -> Result<Self, SourceError> {
        update_earlier_store(files, folder, memory_budget, events);
        let opened =
            StoredLod::open_or_build(files, folder, memory_budget, disk_budget, &mut |points| {
                events(SourceEvent::Building { points, folder })
            });
        let (stored, rebuilt) = match opened {
            Ok(stored) => (stored, false),
            Err(damage) if damage.is_store_damage() && !files.is_empty() => {
                let stored = rebuild(files, folder, memory_budget, disk_budget, &damage, events)?;
                (stored, true)
            }
            Err(error) => return Err(error.into()),
        };
        say_built(&stored, events);
        list_files(files, folder);
        Ok(Self {
            stored,
            files: files.to_vec(),
            memory_budget,
            disk_budget,
            rebuilt,
        })
    }

    /// A store built by another thread (behind a preview) from `files`.
    pub fn of_built(
        stored: StoredLod,
        files: &[PathBuf],
        memory_budget: u64,
        disk_budget: Option<u64>,
        events: &dyn Fn(SourceEvent<'_>),
    ) -> Self {
        say_built(&stored, events);
        Self {
            stored,
            files: files.to_vec(),
            memory_budget,
            disk_budget,
            rebuilt: false,
        }
    }

    /// The store's folder.
    pub fn folder(&self) -> &Path {
        &self.stored.folder
    }

    /// How many files the store was opened with (none: opened without them).
    pub fn file_count(&self) -> usize {
        self.files.len()
    }

    /// Builds the store again after `damage` (its bytes failed their checks), the first time
    /// and when it has its files. Otherwise the damaged store is removed, for the next opening
    /// to build, and `damage` is the error: after a rebuild, naming the store's folder.
    pub fn rebuild_after(
        &mut self,
        damage: CutError,
        events: &dyn Fn(SourceEvent<'_>),
    ) -> Result<(), SourceError> {
        let folder = self.stored.folder.clone();
        if self.rebuilt || self.files.is_empty() {
            tracing::warn!(folder = %folder.display(), reason = %damage, "removing a damaged store");
            StoredLod::remove_damaged(&folder)?;
            return Err(match self.rebuilt {
                true => SourceError::DamagedAgain { folder, damage },
                false => damage.into(),
            });
        }
        self.rebuilt = true;
        let stored = rebuild(
            &self.files,
            &folder,
            self.memory_budget,
            self.disk_budget,
            &damage,
            events,
        )?;
        say_built(&stored, events);
        // The damaged store's files are let go of only now: its folder was removed first.
        self.stored = stored;
        Ok(())
    }

    /// Builds the store of `input` (files here, or tiles by URL streamed) in `folder` on a
    /// thread of its own once `start` is sent to or dropped, listing in `progress` the nodes it
    /// stores as it stores them: a preview draws them meanwhile.
    pub fn build_in_background(
        input: StoreInput,
        folder: PathBuf,
        memory_budget: u64,
        disk_budget: Option<u64>,
        start: Receiver<()>,
        progress: Arc<BuildProgress>,
    ) -> Result<JoinHandle<Result<StoredLod, CutError>>, SourceError> {
        build_on_thread(start, move || {
            let on_build = &mut |points| {
                tracing::info!(
                    points,
                    folder = %folder.display(),
                    "building levels of detail behind a preview"
                );
            };
            let build = StoreBuild {
                folder: &folder,
                memory_budget,
                disk_budget,
                on_build,
                progress: &progress,
            };
            let files = match input {
                StoreInput::Files(files) => files,
                StoreInput::Tiles(client, tiles) => {
                    return open_or_build_tiles(&client, &tiles, build);
                }
            };
            update_earlier_store(&files, &folder, memory_budget, &|_| {});
            let opened = StoredLod::open_or_build_watched(&files, build);
            if opened.is_ok() {
                list_files(&files, &folder);
            }
            opened
        })
    }
}

/// Runs `build` on a thread of its own once `start` is sent to or dropped: a preview's first
/// frame goes first.
fn build_on_thread(
    start: Receiver<()>,
    build: impl FnOnce() -> Result<StoredLod, CutError> + Send + 'static,
) -> Result<JoinHandle<Result<StoredLod, CutError>>, SourceError> {
    std::thread::Builder::new()
        .name("lod-build".into())
        .spawn(move || {
            // Sent or dropped: either way the build goes on.
            let _ = start.recv();
            build()
        })
        .map_err(|error| SourceError::Io {
            path: PathBuf::from("lod-build thread"),
            error,
        })
}

/// Updates the store of an earlier set of `files` into `folder` where there is one
/// (`earlier.rs`); a store that cannot be updated is left for the opening to build.
pub(super) fn update_earlier_store(
    files: &[PathBuf],
    folder: &Path,
    memory_budget: u64,
    events: &dyn Fn(SourceEvent<'_>),
) {
    if files.is_empty() {
        return;
    }
    match earlier::update_earlier(files, folder, memory_budget) {
        Ok(Some(updated)) => {
            let regions_rebuilt = updated.report.regions_rebuilt + updated.report.regions_added;
            tracing::info!(
                folder = %folder.display(),
                points_added = updated.report.points_added,
                points_removed = updated.report.points_removed,
                files_reread = updated.report.files_reread,
                seconds = format!("{:.1}", updated.report.seconds),
                "updated store: {} files added, {} removed, {} changed, {regions_rebuilt} regions rebuilt",
                updated.files_added,
                updated.files_removed,
                updated.files_changed,
            );
            events(SourceEvent::Updated {
                files_added: updated.files_added,
                files_removed: updated.files_removed,
                files_changed: updated.files_changed,
                regions_rebuilt,
                points_added: updated.report.points_added,
                points_removed: updated.report.points_removed,
                seconds: updated.report.seconds,
            });
        }
        Ok(None) => {}
        Err(reason) => {
            tracing::info!(folder = %folder.display(), %reason, "building the store in full")
        }
    }
}

/// Keeps the list of the store's `files` in `folder`, for a later set of them to update it.
pub(super) fn list_files(files: &[PathBuf], folder: &Path) {
    if files.is_empty() || earlier::lists(folder, files) {
        return;
    }
    if let Err(reason) = earlier::write_file_list(folder, files) {
        tracing::warn!(folder = %folder.display(), %reason, "the store's file list");
    }
}

/// Removes the damaged store in `folder` and builds it anew from `files`.
fn rebuild(
    files: &[PathBuf],
    folder: &Path,
    memory_budget: u64,
    disk_budget: Option<u64>,
    damage: &CutError,
    events: &dyn Fn(SourceEvent<'_>),
) -> Result<StoredLod, CutError> {
    tracing::warn!(folder = %folder.display(), reason = %damage, "rebuilding a damaged store");
    events(SourceEvent::Rebuilding { folder, damage });
    StoredLod::remove_damaged(folder)?;
    StoredLod::open_or_build(files, folder, memory_budget, disk_budget, &mut |points| {
        events(SourceEvent::Building { points, folder })
    })
}

/// Tells how the store was built, when its opening built it.
fn say_built(stored: &StoredLod, events: &dyn Fn(SourceEvent<'_>)) {
    if let Some((report, seconds)) = &stored.built {
        events(SourceEvent::Built {
            nodes: report.hierarchy.nodes().len(),
            points: stored.dataset.point_count(),
            seconds: *seconds,
        });
    }
}

mod earlier;
impl StoreCache {
    /// The folder of the store of `tiles` by URL: named by a digest of each one's URL, size
    /// and version, so a replaced object gets a new store.
    pub fn folder_of_objects(&self, tiles: &[ListedObject]) -> PathBuf {
        let mut digest = Sha256::new();
        digest.update(b"objects\0");
        for tile in tiles {
            digest.update(tile.url.as_str().as_bytes());
            digest.update([0]);
            digest.update(tile.size.to_le_bytes());
            digest.update(tile.version.as_deref().unwrap_or("").as_bytes());
            digest.update([0]);
        }
        let name: String = (digest.finalize().iter().take(12))
            .map(|b| format!("{b:02x}"))
            .collect();
        self.dir.join(name)
    }
}

impl LocalStore {
    /// The store of `tiles` by URL in `folder`, opened, or built first by streaming them. A
    /// store that fails its checks later is removed, for the next render to build.
    pub fn open_or_build_tiles(
        client: &RemoteClient,
        tiles: &[ListedObject],
        folder: &Path,
        memory_budget: u64,
        disk_budget: Option<u64>,
        events: &dyn Fn(SourceEvent<'_>),
    ) -> Result<Self, SourceError> {
        let build = StoreBuild {
            folder,
            memory_budget,
            disk_budget,
            on_build: &mut |points| events(SourceEvent::Building { points, folder }),
            progress: &BuildProgress::new(),
        };
        let stored = open_or_build_tiles(client, tiles, build)?;
        Ok(Self::of_built(
            stored,
            &[],
            memory_budget,
            disk_budget,
            events,
        ))
    }
}

#[cfg(test)]
mod tests;

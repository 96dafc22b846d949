//! The disk space of the level-of-detail stores kept side by side in one folder (a worker's
//! `lod` folder, the CLI's): they are kept within a byte budget by removing the least recently
//! used ones before a build. A store's folder holds a `last_used` file, locked shared while
//! the store is open (by any process) and touched when it is opened and closed; a store whose
//! file is locked is in use and never removed. The stores' bytes are counted by
//! `lod::disk_usage`: a payload layer two stores link is counted once, and removing a store
//! frees only the files no other store links.

use std::fs::{File, OpenOptions};
use std::io;
use std::path::{Path, PathBuf};
use std::time::SystemTime;

use rustix::fs::FlockOperation;

use super::CutError;
#[cfg(test)]
pub(crate) use crate::lod::disk_usage::folder_bytes;
use crate::lod::disk_usage::DiskUsage;

/// The file in a store's folder whose lock marks the store in use and whose modification
/// time is when it was last used.
const LAST_USED_FILE: &str = "last_used";

/// A store's finished mark (see `stored.rs`); a folder without it is unfinished or damaged.
const FINISHED_FILE: &str = "finished.json";

/// The prefix of a folder being removed: renamed first, so its name is free at once.
const REMOVING_PREFIX: &str = ".removing-";

/// Holds a store's folder in use: a shared lock on its `last_used` file, whose modification
/// time is set when taken and when dropped.
#[derive(Debug)]
pub(crate) struct InUse {
    file: File,
}

impl InUse {
    /// Marks `folder` (created when missing) in use by this process until dropped. Waits
    /// while another process removes it, then takes the folder made anew.
    pub(crate) fn take(folder: &Path) -> Result<Self, CutError> {
        let failed = |e: io::Error| {
            CutError::Cache(format!(
                "marking the store in {} in use: {e}",
                folder.display()
            ))
        };
        let path = folder.join(LAST_USED_FILE);
        let mut last_error = None;
        for _ in 0..8 {
            std::fs::create_dir_all(folder).map_err(failed)?;
            let file = match open_rw(&path, true) {
                Ok(file) => file,
                // The folder was renamed away between its creation and the file's.
                Err(e) if e.kind() == io::ErrorKind::NotFound => {
                    last_error = Some(e);
                    continue;
                }
                Err(e) => return Err(failed(e)),
            };
            rustix::fs::flock(&file, FlockOperation::LockShared).map_err(|e| failed(e.into()))?;
            // The lock is the folder's only while its file is still at `path`: a removal
            // renames the folder away while holding the lock exclusively.
            if same_file(&file, &path) {
                let _ = file.set_modified(SystemTime::now());
                return Ok(Self { file });
            }
            last_error = Some(io::Error::other("removed while it was opened"));
        }
        Err(failed(
            last_error.unwrap_or_else(|| io::Error::other("busy")),
        ))
    }
}

impl Drop for InUse {
    fn drop(&mut self) {
        let _ = self.file.set_modified(SystemTime::now());
    }
}

fn open_rw(path: &Path, create: bool) -> io::Result<File> {
    OpenOptions::new()
        .read(true)
        .write(true)
        .create(create)
        .truncate(false)
        .open(path)
}

fn same_file(file: &File, path: &Path) -> bool {
    match (rustix::fs::fstat(file), rustix::fs::stat(path)) {
        (Ok(a), Ok(b)) => (a.st_dev, a.st_ino) == (b.st_dev, b.st_ino),
        _ => false,
    }
}

/// A store folder beside the one being built.
#[derive(Debug)]
struct Neighbour {
    folder: PathBuf,
    finished: bool,
    last_used: SystemTime,
}

impl Neighbour {
    fn read(folder: PathBuf) -> Self {
        let modified = |path: &Path| std::fs::metadata(path).and_then(|m| m.modified()).ok();
        let finished = folder.join(FINISHED_FILE).is_file()
            && !folder
                .file_name()
                .is_some_and(|n| n.to_string_lossy().starts_with(REMOVING_PREFIX));
        let last_used = modified(&folder.join(LAST_USED_FILE))
            .or_else(|| modified(&folder.join(FINISHED_FILE)))
            .or_else(|| modified(&folder))
            .unwrap_or(SystemTime::UNIX_EPOCH);
        Self {
            folder,
            finished,
            last_used,
        }
    }

    /// Why it goes before the others.
    fn reason(&self) -> &'static str {
        if self.finished {
            "least recently used store"
        } else {
            "unfinished or damaged store"
        }
    }
}

/// What [`make_space`] found and did.
#[derive(Debug, Default, Clone, PartialEq, Eq)]
pub(crate) struct SpaceReport {
    /// The folders removed, in order.
    pub removed: Vec<PathBuf>,
    /// The bytes their removal freed.
    pub removed_bytes: u64,
    /// The bytes of the stores left beside the one to build, each file once.
    pub remaining_bytes: u64,
}

/// Removes store folders beside `keep` (the folders in its parent), unfinished or damaged ones
/// first, then finished ones least recently used first, until `needed` bytes plus what remains
/// fit `budget`. Stores in use are left alone; when they alone leave too little room, the
/// build is refused with [`CutError::DiskTooSmall`] (`points` names it).
pub(crate) fn make_space(
    keep: &Path,
    points: u64,
    needed: u64,
    budget: u64,
) -> Result<SpaceReport, CutError> {
    let mib = |bytes: u64| bytes >> 20;
    let refuse = |limit: String| CutError::DiskTooSmall {
        points,
        needed_mib: mib(needed),
        folder: keep.to_owned(),
        limit,
    };
    if needed > budget {
        return Err(refuse(format!(
            "more than its budget of {} MiB",
            mib(budget)
        )));
    }
    let Some(root) = keep.parent() else {
        return Ok(SpaceReport::default());
    };
    let mut neighbours: Vec<Neighbour> = match std::fs::read_dir(root) {
        Ok(entries) => entries
            .flatten()
            .filter(|e| e.file_type().is_ok_and(|t| t.is_dir()))
            .map(|e| e.path())
            .filter(|path| path.file_name() != keep.file_name() && is_store(path))
            .map(Neighbour::read)
            .collect(),
        Err(_) => Vec::new(),
    };
    neighbours.sort_by(|a, b| {
        (a.finished, a.last_used, &a.folder).cmp(&(b.finished, b.last_used, &b.folder))
    });
    let mut all = DiskUsage::default();
    for neighbour in &neighbours {
        all.add(&neighbour.folder);
    }
    let mut report = SpaceReport {
        remaining_bytes: all.bytes(),
        ..SpaceReport::default()
    };
    for neighbour in &neighbours {
        if report.remaining_bytes.saturating_add(needed) <= budget {
            break;
        }
        // Measured just before: a layer it shares with a store removed before is its own now.
        let freed = DiskUsage::of(&neighbour.folder).freed_bytes();
        match remove_unused(root, &neighbour.folder) {
            Ok(true) => {
                tracing::info!(
                    folder = %neighbour.folder.display(),
                    bytes = freed,
                    why = neighbour.reason(),
                    needed,
                    budget,
                    "removed a level-of-detail store to keep the stores within their budget"
                );
                report.remaining_bytes = report.remaining_bytes.saturating_sub(freed);
                report.removed_bytes += freed;
                report.removed.push(neighbour.folder.clone());
            }
            Ok(false) => {}
            Err(error) => tracing::warn!(
                folder = %neighbour.folder.display(),
                %error,
                "could not remove a level-of-detail store"
            ),
        }
    }
    let total = report.remaining_bytes.saturating_add(needed);
    if total > budget {
        return Err(refuse(format!(
            "which with the {} MiB of stores in use is more than their budget of {} MiB",
            mib(report.remaining_bytes),
            mib(budget)
        )));
    }
    Ok(report)
}

/// Removes the store in `folder` unless it is in use: `Ok(false)` when it is.
fn remove_unused(root: &Path, folder: &Path) -> io::Result<bool> {
    let name = folder.file_name().unwrap_or_default().to_string_lossy();
    if name.starts_with(REMOVING_PREFIX) {
        std::fs::remove_dir_all(folder)?;
        return Ok(true);
    }
    let lock = match open_rw(&folder.join(LAST_USED_FILE), false) {
        Ok(file) => Some(file),
        Err(e) if e.kind() == io::ErrorKind::NotFound => None,
        Err(e) => return Err(e),
    };
    if let Some(lock) = &lock {
        match rustix::fs::flock(lock, FlockOperation::NonBlockingLockExclusive) {
            Ok(()) => {}
            Err(rustix::io::Errno::WOULDBLOCK) => return Ok(false),
            Err(e) => return Err(e.into()),
        }
    }
    let removing = root.join(format!("{REMOVING_PREFIX}{name}"));
    std::fs::rename(folder, &removing)?;
    // Whoever waits on the lock finds the folder gone and makes it anew.
    drop(lock);
    std::fs::remove_dir_all(&removing)?;
    Ok(true)
}

/// Removes the store in `folder` now, in use or not (a damaged store is of no use to anyone):
/// renamed away first, so that its name is free at once for the store built in its place,
/// while what still reads the old files reads them until it lets go. Nothing there is fine.
pub(crate) fn remove_now(folder: &Path) -> io::Result<()> {
    let Some(root) = folder.parent() else {
        return Err(io::Error::other("a store's folder has a parent"));
    };
    let name = folder.file_name().unwrap_or_default().to_string_lossy();
    let stamp = SystemTime::now()
        .duration_since(SystemTime::UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos());
    let removing = root.join(format!(
        "{REMOVING_PREFIX}{name}-{}-{stamp}",
        std::process::id()
    ));
    match std::fs::rename(folder, &removing) {
        Ok(()) => {}
        Err(e) if e.kind() == io::ErrorKind::NotFound => return Ok(()),
        Err(e) => return Err(e),
    }
    // Whoever waits on its lock finds the folder gone and makes it anew. What cannot be
    // removed now (a file written meanwhile) is removed with the stores beside a later build.
    if let Err(error) = std::fs::remove_dir_all(&removing) {
        tracing::warn!(%error, folder = %removing.display(), "removing a damaged store's files");
    }
    Ok(())
}

/// Whether `folder` holds a store, finished or not, or one being removed: other folders are
/// neither counted nor removed.
fn is_store(folder: &Path) -> bool {
    let name = folder.file_name().unwrap_or_default().to_string_lossy();
    name.starts_with(REMOVING_PREFIX)
        || [LAST_USED_FILE, FINISHED_FILE, "index", "nodes.bin", "spill"]
            .iter()
            .any(|file| folder.join(file).exists())
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    /// A store folder of `bytes` bytes in two files, finished or not, last used `age` ago.
    fn fake_store(root: &Path, name: &str, bytes: u64, finished: bool, age: u64) -> PathBuf {
        let folder = root.join(name);
        std::fs::create_dir_all(folder.join("index")).expect("folder");
        std::fs::write(folder.join("nodes.bin"), vec![7u8; (bytes / 2) as usize]).expect("write");
        let rest = bytes - bytes / 2;
        std::fs::write(folder.join("index").join("db"), vec![1u8; rest as usize]).expect("write");
        if finished {
            std::fs::write(folder.join(FINISHED_FILE), b"").expect("write");
        }
        let used = SystemTime::now() - Duration::from_secs(age);
        let file = open_rw(&folder.join(LAST_USED_FILE), true).expect("last used");
        file.set_modified(used).expect("touch");
        folder
    }

    fn names(report: &SpaceReport) -> Vec<String> {
        report
            .removed
            .iter()
            .map(|p| p.file_name().expect("name").to_string_lossy().into_owned())
            .collect()
    }

    #[test]
    fn a_folder_measures_the_lengths_of_its_files() {
        let dir = tempfile::tempdir().expect("tempdir");
        let folder = fake_store(dir.path(), "a", 10_001, true, 0);
        assert_eq!(folder_bytes(&folder), 10_001);
        assert_eq!(folder_bytes(&dir.path().join("missing")), 0);
    }

    #[test]
    fn unfinished_then_least_recently_used_stores_go_until_the_build_fits() {
        let dir = tempfile::tempdir().expect("tempdir");
        let root = dir.path();
        fake_store(root, "old", 1000, true, 300);
        fake_store(root, "recent", 1000, true, 10);
        fake_store(root, "older", 1000, true, 600);
        fake_store(root, "broken", 500, false, 1);
        let keep = fake_store(root, "keep", 5000, false, 1000);
        // 3500 bytes beside `keep`; 2000 to build within 4000 leaves room for 2000.
        let report = make_space(&keep, 1, 2000, 4000).expect("room made");
        assert_eq!(names(&report), ["broken", "older"]);
        assert_eq!(report.remaining_bytes, 2000);
        assert_eq!(report.removed_bytes, 1500);
        assert!(root.join("old").is_dir() && root.join("recent").is_dir() && keep.is_dir());
        assert!(!root.join("older").exists() && !root.join("broken").exists());
        let left = std::fs::read_dir(root).expect("list").count();
        assert_eq!(left, 3, "nothing is left of the removed folders");
        assert_eq!(folder_bytes(root) - folder_bytes(&keep), 2000);
        // Enough room: nothing goes.
        assert_eq!(
            make_space(&keep, 1, 2000, 4000)
                .expect("fits")
                .removed
                .len(),
            0
        );
    }

    #[test]
    fn a_layer_two_stores_share_is_counted_once_and_freed_with_the_last() {
        let dir = tempfile::tempdir().expect("tempdir");
        let root = dir.path();
        let first = fake_store(root, "first", 2000, true, 600);
        let grown = fake_store(root, "grown", 400, true, 10);
        std::fs::hard_link(first.join("nodes.bin"), grown.join("nodes.bin.0")).expect("a layer");
        let keep = root.join("new");
        // 2400 bytes beside `keep`, the shared 1000 once; the first store frees its index alone.
        let report = make_space(&keep, 1, 1000, 2500).expect("room made");
        assert_eq!(names(&report), ["first"]);
        assert_eq!((report.removed_bytes, report.remaining_bytes), (1000, 1400));
        assert_eq!(folder_bytes(root), 1400);
        // The layer is the grown store's own now, freed with it.
        let report = make_space(&keep, 1, 2000, 2500).expect("room made");
        assert_eq!(names(&report), ["grown"]);
        assert_eq!((report.removed_bytes, report.remaining_bytes), (1400, 0));
    }

    #[test]
    fn a_store_in_use_is_never_removed() {
        let dir = tempfile::tempdir().expect("tempdir");
        let root = dir.path();
        let oldest = fake_store(root, "oldest", 1000, true, 900);
        fake_store(root, "newer", 1000, true, 10);
        let in_use = InUse::take(&oldest).expect("in use");
        let keep = root.join("new");
        let report = make_space(&keep, 1, 1000, 2000).expect("room made");
        assert_eq!(names(&report), ["newer"]);
        assert!(oldest.join("nodes.bin").is_file());
        // With nothing else to remove, the stores in use leave too little room.
        let error = make_space(&keep, 7, 1500, 2000).expect_err("refused");
        assert!(matches!(error, CutError::DiskTooSmall { points: 7, .. }));
        assert!(error.to_string().contains("stores in use"), "{error}");
        drop(in_use);
        let report = make_space(&keep, 1, 1500, 2000).expect("room made");
        assert_eq!(names(&report), ["oldest"]);
    }

    #[test]
    fn a_build_larger_than_the_budget_removes_nothing() {
        let dir = tempfile::tempdir().expect("tempdir");
        let other = fake_store(dir.path(), "other", 1000, true, 100);
        let keep = dir.path().join("new");
        let error = make_space(&keep, 3, 300 << 20, 100 << 20).expect_err("refused");
        assert!(error.to_string().contains("budget of 100 MiB"), "{error}");
        assert!(other.join("nodes.bin").is_file());
    }

    #[test]
    fn folders_that_hold_no_store_are_left_alone() {
        let dir = tempfile::tempdir().expect("tempdir");
        let unrelated = dir.path().join("photos");
        std::fs::create_dir_all(&unrelated).expect("folder");
        std::fs::write(unrelated.join("a.jpg"), vec![0u8; 5000]).expect("write");
        let store = fake_store(dir.path(), "store", 1000, true, 100);
        let report = make_space(&dir.path().join("new"), 1, 1000, 1000).expect("room made");
        assert_eq!(report.removed, [store]);
        assert_eq!(report.remaining_bytes, 0);
        assert!(unrelated.join("a.jpg").is_file());
    }

    #[test]
    fn taking_a_store_in_use_touches_it_and_a_removed_one_is_made_anew() {
        let dir = tempfile::tempdir().expect("tempdir");
        let folder = fake_store(dir.path(), "a", 100, true, 1000);
        let before = SystemTime::now() - Duration::from_secs(1);
        let in_use = InUse::take(&folder).expect("in use");
        let touched = std::fs::metadata(folder.join(LAST_USED_FILE))
            .and_then(|m| m.modified())
            .expect("mtime");
        assert!(touched >= before);
        drop(in_use);
        assert!(remove_unused(dir.path(), &folder).expect("removed"));
        assert!(!folder.exists());
        let again = InUse::take(&folder).expect("made anew");
        assert!(folder.join(LAST_USED_FILE).is_file());
        assert!(!remove_unused(dir.path(), &folder).expect("in use"));
        drop(again);
    }
}

//! A local store updated instead of built anew when its files changed: a store folder is named
//! by its files, so the files of a dataset that gained, lost or changed a tile name a folder
//! without a store; the store of the earlier files (a folder beside it whose file list shares
//! at least half of its files and of the dataset's) is taken over and updated with the added
//! files, without the removed ones; a changed file (the same path, another length or
//! modification time) is both ([`crate::lod::update_store`]). A store in the folder itself is
//! updated whatever share of the files it holds: the folder is named by them, so it was
//! built for them (camera first, from the files a camera path sees: `camera_first.rs`).
//!
//! Each local store keeps its file list, one line a file (its points, and its path, length and
//! modification time: one file's [`files_fingerprint`], which also names a build's inputs), in
//! `files.txt`, written after a build or update finishes, in the order the store took its files
//! in, which is how an update names the removed ones. The list is trusted only where its
//! points add up to the store's: an update that stopped after its store switched, before the
//! list was written, leaves a store of other points, which is then used as it is or built
//! again, never updated twice.
//!
//! Taking a store over: its folder is locked against other users (the lock every opening of a
//! store takes, `cut/store_space.rs`, exclusively and without waiting: a store in use is not
//! taken), unmarked as finished, then renamed to the new folder. An update killed part way
//! leaves the old store whole in the new folder, unfinished, for the next opening to update.

use std::collections::HashSet;
use std::path::{Path, PathBuf};

use crate::ingest::{update_from_files, DatasetSource, FilesChange};
use crate::lod::source::files_fingerprint;
use crate::lod::{LodStore, LodUpdateReport, PointSource};

const FILE_LIST: &str = "files.txt";
/// What `cut/stored.rs` names the parts of a store's folder.
const INDEX_FOLDER: &str = "index";
const PAYLOAD_FILE: &str = "nodes.bin";
const FINISHED_FILE: &str = "finished.json";
const LAST_USED_FILE: &str = "last_used";

/// One file of a store: its points, and its path, length and modification time.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
struct ListedFile {
    points: u64,
    identity: String,
}

/// The update a store of earlier files got, with what it was told.
pub struct Updated {
    pub report: LodUpdateReport,
    pub files_added: usize,
    pub files_removed: usize,
    /// Files of the same path with other contents: each removed as it was, added as it is.
    pub files_changed: usize,
}

impl ListedFile {
    /// Whether the file is no longer there as it was listed: deleted, or changed.
    fn is_gone(&self) -> bool {
        files_fingerprint([Path::new(self.path())]).is_none_or(|now| now != self.identity)
    }

    /// The file's path, as its identity spells it.
    fn path(&self) -> &str {
        let identity = self.identity.trim_end_matches("; ");
        identity
            .rsplit_once(" bytes modified ")
            .and_then(|(path_len, _)| path_len.rsplit_once(' '))
            .map_or(identity, |(path, _)| path)
    }
}

/// Each of `files` as listed, its points read from its header.
fn list_of(files: &[PathBuf]) -> Result<Vec<ListedFile>, String> {
    files
        .iter()
        .map(|file| {
            let identity = files_fingerprint([file.as_path()])
                .ok_or_else(|| format!("{} cannot be looked up", file.display()))?;
            let source =
                DatasetSource::open(std::slice::from_ref(file)).map_err(|e| e.to_string())?;
            Ok(ListedFile {
                points: source.point_count(),
                identity,
            })
        })
        .collect()
}

fn read_list(folder: &Path) -> Option<Vec<ListedFile>> {
    let text = std::fs::read_to_string(folder.join(FILE_LIST)).ok()?;
    text.lines()
        .map(|line| {
            let (points, identity) = line.split_once('\t')?;
            Some(ListedFile {
                points: points.parse().ok()?,
                identity: identity.to_string(),
            })
        })
        .collect()
}

/// Writes the list of `files`, in the order the store took them in, into the store's
/// `folder`, replacing the one there at once.
pub fn write_file_list(folder: &Path, files: &[PathBuf]) -> Result<(), String> {
    write_list(folder, &list_of(files)?)
}

fn write_list(folder: &Path, list: &[ListedFile]) -> Result<(), String> {
    let text: String = list
        .iter()
        .map(|f| format!("{}\t{}\n", f.points, f.identity))
        .collect();
    crate::write_whole::write_whole(&folder.join(FILE_LIST), text.as_bytes())
        .map_err(|e| format!("writing the file list in {}: {e}", folder.display()))
}

/// Whether `folder` lists exactly `files`, in any order.
pub fn lists(folder: &Path, files: &[PathBuf]) -> bool {
    let now: Option<HashSet<String>> = files
        .iter()
        .map(|f| files_fingerprint([f.as_path()]))
        .collect();
    match (read_list(folder), now) {
        (Some(list), Some(now)) => {
            list.len() == now.len() && list.iter().all(|f| now.contains(&f.identity))
        }
        _ => false,
    }
}

/// Updates the store of an earlier set of `files` into `folder` (its own, left by an update
/// that stopped, or one beside it, taken over) with the files added since and without those
/// removed, when there is one; `None` when there is none to update. An error leaves `folder`
/// to be built.
pub fn update_earlier(
    files: &[PathBuf],
    folder: &Path,
    memory_budget: u64,
) -> Result<Option<Updated>, String> {
    if lists(folder, files) {
        return Ok(None);
    }
    let now = list_of(files)?;
    let now_set: HashSet<&ListedFile> = now.iter().collect();
    // Most of the dataset's files are the store's, most of the store's are still there, and
    // those it lost are deleted or changed: a store of files still there as they were is
    // another dataset's (a render of fewer of them leaves the whole one's store alone).
    let earlier = |list: &[ListedFile]| {
        let common = list.iter().filter(|f| now_set.contains(f)).count();
        common > 0
            && !(common == list.len() && common == now.len())
            && 2 * common >= now.len()
            && 2 * common >= list.len()
            && list
                .iter()
                .filter(|f| !now_set.contains(f))
                .all(ListedFile::is_gone)
    };
    // The folder's own store was meant for these files whatever share of them it holds (a
    // store built camera first from those a path sees, or one an update left unfinished).
    let own_earlier = |list: &[ListedFile]| {
        let common = list.iter().filter(|f| now_set.contains(f)).count();
        common > 0
            && common < now.len().max(list.len())
            && list
                .iter()
                .filter(|f| !now_set.contains(f))
                .all(ListedFile::is_gone)
    };
    let own = read_list(folder).filter(|list| own_earlier(list));
    let list = match own {
        Some(list) => list,
        None => match take_over(folder, &earlier)? {
            Some(list) => list,
            None => return Ok(None),
        },
    };
    let listed: HashSet<&ListedFile> = list.iter().collect();
    let added: Vec<(PathBuf, &ListedFile)> = files
        .iter()
        .zip(&now)
        .filter(|(_, f)| !listed.contains(f))
        .map(|(path, f)| (path.clone(), f))
        .collect();
    let removed: Vec<usize> = (0..list.len())
        .filter(|&i| !now_set.contains(&list[i]))
        .collect();
    let added_paths: HashSet<&str> = added.iter().map(|(_, f)| f.path()).collect();
    let files_changed = removed
        .iter()
        .filter(|&&i| added_paths.contains(list[i].path()))
        .count();
    let db = crate::sled_open::open_waiting(&sled::Config::new().path(folder.join(INDEX_FOLDER)))
        .map_err(|e| format!("opening the store in {}: {e}", folder.display()))?;
    let tree = db.open_tree("lod").map_err(|e| e.to_string())?;
    let store = LodStore::open(tree, folder.join(PAYLOAD_FILE)).map_err(|e| e.to_string())?;
    let hierarchy = store.read_hierarchy().map_err(|e| e.to_string())?;
    let listed_points: u64 = list.iter().map(|f| f.points).sum();
    if hierarchy.point_count != listed_points {
        return Err(format!(
            "the store holds {} points, its file list {listed_points}",
            hierarchy.point_count
        ));
    }
    let added_paths: Vec<PathBuf> = added.iter().map(|(path, _)| path.clone()).collect();
    // The store's files that stay, by their place in its list, are among `files`.
    let path_of: std::collections::HashMap<&ListedFile, &PathBuf> = now.iter().zip(files).collect();
    let kept = |i: usize| {
        list.get(i)
            .and_then(|f| path_of.get(f))
            .map(|p| (*p).clone())
    };
    // The store's order after the update: its remaining files, then the added ones.
    let after: Vec<ListedFile> = list
        .iter()
        .filter(|f| now_set.contains(f))
        .chain(added.iter().map(|(_, f)| *f))
        .cloned()
        .collect();
    let change = FilesChange {
        added: &added_paths,
        removed: removed.clone(),
        kept: &kept,
        files: after.iter().map(|f| f.identity.clone()).collect(),
    };
    let report = update_from_files(&store, change, folder.join("spill"), memory_budget)?;
    drop(store);
    drop(db);
    write_list(folder, &after)?;
    Ok(Some(Updated {
        report,
        files_added: added.len() - files_changed,
        files_removed: removed.len() - files_changed,
        files_changed,
    }))
}

/// Takes over the store beside `folder` whose list is `earlier` and lists the most files,
/// renaming it to `folder`; returns its list. `folder` must hold no store.
fn take_over(
    folder: &Path,
    earlier: &dyn Fn(&[ListedFile]) -> bool,
) -> Result<Option<Vec<ListedFile>>, String> {
    if folder.join(INDEX_FOLDER).exists() {
        return Ok(None);
    }
    let Some(parent) = folder.parent() else {
        return Ok(None);
    };
    let Ok(entries) = std::fs::read_dir(parent) else {
        return Ok(None);
    };
    let mut candidates: Vec<(PathBuf, Vec<ListedFile>)> = entries
        .filter_map(Result::ok)
        .map(|e| e.path())
        .filter(|path| path != folder)
        .filter_map(|path| read_list(&path).filter(|l| earlier(l)).map(|l| (path, l)))
        .collect();
    candidates.sort_by_key(|(_, list)| std::cmp::Reverse(list.len()));
    for (candidate, list) in candidates {
        let Ok(lock) = std::fs::File::open(candidate.join(LAST_USED_FILE)) else {
            continue;
        };
        let exclusive = rustix::fs::FlockOperation::NonBlockingLockExclusive;
        if rustix::fs::flock(&lock, exclusive).is_err() {
            continue;
        }
        // A folder an opening made (its lock file alone) gives way to the store.
        if folder.exists() {
            std::fs::remove_dir_all(folder)
                .map_err(|e| format!("clearing {}: {e}", folder.display()))?;
        }
        match std::fs::remove_file(candidate.join(FINISHED_FILE)) {
            Err(e) if e.kind() != std::io::ErrorKind::NotFound => {
                return Err(format!("unmarking {}: {e}", candidate.display()))
            }
            _ => {}
        }
        std::fs::rename(&candidate, folder).map_err(|e| {
            format!(
                "taking over {} as {}: {e}",
                candidate.display(),
                folder.display()
            )
        })?;
        tracing::info!(
            from = %candidate.display(),
            to = %folder.display(),
            files = list.len(),
            "taking over the store of earlier files"
        );
        return Ok(Some(list));
    }
    Ok(None)
}

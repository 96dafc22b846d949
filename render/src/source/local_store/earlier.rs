//! A local store updated instead of built anew when its files grew: a store folder is named by
//! its files, so the files of a dataset that gained a tile name a folder without a store; the
//! store of the earlier files (a folder beside it whose file list holds only files still
//! listed, at least half of them) is taken over and updated with the added files
//! ([`crate::lod::update_lod`]).
//!
//! Each local store keeps its file list, one line a file (its points, and its path, length and
//! modification time), in `files.txt`, written after a build or update finishes. The list is
//! trusted only where its points add up to the store's: an update that stopped after its
//! store switched, before the list was written, leaves a store of other points, which is then
//! used as it is or built again, never updated twice.
//!
//! Taking a store over: its folder is locked against other users (the lock every opening of a
//! store takes, `cut/store_space.rs`, exclusively and without waiting: a store in use is not
//! taken), unmarked as finished, then renamed to the new folder. An update killed part way
//! leaves the old store whole in the new folder, unfinished, for the next opening to update.

use std::collections::HashSet;
use std::path::{Path, PathBuf};

use crate::ingest::DatasetSource;
use crate::lod::source::files_fingerprint;
use crate::lod::{update_lod, LodBuildOptions, LodError, LodStore, LodUpdateReport, PointSource};

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

/// Writes the list of `files` into the store's `folder`, replacing the one there at once.
pub fn write_file_list(folder: &Path, files: &[PathBuf]) -> Result<(), String> {
    write_list(folder, &list_of(files)?)
}

fn write_list(folder: &Path, list: &[ListedFile]) -> Result<(), String> {
    let text: String = list
        .iter()
        .map(|f| format!("{}\t{}\n", f.points, f.identity))
        .collect();
    let partial = folder.join(format!("{FILE_LIST}.partial"));
    std::fs::write(&partial, text)
        .and_then(|()| std::fs::rename(&partial, folder.join(FILE_LIST)))
        .map_err(|e| format!("writing the file list in {}: {e}", folder.display()))
}

/// Whether `folder` lists exactly `files`.
pub fn lists(folder: &Path, files: &[PathBuf]) -> bool {
    let now: Option<Vec<String>> = files
        .iter()
        .map(|f| files_fingerprint([f.as_path()]))
        .collect();
    match (read_list(folder), now) {
        (Some(list), Some(now)) => list.into_iter().map(|f| f.identity).eq(now),
        _ => false,
    }
}

/// Updates the store of an earlier set of `files` into `folder` (its own, left by an update
/// that stopped, or one beside it, taken over) with the files added since, when there is
/// one; `None` when there is none to update. An error leaves `folder` to be built.
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
    let earlier = |list: &[ListedFile]| {
        !list.is_empty()
            && list.len() < now.len()
            && 2 * list.len() >= now.len()
            && list.iter().all(|f| now_set.contains(f))
    };
    let own = read_list(folder).filter(|list| earlier(list));
    let list = match own {
        Some(list) => list,
        None => match take_over(folder, &earlier)? {
            Some(list) => list,
            None => return Ok(None),
        },
    };
    let listed: HashSet<&ListedFile> = list.iter().collect();
    let added: Vec<PathBuf> = files
        .iter()
        .zip(&now)
        .filter(|(_, f)| !listed.contains(f))
        .map(|(path, _)| path.clone())
        .collect();
    let db = sled::Config::new()
        .path(folder.join(INDEX_FOLDER))
        .open()
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
    let source = DatasetSource::open(&added).map_err(|e| e.to_string())?;
    let mut options = LodBuildOptions::new(folder.join("spill"));
    options.memory_budget_bytes = memory_budget.max(options.min_memory_budget_bytes());
    let identities = now.iter().map(|f| f.identity.clone()).collect();
    let report = update_lod(&store, &source, identities, &options).map_err(|e| match e {
        LodError::CannotUpdate(reason) => reason,
        other => other.to_string(),
    })?;
    drop(store);
    drop(db);
    write_list(folder, &now)?;
    Ok(Some(Updated {
        report,
        files_added: added.len(),
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

//! A campaign that grows through the server gets its store updated, not built again. Each
//! dataset content has a store of its own (`DATA/lod/SHA256`), so a dataset composed of the
//! files of an earlier one plus a new day's tiles (or less a dropped tile) is a content
//! without a store. When its store is first needed and another content's finished store
//! differs from it by a few files (by their content hashes: at most a quarter of its files
//! added and removed), the one needing the fewest files added and removed is copied and the
//! copy updated (`lod::update_store`): the regions the changed files touch are built again,
//! then the levels above.
//!
//! The earlier store is only read: its payload (its own file, and the layers below it where it
//! was grown itself) becomes the layers of the grown store's payload, hard-linked, never copied
//! nor written again (`lod::layers`); the update appends its nodes to the grown store's own
//! file, and its small sled index is copied. Jobs rendering the earlier store go on, workers,
//! which key their node caches by the content hash, never mix the two, and removing the
//! earlier store leaves the grown one whole. A chain of growths past `lod::layers::MAX_LAYERS`
//! layers, or one whose payload is mostly dead bytes, is compacted into one file before it is
//! updated (`lod::compact`), the log saying the dead bytes it drops. The copy is made and updated in a folder of its own
//! (`SHA256.growing`), checked (the copied hierarchy holds the earlier files' points, the
//! updated one the dataset's), and only then renamed to the store's folder, where the
//! opening marks it finished: a half-updated store is never served. An update that stops
//! part way (the daemon killed) leaves its `.growing` folder, which the next attempt removes
//! before starting again. An update that is refused (a store without regions, a removed
//! file whose points cannot be told apart) leaves the store to be built whole.
//!
//! Each store built or grown here lists its files, by content hash and points, in the store's
//! order (`contents.txt`), which is how a later update names the files it removes. A store
//! built before stores listed their files is listed when the daemon starts
//! ([`list_unlisted_stores`]) from the record of a dataset of its content, only where that is
//! proven: the files' hashes in order hash to the store's name, and the store's own facts give
//! as many files, each with the points its header says where the file is still at hand, and
//! their points add up to the store's. Otherwise it stays unlisted, said in the log, and a
//! content near it has its store built whole.

use std::collections::{HashMap, HashSet};
use std::path::{Path, PathBuf};
use std::time::Instant;

use pointfarm_render::cut::{CutError, PAYLOAD_FILE};
use pointfarm_render::ingest::{update_from_files, DatasetSource, FilesChange};
use pointfarm_render::lod::compact::compact;
use pointfarm_render::lod::layers::{link_layers, needs_compaction};
use pointfarm_render::lod::{BuildProgress, LodStore, PointSource};
use pointfarm_render::source::StoreInput;
use pointfarm_render::write_whole::write_whole;

use super::{open_or_build, ReadyStore};
use crate::model::{content_sha256, Dataset, DatasetFile};

/// The list of a store's files in its folder: a line per file, `SHA256<TAB>points`.
const CONTENTS_FILE: &str = "contents.txt";
/// What `render/src/cut/stored.rs` names a store's sled index in its folder.
const INDEX_FOLDER: &str = "index";
/// What a store being grown is kept in until it is checked, beside the store's folder.
/// The files added and removed may be at most this share of a dataset's files for its store
/// to be grown: past it an update rebuilds most regions and costs about a whole build
/// (`docs/perf/lod-store-update.md`), and a whole build's store is the one exports match.
const MAX_CHANGE_SHARE: usize = 4;
const GROWING_SUFFIX: &str = ".growing";

/// How a store was made from another content's store.
#[derive(Debug, Clone, PartialEq)]
pub struct Grown {
    /// The content hash of the store it was copied from.
    pub from_sha256: String,
    pub files_added: usize,
    pub files_removed: usize,
    /// Regions built again, those started in empty parts of the cube among them.
    pub regions_rebuilt: usize,
    pub regions_kept: usize,
    pub points_added: u64,
    pub points_removed: u64,
    /// The copy, the update and the checks together.
    pub seconds: f64,
    /// The update alone (`lod::update_store`).
    pub update_seconds: f64,
    /// Bytes of the earlier store's payload the grown one holds as hard-linked layers.
    pub payload_bytes_linked: u64,
    /// Bytes of payload written to compact it, 0 where the earlier payload was only linked.
    pub payload_bytes_copied: u64,
}

/// Opens the store of `input` (the dataset `dataset_id`'s `files`, `points` in all) in
/// `folder`: grown from the nearest store of another content where there is one ([`grow`]),
/// else built whole, listing in `progress` the nodes it stores; the store's files are listed
/// after.
pub(super) fn grow_or_build(
    input: &StoreInput,
    folder: &Path,
    budget: u64,
    progress: &BuildProgress,
    files: &[DatasetFile],
    points: u64,
    dataset_id: &str,
) -> Result<ReadyStore, CutError> {
    let grown = match input {
        StoreInput::Files(_) => grow(folder, files, points, budget, dataset_id, None),
        StoreInput::Tiles(..) => None,
    };
    let mut ready = open_or_build(input, folder, budget, progress)?;
    if let StoreInput::Files(_) = input {
        list_contents(folder, files);
    }
    if let Some(grown) = grown {
        ready.build_ms = grown.seconds * 1e3;
        ready.grown = Some(grown);
    }
    Ok(ready)
}

/// One file of a store: its content hash and points.
#[derive(Debug, Clone, PartialEq, Eq)]
struct Listed {
    sha256: String,
    points: u64,
}

/// The folder a store of `folder` is grown in.
pub(super) fn growing_folder(folder: &Path) -> PathBuf {
    let mut name = folder.file_name().unwrap_or_default().to_os_string();
    name.push(GROWING_SUFFIX);
    folder.with_file_name(name)
}

fn read_contents(folder: &Path) -> Option<Vec<Listed>> {
    let text = std::fs::read_to_string(folder.join(CONTENTS_FILE)).ok()?;
    text.lines()
        .map(|line| {
            let (sha256, points) = line.split_once('\t')?;
            Some(Listed {
                sha256: sha256.to_owned(),
                points: points.parse().ok()?,
            })
        })
        .collect()
}

fn write_contents(folder: &Path, list: &[Listed]) -> Result<(), String> {
    let text: String = list
        .iter()
        .map(|f| format!("{}\t{}\n", f.sha256, f.points))
        .collect();
    write_whole(&folder.join(CONTENTS_FILE), text.as_bytes())
        .map_err(|e| format!("writing the store's file list: {e}"))
}

/// The points of each of `files`, from its header.
fn listed(files: &[&DatasetFile]) -> Result<Vec<Listed>, String> {
    files
        .iter()
        .map(|file| {
            let source =
                DatasetSource::open(std::slice::from_ref(&file.path)).map_err(|e| e.to_string())?;
            Ok(Listed {
                sha256: file.sha256.clone(),
                points: source.point_count(),
            })
        })
        .collect()
}

/// Lists `files` (the dataset's, in the order its store took them) in the store's `folder`
/// where no list is there yet, so a later content can grow from it.
pub(super) fn list_contents(folder: &Path, files: &[DatasetFile]) {
    if folder.join(CONTENTS_FILE).exists() || !unique(files.iter().map(|f| &f.sha256)) {
        return;
    }
    let list = listed(&files.iter().collect::<Vec<_>>()).and_then(|l| write_contents(folder, &l));
    if let Err(reason) = list {
        tracing::warn!(folder = %folder.display(), %reason, "the store's file list");
    }
}

/// Lists each finished store under `dir` that has no file list yet from the record of a
/// dataset of its content (`datasets`, files on the server), where the list is proven right.
pub fn list_unlisted_stores(dir: &Path, datasets: &[Dataset]) {
    for dataset in datasets.iter().filter(|d| !d.is_by_url()) {
        let folder = dir.join(&dataset.sha256);
        if folder.join(CONTENTS_FILE).exists()
            || !pointfarm_render::cut::StoredLod::is_built(&folder)
        {
            continue;
        }
        let listed = derived_contents(&folder, &dataset.files())
            .and_then(|list| write_contents(&folder, &list).map(|()| list.len()));
        match listed {
            Ok(files) => tracing::info!(dataset = %dataset.id, files,
                "listed the files of a store built before stores listed them, so it can be grown from"),
            Err(reason) => tracing::info!(dataset = %dataset.id, %reason,
                "a store built before stores listed their files stays unlisted: datasets near it \
                 have their stores built whole"),
        }
    }
}

/// What `contents.txt` of the store in `folder` holds, derived from `files` (a dataset of the
/// store's content) and the store's own facts; an error says what disproves it.
fn derived_contents(folder: &Path, files: &[DatasetFile]) -> Result<Vec<Listed>, String> {
    let name = folder.file_name().unwrap_or_default().to_string_lossy();
    if files.is_empty() || content_sha256(files) != name {
        return Err("the dataset's files are not the store's content".to_owned());
    }
    if !unique(files.iter().map(|f| &f.sha256)) {
        return Err("the dataset holds a file twice".to_owned());
    }
    let (_db, store) = open_store(folder)?;
    let regions = store
        .read_regions()
        .map_err(|e| e.to_string())?
        .ok_or("the store keeps no regions, so it cannot be updated")?;
    let facts = regions
        .file_facts
        .ok_or("the store keeps no facts of its files")?;
    let hashes: Vec<&str> = files.iter().map(|f| f.sha256.as_str()).collect();
    if facts.len() != files.len() || !(regions.files.is_empty() || regions.files == hashes) {
        return Err(format!(
            "the store holds {} files, the dataset {}",
            facts.len(),
            files.len()
        ));
    }
    let stored = store
        .read_hierarchy()
        .map_err(|e| e.to_string())?
        .point_count;
    let facts_points: u64 = facts.iter().map(|f| f.points).sum();
    if facts_points != stored {
        return Err(format!(
            "the store holds {stored} points, its files' facts {facts_points}"
        ));
    }
    let mut list = Vec::with_capacity(files.len());
    for (file, facts) in files.iter().zip(&facts) {
        // A file still at hand as recorded has its points checked against the store's facts.
        let at_hand = std::fs::metadata(&file.path).is_ok_and(|m| m.len() == file.size_bytes);
        if at_hand {
            let header = listed(&[file])?;
            if header[0].points != facts.points {
                return Err(format!(
                    "{} holds {} points, the store's facts of it {}",
                    file.name, header[0].points, facts.points
                ));
            }
        }
        list.push(Listed {
            sha256: file.sha256.clone(),
            points: facts.points,
        });
    }
    Ok(list)
}

fn unique<'a>(hashes: impl Iterator<Item = &'a String>) -> bool {
    let mut seen = HashSet::new();
    hashes.into_iter().all(|h| seen.insert(h))
}

/// A finished store beside `folder` to grow `files` from: one from which `files` differ by
/// at most a quarter of their count added and removed (and not none: a store of the same
/// files is built whole), the fewest, the most shared on a tie.
fn nearest(folder: &Path, files: &[DatasetFile]) -> Option<(PathBuf, Vec<Listed>)> {
    let wanted: HashSet<&str> = files.iter().map(|f| f.sha256.as_str()).collect();
    let parent = folder.parent()?;
    let entries = std::fs::read_dir(parent).ok()?;
    let mut best: Option<(usize, usize, PathBuf, Vec<Listed>)> = None;
    for path in entries.filter_map(Result::ok).map(|e| e.path()) {
        let is_growing = path.to_string_lossy().ends_with(GROWING_SUFFIX);
        if path == folder || is_growing || !pointfarm_render::cut::StoredLod::is_built(&path) {
            continue;
        }
        let Some(list) = read_contents(&path) else {
            continue;
        };
        if !unique(list.iter().map(|f| &f.sha256)) {
            continue;
        }
        let common = list
            .iter()
            .filter(|f| wanted.contains(f.sha256.as_str()))
            .count();
        let change = (wanted.len() - common) + (list.len() - common);
        let few = change > 0 && change * MAX_CHANGE_SHARE <= wanted.len();
        if common == 0 || !few {
            continue;
        }
        let better = best
            .as_ref()
            .is_none_or(|(c, shared, ..)| change < *c || (change == *c && common > *shared));
        if better {
            best = Some((change, common, path, list));
        }
    }
    best.map(|(_, _, path, list)| (path, list))
}

/// Makes the store of `files` (`points` in all) in `folder`, which holds none, from the
/// nearest finished store of another content, or from the finished store in `from` whatever
/// share of files it lacks (a camera first store of some of the dataset's files, built within
/// the cube of all of them): copied and updated beside it, checked, then renamed into place.
/// `None` when there is no such store, or the update was refused or failed (said in the log):
/// the store is then built whole.
pub(super) fn grow(
    folder: &Path,
    files: &[DatasetFile],
    points: u64,
    memory_budget: u64,
    dataset_id: &str,
    from: Option<&Path>,
) -> Option<Grown> {
    let growing = growing_folder(folder);
    if growing.exists() {
        // Left by an update that stopped part way: started again from a fresh copy.
        tracing::info!(dataset = %dataset_id, "removing the store update a stopped daemon left");
        if let Err(error) = std::fs::remove_dir_all(&growing) {
            tracing::warn!(%error, folder = %growing.display(), "removing an unfinished update");
            return None;
        }
    }
    if folder.exists() || !unique(files.iter().map(|f| &f.sha256)) {
        return None;
    }
    let (from, earlier) = match from {
        Some(from) => (from.to_path_buf(), read_contents(from)?),
        None => nearest(folder, files)?,
    };
    let from_sha256 = from.file_name()?.to_string_lossy().into_owned();
    let from_id = crate::model::dataset_id(&from_sha256);
    tracing::info!(dataset = %dataset_id, from = %from_id,
        "updating a copy of the store of dataset {from_id} instead of building the store whole");
    let started = Instant::now();
    let grown = copy_and_update(&from, &growing, &earlier, files, points, memory_budget).and_then(
        |mut grown| {
            let _ = std::fs::remove_dir_all(growing.join("spill"));
            std::fs::rename(&growing, folder)
                .map_err(|e| format!("moving the updated store into place: {e}"))?;
            grown.from_sha256 = from_sha256.clone();
            grown.seconds = started.elapsed().as_secs_f64();
            Ok(grown)
        },
    );
    match grown {
        Ok(grown) => {
            tracing::info!(dataset = %dataset_id, from = %from_id,
                files_added = grown.files_added, files_removed = grown.files_removed,
                regions_rebuilt = grown.regions_rebuilt, regions_kept = grown.regions_kept,
                points_added = grown.points_added, points_removed = grown.points_removed,
                seconds = format!("{:.2}", grown.seconds),
                update_seconds = format!("{:.2}", grown.update_seconds),
                payload_bytes_linked = grown.payload_bytes_linked,
                payload_bytes_copied = grown.payload_bytes_copied,
                "updated the store of {dataset_id} from the store of dataset {from_id}: {} files \
                 added, {} removed, {} regions rebuilt",
                grown.files_added, grown.files_removed, grown.regions_rebuilt);
            Some(grown)
        }
        Err(reason) => {
            tracing::info!(dataset = %dataset_id, from = %from_id, %reason,
                "the store is built whole: the earlier store could not be updated");
            let _ = std::fs::remove_dir_all(&growing);
            None
        }
    }
}

/// Copies the store in `from`, of the files `earlier`, into `into` and applies the change to
/// `files`; the copy is checked against `earlier`'s points before, and the update against
/// `points` after.
fn copy_and_update(
    from: &Path,
    into: &Path,
    earlier: &[Listed],
    files: &[DatasetFile],
    points: u64,
    memory_budget: u64,
) -> Result<Grown, String> {
    std::fs::create_dir_all(into).map_err(|e| format!("making {}: {e}", into.display()))?;
    let copying = Instant::now();
    copy_folder(&from.join(INDEX_FOLDER), &into.join(INDEX_FOLDER))?;
    let linked = link_layers(&from.join(PAYLOAD_FILE), &into.join(PAYLOAD_FILE))
        .map_err(|e| format!("linking the earlier store's payload: {e}"))?;
    let (db, store) = open_store(into)?;
    let copied = store.read_hierarchy().map_err(|e| e.to_string())?;
    let layers = store.payload_files() - 1;
    let live = copied.payload_bytes() + region_root_bytes(&store)?;
    let (mut payload_bytes_linked, mut payload_bytes_copied) = (linked, 0);
    if needs_compaction(layers, linked, live) {
        let compacted = compact(&store).map_err(|e| format!("compacting the payload: {e}"))?;
        (payload_bytes_linked, payload_bytes_copied) = (0, compacted.bytes_after);
        // The dead bytes leave the disk with the last store that links the layers.
        let freed_bytes = compacted.bytes_before.saturating_sub(compacted.bytes_after);
        tracing::info!(
            layers,
            payload_bytes = linked,
            live_bytes = live,
            compacted_bytes = compacted.bytes_after,
            freed_bytes,
            "compacted the earlier store's payload into one file to update: {freed_bytes} bytes \
             no node lists dropped, {layers} layers no longer linked"
        );
    }
    tracing::info!(
        seconds = format!("{:.2}", copying.elapsed().as_secs_f64()),
        payload_bytes_linked,
        payload_bytes_copied,
        layers = store.payload_files() - 1,
        "copied the earlier store to update"
    );
    let listed_points: u64 = earlier.iter().map(|f| f.points).sum();
    if copied.point_count != listed_points {
        return Err(format!(
            "the earlier store holds {} points, its file list {listed_points}",
            copied.point_count
        ));
    }
    let now: HashMap<&str, &DatasetFile> = files.iter().map(|f| (f.sha256.as_str(), f)).collect();
    let had: HashSet<&str> = earlier.iter().map(|f| f.sha256.as_str()).collect();
    let removed: Vec<usize> = (0..earlier.len())
        .filter(|&i| !now.contains_key(earlier[i].sha256.as_str()))
        .collect();
    let added: Vec<&DatasetFile> = files
        .iter()
        .filter(|f| !had.contains(f.sha256.as_str()))
        .collect();
    let added_paths: Vec<PathBuf> = added.iter().map(|f| f.path.clone()).collect();
    // The store's files that stay, by their place in its list, are the dataset's.
    let kept = |i: usize| {
        earlier
            .get(i)
            .and_then(|f| now.get(f.sha256.as_str()))
            .map(|f| f.path.clone())
    };
    // The store's order after the update: its remaining files, then the added ones.
    let mut after: Vec<Listed> = earlier
        .iter()
        .filter(|f| now.contains_key(f.sha256.as_str()))
        .cloned()
        .collect();
    after.extend(listed(&added)?);
    let change = FilesChange {
        added: &added_paths,
        removed: removed.clone(),
        kept: &kept,
        files: after.iter().map(|f| f.sha256.clone()).collect(),
    };
    let report = update_from_files(&store, change, into.join("spill"), memory_budget)?;
    let stored = store.read_hierarchy().map_err(|e| e.to_string())?;
    if stored.point_count != points || report.hierarchy.point_count != points {
        return Err(format!(
            "the updated store holds {} points, the dataset's files {points}",
            stored.point_count
        ));
    }
    drop(store);
    db.flush().map_err(|e| e.to_string())?;
    drop(db);
    write_contents(into, &after)?;
    Ok(Grown {
        from_sha256: String::new(),
        files_added: added.len(),
        files_removed: removed.len(),
        regions_rebuilt: report.regions_rebuilt + report.regions_added,
        regions_kept: report.regions_kept,
        points_added: report.points_added,
        points_removed: report.points_removed,
        seconds: 0.0,
        update_seconds: report.seconds,
        payload_bytes_linked,
        payload_bytes_copied,
    })
}

/// The store in `folder`: its sled index (kept open while the store is) and payload file.
fn open_store(folder: &Path) -> Result<(sled::Db, LodStore), String> {
    let db = sled::Config::new()
        .path(folder.join(INDEX_FOLDER))
        .open()
        .map_err(|e| format!("opening the store in {}: {e}", folder.display()))?;
    let tree = db.open_tree("lod").map_err(|e| e.to_string())?;
    let store = LodStore::open(tree, folder.join(PAYLOAD_FILE)).map_err(|e| e.to_string())?;
    Ok((db, store))
}

/// Copies the files of folder `from` (a sled index: small, written in place) into `into`.
fn copy_folder(from: &Path, into: &Path) -> Result<(), String> {
    std::fs::create_dir_all(into).map_err(|e| format!("making {}: {e}", into.display()))?;
    let entries =
        std::fs::read_dir(from).map_err(|e| format!("reading {}: {e}", from.display()))?;
    for entry in entries {
        let entry = entry.map_err(|e| format!("reading {}: {e}", from.display()))?;
        let kind = entry.file_type().map_err(|e| e.to_string())?;
        let target = into.join(entry.file_name());
        if kind.is_dir() {
            copy_folder(&entry.path(), &target)?;
        } else if kind.is_file() {
            std::fs::copy(entry.path(), &target)
                .map_err(|e| format!("copying {}: {e}", entry.path().display()))?;
        }
    }
    Ok(())
}

/// Bytes of the regions' kept roots in `store`'s payload: live beside its nodes' records.
fn region_root_bytes(store: &LodStore) -> Result<u64, String> {
    let regions = store.read_regions().map_err(|e| e.to_string())?;
    Ok(regions.map_or(0, |r| {
        r.regions
            .iter()
            .filter_map(|region| region.root.map(|n| n.stored_bytes()))
            .sum()
    }))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn file(sha256: &str) -> DatasetFile {
        DatasetFile {
            name: format!("{sha256}.las"),
            path: PathBuf::from(format!("/nowhere/{sha256}.las")),
            size_bytes: 1,
            sha256: sha256.to_owned(),
        }
    }

    /// A finished-looking store folder listing `hashes`.
    fn store(dir: &Path, name: &str, hashes: &[&str]) {
        let folder = dir.join(name);
        std::fs::create_dir_all(&folder).expect("folder");
        let list: Vec<Listed> = hashes
            .iter()
            .map(|h| Listed {
                sha256: (*h).to_owned(),
                points: 1,
            })
            .collect();
        write_contents(&folder, &list).expect("list");
        let finished = r#"{"points":1,"min":[0,0,0],"max":[1,1,1]}"#;
        std::fs::write(folder.join("finished.json"), finished).expect("marker");
    }

    #[test]
    fn the_nearest_store_needs_the_fewest_files_added_and_removed() {
        let dir = tempfile::tempdir().expect("tempdir");
        store(dir.path(), "four", &["a", "b", "c", "d"]);
        store(dir.path(), "three", &["a", "b", "c"]);
        store(dir.path(), "other", &["x", "y", "z"]);
        store(dir.path(), "one", &["a"]);
        let wanted: Vec<DatasetFile> = ["a", "b", "c", "e"].iter().map(|h| file(h)).collect();
        let (path, list) = nearest(&dir.path().join("new"), &wanted).expect("a store");
        // three: one added; four: one added and one removed.
        assert_eq!(path.file_name().expect("a name"), "three");
        assert_eq!(list.len(), 3);
        let wanted: Vec<DatasetFile> = ["x", "q", "r", "s", "t"].iter().map(|h| file(h)).collect();
        assert!(
            nearest(&dir.path().join("new"), &wanted).is_none(),
            "too few shared"
        );
    }

    #[test]
    fn a_store_of_the_same_files_or_too_far_is_no_candidate() {
        let dir = tempfile::tempdir().expect("tempdir");
        store(dir.path(), "same", &["a", "b", "c", "d"]);
        store(dir.path(), "twice", &["a", "b"]);
        let wanted =
            |hashes: &[&str]| -> Vec<DatasetFile> { hashes.iter().map(|h| file(h)).collect() };
        let new = dir.path().join("new");
        assert!(
            nearest(&new, &wanted(&["a", "b", "c", "d"])).is_none(),
            "nothing to change"
        );
        let (path, _) = nearest(&new, &wanted(&["a", "b", "c", "d", "e"])).expect("one added");
        assert_eq!(path.file_name().expect("a name"), "same");
        assert!(
            nearest(&new, &wanted(&["a", "b", "c"])).is_none(),
            "one of three is more than a quarter"
        );
        // Two of four removed is more than a quarter.
        assert!(nearest(&new, &wanted(&["c", "d"])).is_none());
    }

    /// A LAS file of `points` of the sample scene at `path`, recorded as `sha256`.
    fn las(path: &Path, points: usize, seed: u64, sha256: &str) -> DatasetFile {
        let cloud = pointfarm_render::sample::sample_scene(points, seed);
        let options = pointfarm_render::ingest::LasWriteOptions::default();
        pointfarm_render::ingest::write_las(path, &cloud, &options).expect("a tile");
        DatasetFile {
            name: "tile.las".to_owned(),
            path: path.to_owned(),
            size_bytes: std::fs::metadata(path).expect("written").len(),
            sha256: sha256.to_owned(),
        }
    }

    #[test]
    fn a_store_without_a_file_list_is_listed_only_where_its_files_prove_it() {
        let dir = tempfile::tempdir().expect("tempdir");
        let files = vec![
            las(&dir.path().join("a.las"), 3_000, 1, "a"),
            las(&dir.path().join("b.las"), 2_000, 2, "b"),
        ];
        let folder = dir.path().join("lod").join(content_sha256(&files));
        let paths: Vec<PathBuf> = files.iter().map(|f| f.path.clone()).collect();
        let built = pointfarm_render::cut::StoredLod::open_or_build(
            &paths,
            &folder,
            64 << 20,
            None,
            &mut |_| {},
        )
        .expect("a store");
        drop(built);

        // In another order the files are another content.
        let swapped = vec![files[1].clone(), files[0].clone()];
        let error = derived_contents(&folder, &swapped).expect_err("another content");
        assert!(error.contains("not the store's content"), "{error}");
        // A file at hand whose header gives other points than the store's facts disproves it.
        let mut changed = files.clone();
        changed[1] = las(&dir.path().join("b2.las"), 2_500, 2, "b");
        let error = derived_contents(&folder, &changed).expect_err("other points");
        assert!(error.contains("the store's facts of it 2000"), "{error}");

        let mut dataset = crate::model::Dataset {
            id: "ds-ab".to_owned(),
            name: "tiles".to_owned(),
            size_bytes: 0,
            sha256: content_sha256(&files),
            path: files[0].path.clone(),
            files: files.clone(),
            created_unix_ms: 0,
            remote: None,
            tiles: Vec::new(),
        };
        list_unlisted_stores(&dir.path().join("lod"), std::slice::from_ref(&dataset));
        let listed = read_contents(&folder).expect("listed");
        let expected = [("a", 3_000), ("b", 2_000)].map(|(sha256, points)| Listed {
            sha256: sha256.to_owned(),
            points,
        });
        assert_eq!(listed, expected);
        // A file gone from its path is taken at the store's word, the content being proven.
        std::fs::remove_file(folder.join(CONTENTS_FILE)).expect("unlist");
        std::fs::remove_file(&files[0].path).expect("remove a file");
        dataset.files[0].size_bytes += 1;
        assert_eq!(
            derived_contents(&folder, &dataset.files).expect("listed"),
            expected
        );
    }

    #[test]
    fn a_store_being_grown_or_unfinished_is_no_candidate() {
        let dir = tempfile::tempdir().expect("tempdir");
        store(dir.path(), "half", &["a", "b"]);
        std::fs::remove_file(dir.path().join("half/finished.json")).expect("unmark");
        store(dir.path(), "x.growing", &["a", "b"]);
        let wanted: Vec<DatasetFile> = ["a", "b", "c"].iter().map(|h| file(h)).collect();
        assert!(nearest(&dir.path().join("new"), &wanted).is_none());
        assert_eq!(
            growing_folder(&dir.path().join("abc")),
            dir.path().join("abc.growing")
        );
    }
}

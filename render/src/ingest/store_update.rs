//! A level-of-detail store updated from its dataset's files on disk: the files it gains
//! opened as one source, and those that stay reopened by their place in the store's list
//! where the update reads them again.

use std::path::PathBuf;

use super::DatasetSource;
use crate::lod::update::update_within;
use crate::lod::{LodError, LodStore, LodUpdateReport, PointSource, StoreChange};

/// What changed in a store's files, as paths on disk.
pub struct FilesChange<'a> {
    /// The files the store gains, in the order it takes them (a changed file as it is now).
    pub added: &'a [PathBuf],
    /// The store's files that are gone (a changed file as it was), by their place in its list.
    pub removed: Vec<usize>,
    /// Where the store's file at a place in its list is now, if it stays.
    pub kept: &'a (dyn Fn(usize) -> Option<PathBuf> + Sync),
    /// One entry per file after the update: the remaining ones in the store's order, then the
    /// added ones.
    pub files: Vec<String>,
}

/// Updates `store` by `change` within `memory_budget`, spilling under `spill_dir`.
pub fn update_from_files(
    store: &LodStore,
    change: FilesChange<'_>,
    spill_dir: PathBuf,
    memory_budget: u64,
) -> Result<LodUpdateReport, String> {
    let added = match change.added.is_empty() {
        true => None,
        false => Some(DatasetSource::open(change.added).map_err(|e| e.to_string())?),
    };
    let kept = change.kept;
    let reopen = |places: &[usize]| -> Result<Box<dyn PointSource>, LodError> {
        let paths: Vec<PathBuf> = places.iter().filter_map(|&i| kept(i)).collect();
        let source = DatasetSource::open(&paths).map_err(|e| LodError::Source(e.to_string()))?;
        Ok(Box::new(source))
    };
    let change = StoreChange {
        added: added.as_ref().map(|s| s as &dyn PointSource),
        removed: change.removed,
        reopen: &reopen,
        files: change.files,
    };
    update_within(store, &change, spill_dir, memory_budget)
}

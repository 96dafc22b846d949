//! The level-of-detail store of a local dataset: kept in the cache folder under a name made
//! of its files (paths, sizes, modification times), so later renders of the same files open
//! it and a changed file gets a new one.

use std::cell::RefCell;
use std::path::PathBuf;
use std::sync::mpsc::Receiver;
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::UNIX_EPOCH;

use anyhow::{Context, Result};
use pointfarm_render::cut::StoredLod;
use pointfarm_render::lod::BuildProgress;
use sha2::{Digest, Sha256};

/// The name of a dataset's store: a digest of each file's absolute path, size and
/// modification time.
fn store_name(files: &[PathBuf]) -> Result<String> {
    let mut digest = Sha256::new();
    for file in files {
        let path =
            std::fs::canonicalize(file).with_context(|| format!("reading {}", file.display()))?;
        let meta =
            std::fs::metadata(&path).with_context(|| format!("reading {}", path.display()))?;
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

/// Where local renders keep their stores, and the most disk they may take together.
#[derive(Debug, Clone)]
pub struct StoreCache {
    pub dir: PathBuf,
    pub size_bytes: Option<u64>,
}

impl StoreCache {
    /// The folder of the store of `files`.
    pub fn folder(&self, files: &[PathBuf]) -> Result<PathBuf> {
        Ok(self.dir.join("lod").join(store_name(files)?))
    }
}

/// Opens the store of `files` in `cache`, building it first (with a spinner) when there is
/// none, within `memory_budget` bytes of build buffers.
pub fn open_or_build(
    files: &[PathBuf],
    cache: &StoreCache,
    memory_budget: u64,
    say: &dyn Fn(String),
) -> Result<StoredLod> {
    let folder = cache.folder(files)?;
    let spinner = RefCell::new(None);
    let budget = cache.size_bytes;
    let opened = StoredLod::open_or_build(files, &folder, memory_budget, budget, &mut |points| {
        *spinner.borrow_mut() = Some(crate::progress::spinner(format!(
            "building levels of detail of {points} points (once; kept in {})",
            folder.display()
        )));
    });
    if let Some(spinner) = spinner.take() {
        spinner.finish_and_clear();
    }
    let opened = opened.with_context(|| format!("the store in {}", folder.display()))?;
    say_built(&opened, say);
    Ok(opened)
}

/// Says how the store was built, when this opening built it.
pub fn say_built(opened: &StoredLod, say: &dyn Fn(String)) {
    if let Some((report, seconds)) = &opened.built {
        say(format!(
            "levels of detail: {} nodes built in {seconds:.1} s, {:.2} M points/s",
            report.hierarchy.nodes().len(),
            opened.dataset.point_count() as f64 / seconds / 1e6
        ));
    }
}

/// Builds the store of `files` in `folder` (see [`StoreCache::folder`]) on a thread of its
/// own once `start` is sent to or dropped, without a spinner: the preview rendered meanwhile
/// has the terminal, and draws the nodes `progress` lists as they are stored.
pub fn build_in_background(
    files: Vec<PathBuf>,
    folder: PathBuf,
    cache: &StoreCache,
    memory_budget: u64,
    start: Receiver<()>,
    progress: Arc<BuildProgress>,
) -> Result<JoinHandle<Result<StoredLod>>> {
    let budget = cache.size_bytes;
    std::thread::Builder::new()
        .name("lod-build".into())
        .spawn(move || {
            // Sent or dropped: either way the build goes on.
            let _ = start.recv();
            StoredLod::open_or_build_watched(
                &files,
                &folder,
                memory_budget,
                budget,
                &mut |points| {
                    tracing::info!(
                        points,
                        folder = %folder.display(),
                        "building levels of detail behind a preview"
                    );
                },
                &progress,
            )
            .with_context(|| format!("the store in {}", folder.display()))
        })
        .context("starting the levels of detail's build")
}

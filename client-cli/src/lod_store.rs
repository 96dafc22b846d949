//! The level-of-detail store of a local dataset: built once into the cache folder, named by
//! its files (paths, sizes, modification times), and opened again by later renders of the
//! same files.

use std::path::{Path, PathBuf};
use std::time::{Instant, UNIX_EPOCH};

use anyhow::{Context, Result};
use pointfarm_render::cut::LodDataset;
use pointfarm_render::ingest::DatasetSource;
use pointfarm_render::lod::{build_lod, LodBuildOptions, LodError, LodStore, PointSource};
use sha2::{Digest, Sha256};

/// The cache folder when neither `--cache-dir` nor `POINTFARM_CACHE_DIR` names one.
pub fn default_cache_dir() -> PathBuf {
    let base = std::env::var_os("XDG_CACHE_HOME")
        .map(PathBuf::from)
        .or_else(|| std::env::var_os("HOME").map(|home| PathBuf::from(home).join(".cache")))
        .unwrap_or_else(std::env::temp_dir);
    base.join("pointfarm")
}

/// A dataset's store, open; the database stays open as long as this does.
pub struct LocalLod {
    pub dataset: LodDataset,
    pub folder: PathBuf,
    _db: sled::Db,
}

/// The name of a dataset's store: a digest of each file's absolute path, size and
/// modification time, so a changed file gets a new store.
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

/// Opens the store of `files` under `cache_dir`, building it first when there is none (or
/// an unfinished one), within `memory_budget` bytes of build buffers.
pub fn open_or_build(
    files: &[PathBuf],
    cache_dir: &Path,
    memory_budget: u64,
    say: &dyn Fn(String),
) -> Result<LocalLod> {
    let source = DatasetSource::open(files)?;
    let folder = cache_dir.join("lod").join(store_name(files)?);
    std::fs::create_dir_all(&folder).with_context(|| format!("creating {}", folder.display()))?;
    let db = sled::Config::new()
        .path(folder.join("index"))
        .cache_capacity(16 << 20)
        .open()
        .with_context(|| format!("opening the store in {}", folder.display()))?;
    let store = LodStore::open(db.open_tree("lod")?, folder.join("nodes.bin"))?;
    let current = match store.read_hierarchy() {
        Ok(hierarchy) => hierarchy.point_count == source.point_count(),
        Err(LodError::MissingHierarchy) => false,
        // A damaged store is a cache: built again, not trusted.
        Err(error) => {
            tracing::warn!(%error, folder = %folder.display(), "rebuilding a damaged store");
            false
        }
    };
    if !current {
        let started = Instant::now();
        let spinner = crate::render::spinner(format!(
            "building levels of detail of {} points (once; kept in {})",
            source.point_count(),
            folder.display()
        ));
        let mut options = LodBuildOptions::new(folder.join("spill"));
        options.memory_budget_bytes = memory_budget.max(options.min_memory_budget_bytes());
        let report = build_lod(&source, &store, &options);
        spinner.finish_and_clear();
        let report =
            report.with_context(|| format!("building the store in {}", folder.display()))?;
        let seconds = started.elapsed().as_secs_f64();
        say(format!(
            "levels of detail: {} nodes built in {seconds:.1} s, {:.2} M points/s",
            report.hierarchy.nodes().len(),
            source.point_count() as f64 / seconds / 1e6
        ));
    }
    let dataset = LodDataset::open(store, source.bounds())?;
    Ok(LocalLod {
        dataset,
        folder,
        _db: db,
    })
}

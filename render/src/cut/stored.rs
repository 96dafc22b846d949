//! `StoredLod`: a dataset's level-of-detail store in a folder of its own (a sled index
//! holding the hierarchy, and the node payload file), built from the dataset's files when the
//! folder has no finished store, then opened for rendering. The CLI keeps one per set of
//! local files, a worker one per dataset it renders.

use std::path::{Path, PathBuf};
use std::time::Instant;

use super::{CutError, LodDataset};
use crate::cloud::WorldBounds;
use crate::ingest::DatasetSource;
use crate::lod::disk::build_disk_bytes;
use crate::lod::{build_lod, LodBuildOptions, LodBuildReport, LodError, LodStore, PointSource};

/// sled's page cache for the index: it holds one small hierarchy record.
const INDEX_CACHE_BYTES: u64 = 16 << 20;

/// An opened store; its database stays open as long as this does.
pub struct StoredLod {
    pub dataset: LodDataset,
    pub folder: PathBuf,
    /// The build this opening ran, and how long it took, when there was no finished store.
    pub built: Option<(LodBuildReport, f64)>,
    _db: sled::Db,
}

impl StoredLod {
    /// Whether `folder` holds a finished store, which opens without the dataset's files.
    pub fn is_built(folder: &Path) -> bool {
        read_finished(folder).is_some()
    }

    /// Opens the store in `folder`, building it from `files` first when it has none, an
    /// unfinished or a damaged one, or one of another point count, within `memory_budget`
    /// bytes of build buffers. A build that would not fit the disk's free space or
    /// `disk_budget` is refused before it starts. `on_build` is told the points before a
    /// build starts.
    pub fn open_or_build(
        files: &[PathBuf],
        folder: &Path,
        memory_budget: u64,
        disk_budget: Option<u64>,
        on_build: &mut dyn FnMut(u64),
    ) -> Result<Self, CutError> {
        if files.is_empty() {
            return Self::open_finished(folder);
        }
        let source = DatasetSource::open(files)?;
        std::fs::create_dir_all(folder)
            .map_err(|e| CutError::Cache(format!("creating {}: {e}", folder.display())))?;
        let (db, store) = open_index(folder)?;
        let current = match store.read_hierarchy() {
            Ok(hierarchy) => hierarchy.point_count == source.point_count(),
            Err(LodError::MissingHierarchy) => false,
            // A damaged store is a cache: built again, not trusted.
            Err(error) => {
                tracing::warn!(%error, folder = %folder.display(), "rebuilding a damaged store");
                false
            }
        };
        let mut built = None;
        if !current {
            let _ = std::fs::remove_file(folder.join(FINISHED_FILE));
            check_disk(folder, source.point_count(), disk_budget)?;
            on_build(source.point_count());
            let started = Instant::now();
            let mut options = LodBuildOptions::new(folder.join("spill"));
            options.memory_budget_bytes = memory_budget.max(options.min_memory_budget_bytes());
            let report = build_lod(&source, &store, &options)?;
            let seconds = started.elapsed().as_secs_f64();
            tracing::info!(
                folder = %folder.display(),
                points = source.point_count(),
                nodes = report.hierarchy.nodes().len(),
                seconds = format!("{seconds:.1}"),
                "levels of detail built"
            );
            built = Some((report, seconds));
        }
        write_finished(folder, source.point_count(), &source.bounds())?;
        let dataset = LodDataset::open(store, source.bounds())?;
        Ok(Self {
            dataset,
            folder: folder.to_owned(),
            built,
            _db: db,
        })
    }
}

/// The file that marks a finished store: its points and the bounds of its files, so it opens
/// without them (a worker's restart).
const FINISHED_FILE: &str = "finished.json";

impl StoredLod {
    /// Opens a finished store from its folder alone.
    fn open_finished(folder: &Path) -> Result<Self, CutError> {
        let missing = || {
            CutError::Cache(format!(
                "{} holds no finished store, and no files were given to build one",
                folder.display()
            ))
        };
        let (points, bounds) = read_finished(folder).ok_or_else(missing)?;
        let (db, store) = open_index(folder)?;
        let dataset = LodDataset::open(store, bounds)?;
        if dataset.point_count() != points {
            return Err(CutError::Cache(format!(
                "the store in {} holds {} points, its marker says {points}",
                folder.display(),
                dataset.point_count()
            )));
        }
        Ok(Self {
            dataset,
            folder: folder.to_owned(),
            built: None,
            _db: db,
        })
    }
}

fn write_finished(folder: &Path, points: u64, bounds: &WorldBounds) -> Result<(), CutError> {
    let text = serde_json::json!({
        "points": points,
        "min": bounds.min.to_array(),
        "max": bounds.max.to_array(),
    })
    .to_string();
    let partial = folder.join(format!("{FINISHED_FILE}.partial"));
    let write = std::fs::write(&partial, text)
        .and_then(|()| std::fs::rename(&partial, folder.join(FINISHED_FILE)));
    write.map_err(|e| {
        CutError::Cache(format!(
            "marking the store in {} finished: {e}",
            folder.display()
        ))
    })
}

fn read_finished(folder: &Path) -> Option<(u64, WorldBounds)> {
    let text = std::fs::read_to_string(folder.join(FINISHED_FILE)).ok()?;
    let value: serde_json::Value = serde_json::from_str(&text).ok()?;
    let vector = |name: &str| -> Option<glam::DVec3> {
        let v = value[name].as_array()?;
        let c: Vec<f64> = v.iter().filter_map(serde_json::Value::as_f64).collect();
        (c.len() == 3 && c.iter().all(|x| x.is_finite()))
            .then(|| glam::DVec3::new(c[0], c[1], c[2]))
    };
    let bounds = WorldBounds {
        min: vector("min")?,
        max: vector("max")?,
    };
    Some((value["points"].as_u64()?, bounds))
}

/// The store's sled index (holding its hierarchy) and payload file in `folder`.
fn open_index(folder: &Path) -> Result<(sled::Db, LodStore), CutError> {
    let db = sled::Config::new()
        .path(folder.join("index"))
        .cache_capacity(INDEX_CACHE_BYTES)
        .open()
        .map_err(|e| CutError::Cache(format!("opening the store in {}: {e}", folder.display())))?;
    let tree = db.open_tree("lod").map_err(LodError::from)?;
    let store = LodStore::open(tree, folder.join("nodes.bin"))?;
    Ok((db, store))
}

/// Refuses a build whose disk need exceeds the free space under `folder` or `budget`.
fn check_disk(folder: &Path, points: u64, budget: Option<u64>) -> Result<(), CutError> {
    let needed = build_disk_bytes(points, true);
    let mib = |bytes: u64| bytes >> 20;
    let refuse = |limit: String| CutError::DiskTooSmall {
        points,
        needed_mib: mib(needed),
        folder: folder.to_owned(),
        limit,
    };
    if let Some(budget) = budget.filter(|&b| needed > b) {
        return Err(refuse(format!(
            "more than its budget of {} MiB",
            mib(budget)
        )));
    }
    if let Ok(stat) = rustix::fs::statvfs(folder) {
        let free = stat.f_bavail.saturating_mul(stat.f_frsize);
        if needed > free {
            return Err(refuse(format!(
                "more than the {} MiB free there",
                mib(free)
            )));
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_build_larger_than_its_disk_budget_is_refused_before_it_starts() {
        let dir = tempfile::tempdir().expect("tempdir");
        let error = check_disk(dir.path(), 10_000_000, Some(100 << 20)).expect_err("refused");
        assert!(matches!(error, CutError::DiskTooSmall { .. }));
        assert!(error.to_string().contains("budget of 100 MiB"), "{error}");
        // More than any disk has free.
        let error = check_disk(dir.path(), u64::MAX / 64, None).expect_err("refused");
        assert!(error.to_string().contains("free there"), "{error}");
        assert!(check_disk(dir.path(), 1_000, None).is_ok());
    }

    #[test]
    fn a_finished_store_opens_without_its_files() {
        use crate::ingest::{write_las, LasWriteOptions};
        let dir = tempfile::tempdir().expect("tempdir");
        let file = dir.path().join("scene.las");
        let scene = crate::sample::sample_scene(5_000, 2);
        write_las(&file, &scene, &LasWriteOptions::default()).expect("write");
        let folder = dir.path().join("store");
        assert!(!StoredLod::is_built(&folder));
        let first =
            StoredLod::open_or_build(&[file], &folder, 64 << 20, None, &mut |_| {}).expect("built");
        assert!(first.built.is_some());
        let (bounds, points) = (first.dataset.bounds(), first.dataset.point_count());
        drop(first);
        assert!(StoredLod::is_built(&folder));
        let again = StoredLod::open_or_build(&[], &folder, 64 << 20, None, &mut |_| {})
            .expect("opened without files");
        assert!(again.built.is_none());
        assert_eq!(
            (again.dataset.bounds(), again.dataset.point_count()),
            (bounds, points)
        );
        drop(again);
        let empty = dir.path().join("empty");
        let error = StoredLod::open_or_build(&[], &empty, 64 << 20, None, &mut |_| {})
            .err()
            .expect("nothing to open");
        assert!(error.to_string().contains("no finished store"), "{error}");
    }
}

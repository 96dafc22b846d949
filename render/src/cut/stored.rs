//! `StoredLod`: a dataset's level-of-detail store in a folder of its own (a sled index
//! holding the hierarchy, and the node payload file), built from the dataset's files when the
//! folder has no finished store, then opened for rendering. The CLI keeps one per set of
//! local files, a worker one per dataset it renders; the stores beside one another share a
//! disk budget (`store_space.rs`).

use std::path::{Path, PathBuf};
use std::time::Instant;

use super::store_space::{make_space, InUse};
use super::{CutError, LodDataset};
use crate::cloud::WorldBounds;
use crate::ingest::DatasetSource;
use crate::lod::disk::{build_disk_bytes, spill_record_bytes};
use crate::lod::{
    build_lod_watched, BuildProgress, LodBuildOptions, LodBuildReport, LodError, LodStore,
    PointSource,
};

/// The store's payload file in its folder, which `serve --store-url` publishes as it is.
pub const PAYLOAD_FILE: &str = "nodes.bin";

/// sled's page cache for the index: it holds one small hierarchy record.
const INDEX_CACHE_BYTES: u64 = 16 << 20;

/// Where a store is kept and what its build may take: `memory_budget` bytes of build
/// buffers, `disk_budget` for the stores beside it in its folder's parent; `on_build` is told
/// the points before a build starts, and `progress` lists the nodes it stores.
pub struct StoreBuild<'a> {
    pub folder: &'a Path,
    pub memory_budget: u64,
    pub disk_budget: Option<u64>,
    pub on_build: &'a mut dyn FnMut(u64),
    pub progress: &'a BuildProgress,
}

/// An opened store; its database stays open as long as this does.
pub struct StoredLod {
    pub dataset: LodDataset,
    pub folder: PathBuf,
    /// The build this opening ran, and how long it took, when there was no finished store.
    pub built: Option<(LodBuildReport, f64)>,
    _db: sled::Db,
    /// Keeps the store from being removed to make room for another; released last.
    _in_use: InUse,
}

impl StoredLod {
    /// Whether `folder` holds a finished store, which opens without the dataset's files.
    pub fn is_built(folder: &Path) -> bool {
        read_finished(folder).is_some()
    }

    /// Opens the store in `folder`, building it from `files` first when it has none, an
    /// unfinished or a damaged one, or one of another point count, within `memory_budget`
    /// bytes of build buffers. `disk_budget` bounds the stores in `folder`'s parent together:
    /// before a build, stores beside it that are not in use are removed, least recently used
    /// first, until the build's disk need and the rest fit. A build that would not fit the
    /// disk's free space or the budget is refused before it starts. `on_build` is told the
    /// points before a build starts.
    pub fn open_or_build(
        files: &[PathBuf],
        folder: &Path,
        memory_budget: u64,
        disk_budget: Option<u64>,
        on_build: &mut dyn FnMut(u64),
    ) -> Result<Self, CutError> {
        let progress = BuildProgress::new();
        let build = StoreBuild {
            folder,
            memory_budget,
            disk_budget,
            on_build,
            progress: &progress,
        };
        Self::open_or_build_watched(files, build)
    }

    /// [`StoredLod::open_or_build`] in `build`'s folder, listing in its `progress` the nodes
    /// a build stores as it stores them (a preview draws them meanwhile).
    pub fn open_or_build_watched(
        files: &[PathBuf],
        build: StoreBuild<'_>,
    ) -> Result<Self, CutError> {
        if files.is_empty() {
            return Self::open_finished(build.folder);
        }
        let source = DatasetSource::open(files)?;
        Self::open_or_build_source(&source, build).map_err(|error| match error {
            CutError::Store(error) => match source.naming_the_file(error) {
                Ok(named) => CutError::Ingest(named),
                Err(error) => CutError::Store(error),
            },
            error => error,
        })
    }

    /// [`StoredLod::open_or_build_watched`] of a source opened already (tiles by URL, or some
    /// of a dataset's files within the box of all of them).
    pub fn open_or_build_source(
        source: &dyn PointSource,
        build: StoreBuild<'_>,
    ) -> Result<Self, CutError> {
        let StoreBuild {
            folder,
            memory_budget,
            disk_budget,
            on_build,
            progress,
        } = build;
        let in_use = InUse::take(folder)?;
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
            let needed = build_disk_bytes(source.point_count(), true, spill_record_bytes(source));
            check_disk(folder, source.point_count(), needed, disk_budget)?;
            on_build(source.point_count());
            let started = Instant::now();
            let mut options = LodBuildOptions::new(folder.join("spill"));
            options.memory_budget_bytes = memory_budget.max(options.min_memory_budget_bytes());
            let report = build_lod_watched(source, &store, &options, progress)?;
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
            _in_use: in_use,
        })
    }
}

impl StoredLod {
    /// Removes the store in `folder` whose bytes failed their checks, in use or not, so that
    /// the next [`StoredLod::open_or_build`] builds it anew from the dataset's files; what
    /// still reads the old store reads its removed files until it lets go of them.
    pub fn remove_damaged(folder: &Path) -> Result<(), CutError> {
        super::store_space::remove_now(folder).map_err(|e| {
            CutError::Cache(format!(
                "removing the damaged store in {}: {e}",
                folder.display()
            ))
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
        read_finished(folder).ok_or_else(missing)?;
        let in_use = InUse::take(folder)?;
        // Read again once in use: it may have been removed meanwhile.
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
            _in_use: in_use,
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
    crate::write_whole::write_whole(&folder.join(FINISHED_FILE), text.as_bytes()).map_err(|e| {
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
    let config = sled::Config::new()
        .path(folder.join("index"))
        .cache_capacity(INDEX_CACHE_BYTES);
    let db = crate::sled_open::open_waiting(&config)
        .map_err(|e| CutError::Cache(format!("opening the store in {}: {e}", folder.display())))?;
    let tree = db.open_tree("lod").map_err(LodError::from)?;
    let store = LodStore::open(tree, folder.join(PAYLOAD_FILE))?;
    Ok((db, store))
}

/// Refuses a build of `points` points that needs `needed` bytes of disk, more than `budget`
/// or the free space under `folder`; within the budget, first makes room among the stores
/// beside `folder`.
fn check_disk(
    folder: &Path,
    points: u64,
    needed: u64,
    budget: Option<u64>,
) -> Result<(), CutError> {
    if let Some(budget) = budget {
        make_space(folder, points, needed, budget)?;
    }
    if let Ok(stat) = rustix::fs::statvfs(folder) {
        let free = stat.f_bavail.saturating_mul(stat.f_frsize);
        if needed > free {
            return Err(CutError::DiskTooSmall {
                points,
                needed_mib: needed >> 20,
                folder: folder.to_owned(),
                limit: format!("more than the {} MiB free there", free >> 20),
            });
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lod::disk::MAX_SPILL_RECORD_BYTES;

    #[test]
    fn a_build_larger_than_its_disk_budget_is_refused_before_it_starts() {
        let dir = tempfile::tempdir().expect("tempdir");
        let need = |points| build_disk_bytes(points, true, MAX_SPILL_RECORD_BYTES);
        let error = check_disk(dir.path(), 10_000_000, need(10_000_000), Some(100 << 20))
            .expect_err("refused");
        assert!(matches!(error, CutError::DiskTooSmall { .. }));
        assert!(error.to_string().contains("budget of 100 MiB"), "{error}");
        // More than any disk has free.
        let error =
            check_disk(dir.path(), u64::MAX / 64, need(u64::MAX / 64), None).expect_err("refused");
        assert!(error.to_string().contains("free there"), "{error}");
        assert!(check_disk(dir.path(), 1_000, need(1_000), None).is_ok());
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

    /// A LAS file of a small scene in `dir`.
    fn small_dataset(dir: &Path) -> PathBuf {
        use crate::ingest::{write_las, LasWriteOptions};
        let file = dir.join("scene.las");
        let scene = crate::sample::sample_scene(SMALL_POINTS as usize, 3);
        write_las(&file, &scene, &LasWriteOptions::default()).expect("write");
        file
    }

    const SMALL_POINTS: u64 = 4_000;

    /// The disk a build of the small dataset `file` needs, in the records it spills.
    fn small_need(file: &Path) -> u64 {
        let source = DatasetSource::open(&[file.to_owned()]).expect("open");
        assert!(source.position_grid().is_some(), "one file, one grid");
        build_disk_bytes(SMALL_POINTS, true, spill_record_bytes(&source))
    }

    fn build(file: &Path, folder: &Path, budget: Option<u64>) -> Result<StoredLod, CutError> {
        // Stores are ordered by their use times: keep those apart.
        std::thread::sleep(std::time::Duration::from_millis(20));
        StoredLod::open_or_build(&[file.to_owned()], folder, 64 << 20, budget, &mut |_| {})
    }

    /// Builds the store in `folder` and opens it again, as a later render does (its index
    /// then takes its settled size).
    fn build_used(file: &Path, folder: &Path, budget: Option<u64>) -> StoredLod {
        drop(build(file, folder, budget).expect("built"));
        let reopened = StoredLod::open_or_build(&[], folder, 64 << 20, None, &mut |_| {});
        reopened.expect("opened")
    }

    fn bytes(folder: &Path) -> u64 {
        super::super::store_space::folder_bytes(folder)
    }

    /// A budget that holds a build's disk need and one used store of the small dataset
    /// beside it, not two.
    fn budget_for_one_beside(file: &Path, dir: &Path) -> u64 {
        let probe = dir.join("probe").join("store");
        drop(build_used(file, &probe, None));
        let store = bytes(&probe);
        std::fs::remove_dir_all(dir.join("probe")).expect("remove");
        assert!(store > 0);
        small_need(file) + store + store / 2
    }

    /// A folder with a small dataset, and the budget that holds one store of it beside a build.
    fn small_dataset_and_budget() -> (tempfile::TempDir, PathBuf, u64) {
        let dir = tempfile::tempdir().expect("tempdir");
        let file = small_dataset(dir.path());
        let budget = budget_for_one_beside(&file, dir.path());
        (dir, file, budget)
    }

    /// Asserts that `budget` holds the build's need and either store, not both.
    fn assert_one_fits(budget: u64, file: &Path, a: &Path, b: &Path) {
        let (a, b) = (bytes(a), bytes(b));
        let need = small_need(file);
        assert!(
            need + a.max(b) <= budget,
            "{a} or {b} beside {need} > {budget}"
        );
        assert!(
            need + a + b > budget,
            "{a} and {b} beside {need} <= {budget}"
        );
    }

    fn stores_in(root: &Path) -> Vec<String> {
        let mut names: Vec<String> = std::fs::read_dir(root)
            .expect("list")
            .map(|e| e.expect("entry").file_name().to_string_lossy().into_owned())
            .collect();
        names.sort();
        names
    }

    #[test]
    fn building_beyond_the_budget_removes_the_least_recently_used_store() {
        let (dir, file, budget) = small_dataset_and_budget();
        let root = dir.path().join("lod");
        drop(build_used(&file, &root.join("a"), Some(budget)));
        drop(build_used(&file, &root.join("b"), Some(budget)));
        // `a` was built first but used last.
        std::thread::sleep(std::time::Duration::from_millis(20));
        let a = build(&file, &root.join("a"), Some(budget)).expect("a again");
        assert!(a.built.is_none());
        drop(a);
        assert_one_fits(budget, &file, &root.join("a"), &root.join("b"));
        drop(build(&file, &root.join("c"), Some(budget)).expect("c"));
        assert_eq!(stores_in(&root), ["a", "c"]);
        let total = bytes(&root);
        assert!(total <= budget, "{total} > {budget}");
        let reopened = build(&file, &root.join("a"), Some(budget)).expect("a kept");
        assert!(
            reopened.built.is_none(),
            "the store used last was kept whole"
        );
    }

    #[test]
    fn a_store_in_use_is_never_removed_to_make_room() {
        let (dir, file, budget) = small_dataset_and_budget();
        let root = dir.path().join("lod");
        // `a` is the least recently used, and in use throughout.
        let a = build_used(&file, &root.join("a"), Some(budget));
        drop(build_used(&file, &root.join("b"), Some(budget)));
        assert_one_fits(budget, &file, &root.join("a"), &root.join("b"));
        let c = build(&file, &root.join("c"), Some(budget)).expect("c");
        assert_eq!(stores_in(&root), ["a", "c"]);
        assert_eq!(a.dataset.point_count(), SMALL_POINTS);
        let total = bytes(&root);
        assert!(total <= budget, "{total} > {budget}");
        // Used as a later render uses it, `c` is as large as `b` was: with `a` and `c` in use
        // there is no room for another.
        drop(c);
        let c = build_used(&file, &root.join("c"), Some(budget));
        let error = build(&file, &root.join("d"), Some(budget))
            .err()
            .expect("refused");
        assert!(matches!(error, CutError::DiskTooSmall { .. }), "{error}");
        assert!(error.to_string().contains("stores in use"), "{error}");
        assert_eq!(stores_in(&root), ["a", "c", "d"]);
        drop((a, c));
        drop(build(&file, &root.join("d"), Some(budget)).expect("d"));
        let mut left = stores_in(&root);
        left.retain(|name| name != "d");
        assert_eq!(left.len(), 1, "one store beside d: {left:?}");
    }

    #[test]
    fn a_store_larger_than_the_whole_budget_is_refused_and_removes_nothing() {
        let dir = tempfile::tempdir().expect("tempdir");
        let file = small_dataset(dir.path());
        let root = dir.path().join("lod");
        drop(build(&file, &root.join("a"), None).expect("a"));
        let budget = small_need(&file) - 1;
        let error = build(&file, &root.join("b"), Some(budget))
            .err()
            .expect("refused");
        assert!(matches!(error, CutError::DiskTooSmall { .. }), "{error}");
        assert!(
            error.to_string().contains("more than its budget"),
            "{error}"
        );
        assert!(StoredLod::is_built(&root.join("a")));
    }
}

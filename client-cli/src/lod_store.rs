//! The level-of-detail store of a local dataset: kept in the cache folder under a name made
//! of its files (paths, sizes, modification times), so later renders of the same files open
//! it and a changed file gets a new one.

use std::cell::RefCell;
use std::path::{Path, PathBuf};
use std::sync::mpsc::Receiver;
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::UNIX_EPOCH;

use anyhow::{Context, Result};
use pointfarm_render::cut::{CutError, StoredLod};
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

/// A local dataset's store, with what builds it again when its bytes fail their checks: once
/// in a run, after which a second failure is the render's error, not another build.
pub struct LocalStore {
    pub stored: StoredLod,
    files: Vec<PathBuf>,
    memory_budget: u64,
    disk_budget: Option<u64>,
    /// Whether this run has rebuilt the store already.
    rebuilt: bool,
}

impl LocalStore {
    /// `stored`, built from `files` within `memory_budget` bytes of build buffers and the
    /// cache's `disk_budget`.
    pub fn new(
        stored: StoredLod,
        files: Vec<PathBuf>,
        memory_budget: u64,
        disk_budget: Option<u64>,
    ) -> Self {
        Self {
            stored,
            files,
            memory_budget,
            disk_budget,
            rebuilt: false,
        }
    }

    /// Builds the store again after `damage` (its bytes failed their checks), the first time
    /// in this run; a second time it is the error, naming the store's folder.
    pub fn rebuild_after(&mut self, damage: &CutError, say: &dyn Fn(String)) -> Result<()> {
        let folder = self.stored.folder.clone();
        if self.rebuilt {
            anyhow::bail!(
                "the levels of detail in {} failed their checks again after they were rebuilt: \
                 {damage}",
                folder.display()
            );
        }
        self.rebuilt = true;
        let stored = rebuild(
            &self.files,
            &folder,
            self.memory_budget,
            self.disk_budget,
            damage,
            say,
        )?;
        // The damaged store's files are let go of only now: its folder was removed first.
        self.stored = stored;
        Ok(())
    }
}

/// Removes the damaged store in `folder` and builds it anew from `files`, saying so.
fn rebuild(
    files: &[PathBuf],
    folder: &Path,
    memory_budget: u64,
    disk_budget: Option<u64>,
    damage: &CutError,
    say: &dyn Fn(String),
) -> Result<StoredLod> {
    tracing::warn!(folder = %folder.display(), reason = %damage, "rebuilding a damaged store");
    say(format!(
        "levels of detail: the store in {} failed its checks ({damage}); rebuilding it",
        folder.display()
    ));
    StoredLod::remove_damaged(folder)?;
    let rebuilt = build_with_spinner(files, folder, memory_budget, disk_budget)
        .with_context(|| format!("rebuilding the damaged store in {}", folder.display()))?;
    say_built(&rebuilt, say);
    Ok(rebuilt)
}

/// Opens the store of `files` in `folder`, building it first (with a spinner) when there is
/// none.
fn build_with_spinner(
    files: &[PathBuf],
    folder: &Path,
    memory_budget: u64,
    disk_budget: Option<u64>,
) -> Result<StoredLod, CutError> {
    let spinner = RefCell::new(None);
    let opened =
        StoredLod::open_or_build(files, folder, memory_budget, disk_budget, &mut |points| {
            *spinner.borrow_mut() = Some(crate::progress::spinner(format!(
                "building levels of detail of {points} points (once; kept in {})",
                folder.display()
            )));
        });
    if let Some(spinner) = spinner.take() {
        spinner.finish_and_clear();
    }
    opened
}

/// Opens the store of `files` in `cache`, building it first (with a spinner) when there is
/// none, within `memory_budget` bytes of build buffers. A store whose bytes fail their checks
/// as it opens is built again, once.
pub fn open_or_build(
    files: &[PathBuf],
    cache: &StoreCache,
    memory_budget: u64,
    say: &dyn Fn(String),
) -> Result<LocalStore> {
    let folder = cache.folder(files)?;
    let budget = cache.size_bytes;
    let (opened, rebuilt) = match build_with_spinner(files, &folder, memory_budget, budget) {
        Ok(opened) => (opened, false),
        Err(damage) if damage.is_store_damage() => {
            let rebuilt = rebuild(files, &folder, memory_budget, budget, &damage, say)?;
            (rebuilt, true)
        }
        Err(error) => {
            return Err(error).with_context(|| format!("the store in {}", folder.display()))
        }
    };
    if !rebuilt {
        say_built(&opened, say);
    }
    let mut store = LocalStore::new(opened, files.to_vec(), memory_budget, budget);
    store.rebuilt = rebuilt;
    Ok(store)
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

#[cfg(test)]
mod tests {
    use super::*;
    use pointfarm_render::ingest::{write_las, LasWriteOptions};
    use pointfarm_render::lod::{LodError, NodeKey};

    /// The damage a frame's read reports.
    fn damage() -> CutError {
        CutError::Store(LodError::CorruptNode {
            key: NodeKey::new(0, glam::UVec3::ZERO),
            reason: "checksum mismatch".into(),
        })
    }

    #[test]
    fn a_damaged_store_is_built_again_once_and_a_second_damage_is_the_error() {
        let dir = tempfile::tempdir().expect("tempdir");
        let file = dir.path().join("scene.las");
        let scene = pointfarm_render::sample::sample_scene(5_000, 2);
        write_las(&file, &scene, &LasWriteOptions::default()).expect("write");
        let cache = StoreCache {
            dir: dir.path().join("cache"),
            size_bytes: None,
        };
        let files = vec![file];
        let said = RefCell::new(Vec::new());
        let say = |line: String| said.borrow_mut().push(line);
        let mut store = open_or_build(&files, &cache, 64 << 20, &say).expect("built");
        let folder = store.stored.folder.clone();
        let payload = folder.join("nodes.bin");
        let before = std::fs::read(&payload).expect("payload");

        // The payload file cut to nothing: the store is removed and built whole again.
        std::fs::write(&payload, b"").expect("damage");
        store.rebuild_after(&damage(), &say).expect("rebuilt");
        assert!(store.stored.built.is_some());
        assert_eq!(
            std::fs::read(&payload).expect("payload").len(),
            before.len()
        );
        assert_eq!(store.stored.dataset.point_count(), 5_000);
        let lines = said.borrow().join("\n");
        assert!(lines.contains("failed its checks"), "{lines}");
        assert!(lines.contains("checksum mismatch"), "{lines}");

        // A second damage in the same run is reported, naming the store, and not built again.
        let error = store
            .rebuild_after(&damage(), &say)
            .expect_err("not built a second time");
        let message = format!("{error:#}");
        assert!(
            message.contains("again after they were rebuilt"),
            "{message}"
        );
        assert!(message.contains(&folder.display().to_string()), "{message}");
        assert_eq!(
            said.borrow()
                .iter()
                .filter(|l| l.contains("rebuilding"))
                .count(),
            1
        );
    }

    #[test]
    fn a_store_damaged_before_it_opens_is_built_again_as_it_opens() {
        let dir = tempfile::tempdir().expect("tempdir");
        let file = dir.path().join("scene.las");
        let scene = pointfarm_render::sample::sample_scene(5_000, 3);
        write_las(&file, &scene, &LasWriteOptions::default()).expect("write");
        let cache = StoreCache {
            dir: dir.path().join("cache"),
            size_bytes: None,
        };
        let files = vec![file];
        let say = |_: String| {};
        let folder = open_or_build(&files, &cache, 64 << 20, &say)
            .expect("built")
            .stored
            .folder;
        let payload = folder.join("nodes.bin");
        let mut bytes = std::fs::read(&payload).expect("payload");
        for byte in bytes.iter_mut().step_by(61) {
            *byte ^= 0x33;
        }
        std::fs::write(&payload, bytes).expect("damage");
        let said = RefCell::new(Vec::new());
        let say = |line: String| said.borrow_mut().push(line);
        let mut store = open_or_build(&files, &cache, 64 << 20, &say).expect("rebuilt");
        assert!(store.stored.built.is_some(), "built again as it opened");
        assert!(said.borrow().join("\n").contains("rebuilding it"));
        // Its one rebuild of the run is spent.
        assert!(store.rebuild_after(&damage(), &say).is_err());
    }
}

//! `DatasetStores`: the level-of-detail stores the daemon keeps, one per dataset content in
//! `DATA/lod/SHA256`, so that workers read the nodes a frame needs instead of downloading
//! and building from the dataset's files. A store is built once, when a request first needs
//! it, on a thread of its own (one build at a time, within a memory budget); a finished store
//! is opened again after a restart without a build.
//!
//! While a store builds, the daemon serves a preview sample of the dataset (the raw first
//! point of every LAZ chunk, every 50,000th LAS record: `ingest::sample_chunk_starts`), read
//! once per content and kept in memory until the store is ready, with the files' header
//! bounds that frame it, so a preview job's workers render what `render --preview` renders
//! of the same files without downloading them. The build is watched (`BuildProgress`): each
//! time it has stored another tenth of the points, its version (the whole tenths stored)
//! moves, so that leases offer the previewed frames for a redraw, and the next request reads
//! the sample again with the nodes stored so far (coarse levels first, at most
//! `PREVIEW_STORED_POINTS`, `preview`); only the latest sample of a content is kept. A file
//! whose chunk table is damaged is named in the refusal, and the job fails saying so (its
//! store would not build either).
//!
//! Every record served is checked first as a worker checks it (`codec::check_node`). A store
//! whose bytes fail their checks (a record's checksum or layout, a payload file cut short),
//! as records are served or as a finished store opens, is removed and built again from its
//! files, once in a run, logged and counted (`rebuilds`); its frames are tried again once it
//! is ready. A second failure after that rebuild is not built again: every later request is
//! refused naming the dataset by its id and file names, and the job fails saying so.

use std::collections::{HashMap, HashSet};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use pointfarm_render::color::Stretch;
use pointfarm_render::copc::{is_copc, open_copc_whole, CopcDecoder};
use pointfarm_render::cut::{LodDataset, StoredLod};
use pointfarm_render::lod::{BuildProgress, LodHierarchy};
use pointfarm_render::source::{frame_points, FramePoints, PointSourceFacts, StoreInput};

use crate::dataset_files::DatasetFolders;
use crate::error::DaemonError;
use crate::model::Dataset;

/// Most nodes one request may ask for.
pub const MAX_NODES_PER_REQUEST: usize = 256;

/// An opened store, or a COPC file's own hierarchy: what workers are sent of it.
pub struct ReadyStore {
    kept: Kept,
    /// The hierarchy as stored (its own checksum included), sent to workers as it is.
    pub hierarchy_record: Vec<u8>,
    /// How long this daemon took to build it; 0 when it opened one built before (or a COPC
    /// file, which needs no build).
    pub build_ms: f64,
    /// The units this build took over from one a stopped daemon left; `None` when it
    /// started anew or opened a finished store.
    resumed: Option<usize>,
    /// Set when the records are a COPC file's LAZ chunks, not a store's.
    pub copc: Option<CopcServed>,
    /// Set when the store was made from another content's store (`growth`).
    pub grown: Option<Grown>,
}

/// What nodes are read from.
enum Kept {
    Store(Box<StoredLod>),
    /// A dataset of one COPC file, read through its own hierarchy.
    Copc(LodDataset),
}

/// What a worker needs, beyond the hierarchy record, to render a COPC file's chunks as the
/// file is rendered here.
pub struct CopcServed {
    /// The dataset file's name, which errors about its chunks give.
    pub file_name: String,
    pub decoder: CopcDecoder,
    /// The root's point spacing (the record leaves it out).
    pub root_spacing: f64,
    /// The coarsest nodes' elevation range, read when the file was opened, so a worker need
    /// not read them again.
    pub elevation: Option<Stretch>,
    /// The points' spacing, measured from the same nodes, so every renderer of the file
    /// sizes adaptive points alike.
    pub point_spacing: Option<f64>,
}

impl ReadyStore {
    fn dataset(&self) -> &LodDataset {
        match &self.kept {
            Kept::Store(lod) => &lod.dataset,
            Kept::Copc(dataset) => dataset,
        }
    }

    pub fn hierarchy(&self) -> &LodHierarchy {
        self.dataset().hierarchy()
    }

    pub fn point_count(&self) -> u64 {
        self.dataset().point_count()
    }

    pub fn bounds(&self) -> pointfarm_render::cloud::WorldBounds {
        self.dataset().bounds()
    }

    /// The elevation range of its coarsest nodes, relative to the centre of its bounds: read
    /// once when it was opened, the same a worker reads from the same nodes.
    pub fn elevation(&self) -> Option<Stretch> {
        self.dataset().elevation()
    }

    /// Where the store's node records are read from (an export reads them all).
    pub fn node_records(&self) -> &std::sync::Arc<dyn pointfarm_render::lod::NodeRecords> {
        self.dataset().records()
    }
}

/// What a worker is told of a dataset's store.
pub enum StoreAnswer {
    /// Rendered resident, from the dataset's files.
    NotNeeded {
        points: u64,
    },
    Building {
        points: u64,
    },
    Ready(Arc<ReadyStore>),
}

enum Entry {
    /// Points counted from the files' headers; no store asked for yet.
    Counted(u64),
    /// Being built: its points, and the nodes the build has stored so far.
    Building {
        points: u64,
        progress: Arc<BuildProgress>,
    },
    Ready(Arc<ReadyStore>),
    /// The build failed; said to every later request (the files do not change).
    Failed(String),
}

/// What a dataset's content is as a COPC dataset.
enum CopcEntry {
    /// Not one COPC file: its store is built.
    Plain,
    Ready(Arc<ReadyStore>),
    /// Its hierarchy is inconsistent (named); said to every later request.
    Failed(String),
}

pub struct DatasetStores {
    dir: PathBuf,
    build_memory_bytes: u64,
    entries: Arc<Mutex<HashMap<String, Entry>>>,
    /// Datasets by content, as COPC files or not.
    copc: Mutex<HashMap<String, CopcEntry>>,
    /// Held by the build running, so builds take their memory one at a time.
    building: Arc<Mutex<()>>,
    /// Held while a request decides what to do with a store and opens or starts it, so two
    /// workers asking at once never open or build one store twice.
    opening: Mutex<()>,
    /// Preview samples by content, while their stores build. Each content's state is locked
    /// while a request reads its sample, so that requests at once read it once; no other
    /// request takes it.
    previews: Arc<Mutex<HashMap<String, Arc<Mutex<PreviewState>>>>>,
    /// Builds wait here first when set.
    gate: Option<StoreBuildGate>,
    /// Finished builds wait here, still building, when set.
    ready_gate: Option<StoreBuildGate>,
    /// Contents whose store this run built again after it failed its checks: once each, so
    /// a second failure is reported instead of built again.
    rebuilt: Mutex<HashSet<String>>,
    /// Stores this run built again after they failed their checks.
    rebuilds: AtomicU64,
    /// Stores this run made by updating a copy of another content's store.
    updates: Arc<AtomicU64>,
    /// Node records served to workers, which a published store's workers read elsewhere.
    records_served: AtomicU64,
    /// Called when a build's preview version moves and when it ends, so that frames waiting
    /// for the store are leased again (for a redraw, or for their final render).
    on_change: Option<Arc<dyn Fn() + Send + Sync>>,
    /// Where the datasets' files may be read from, checked before a build, a count or a
    /// preview sample reads them; `None` reads them where they are (tests).
    folders: Option<DatasetFolders>,
    /// Publishes ready stores for workers to read from object storage (`serve --store-url`).
    publisher: Option<Arc<StorePublisher>>,
    /// Reads datasets of tiles by URL (`input`).
    urls: Option<pointfarm_render::remote::RemoteClient>,
    /// The parts of datasets built first for the jobs that see them (`camera_first`).
    camera_first: camera_first::CameraFirstParts,
}

impl DatasetStores {
    pub fn new(dir: PathBuf, build_memory_bytes: u64) -> Self {
        Self {
            dir,
            build_memory_bytes,
            entries: Arc::default(),
            copc: Mutex::default(),
            building: Arc::default(),
            opening: Mutex::default(),
            previews: Arc::default(),
            gate: None,
            ready_gate: None,
            rebuilt: Mutex::default(),
            rebuilds: AtomicU64::new(0),
            updates: Arc::default(),
            records_served: AtomicU64::new(0),
            on_change: None,
            folders: None,
            publisher: None,
            urls: None,
            camera_first: Default::default(),
        }
    }

    /// How many stores this run built again after they failed their checks.
    pub fn rebuilds(&self) -> u64 {
        self.rebuilds.load(Ordering::Relaxed)
    }

    /// How many stores this run made by updating a copy of another content's store.
    pub fn updates(&self) -> u64 {
        self.updates.load(Ordering::Relaxed)
    }

    /// Builds wait at `gate` until it is opened.
    pub fn gated(mut self, gate: Option<StoreBuildGate>) -> Self {
        self.gate = gate;
        self
    }

    /// Finished builds wait at `gate` until it is opened before their stores are ready.
    pub fn held_before_ready(mut self, gate: Option<StoreBuildGate>) -> Self {
        self.ready_gate = gate;
        self
    }

    /// The datasets' files are read only while they lie in `folders` (a link swapped in since
    /// registration is not followed out of the data roots).
    pub fn reading_within(mut self, folders: DatasetFolders) -> Self {
        self.folders = Some(folders);
        self
    }

    /// Refuses `dataset` when a file of it here no longer lies where it may be read.
    fn check_files(&self, dataset: &Dataset) -> Result<(), DaemonError> {
        match &self.folders {
            Some(folders) if dataset.tiles.is_empty() => folders.check(dataset),
            _ => Ok(()),
        }
    }

    /// `on_change` is called when a build's preview version moves, and when it ends, ready
    /// or failed.
    pub fn notifying(mut self, on_change: Arc<dyn Fn() + Send + Sync>) -> Self {
        self.on_change = Some(on_change);
        self
    }

    /// The preview version of the store of content `sha256` being built now (the whole
    /// tenths of its points stored so far); `None` when it is not being built.
    pub fn building_version(&self, sha256: &str) -> Option<u32> {
        self.building_progress(sha256)
            .map(|progress| progress.preview_version())
    }

    /// The points the build of content `sha256` has stored so far, and its points in all
    /// (0 of 0 while it still counts them); `None` when it is not being built.
    pub fn building_points(&self, sha256: &str) -> Option<(u64, u64)> {
        self.building_progress(sha256)
            .map(|progress| progress.points())
    }

    /// What the build of content `sha256` has stored so far, while it builds.
    fn building_progress(&self, sha256: &str) -> Option<Arc<BuildProgress>> {
        match self.entries_now().get(sha256) {
            Some(Entry::Building { progress, .. }) => Some(Arc::clone(progress)),
            _ => None,
        }
    }

    fn folder(&self, sha256: &str) -> PathBuf {
        self.dir.join(sha256)
    }

    /// The levels of detail of `dataset` for a worker's frame: a dataset of one COPC file
    /// through its own hierarchy (no build), any other through its store ([`Self::open_store`]).
    pub fn open(
        &self,
        dataset: &Dataset,
        levels_of_detail: bool,
    ) -> Result<StoreAnswer, DaemonError> {
        let _one_decision = self.opening.lock().unwrap_or_else(|e| e.into_inner());
        match self.open_copc(dataset)? {
            Some(ready) => Ok(StoreAnswer::Ready(ready)),
            None => self.open_store_decided(dataset, levels_of_detail),
        }
    }

    /// The store of `dataset` when a frame needs one (`levels_of_detail`, or more points
    /// than render resident, or a store already built): ready, or building (started here).
    /// An export asks for the store whatever the files are.
    pub fn open_store(
        &self,
        dataset: &Dataset,
        levels_of_detail: bool,
    ) -> Result<StoreAnswer, DaemonError> {
        let _one_decision = self.opening.lock().unwrap_or_else(|e| e.into_inner());
        self.open_store_decided(dataset, levels_of_detail)
    }

    /// `dataset` through its own COPC hierarchy when it is one COPC file (whatever its size
    /// and the request, as a local render of the file); `None` otherwise. Several COPC files
    /// keep the store build: each has its own cube, and their nodes do not make one octree.
    /// Called under `opening`.
    fn open_copc(&self, dataset: &Dataset) -> Result<Option<Arc<ReadyStore>>, DaemonError> {
        let lock = || self.copc.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(answer) = self.copc_known(&dataset.sha256) {
            return answer;
        }
        self.check_files(dataset)?;
        let files = dataset.files();
        // A file that cannot be read as COPC is reported by the store's build.
        let ([file], true) = (files.as_slice(), dataset.tiles.is_empty()) else {
            lock().insert(dataset.sha256.clone(), CopcEntry::Plain);
            return Ok(None);
        };
        if !is_copc(&file.path).unwrap_or(false) {
            lock().insert(dataset.sha256.clone(), CopcEntry::Plain);
            return Ok(None);
        }
        let opened = open_copc_file(&file.path, &file.name)
            .map(Arc::new)
            // Refused rather than built as plain LAZ: a file whose hierarchy disagrees with
            // itself or the file is damaged, and the job should say so.
            .map_err(|reason| format!("dataset {}: {reason}", dataset.id));
        let entry = match &opened {
            Ok(ready) => {
                tracing::info!(dataset = %dataset.id, file = %file.name,
                    points = ready.point_count(),
                    "COPC hierarchy ready for workers: no store built");
                CopcEntry::Ready(Arc::clone(ready))
            }
            Err(reason) => {
                tracing::warn!(%reason, "the dataset's COPC hierarchy is refused");
                CopcEntry::Failed(reason.clone())
            }
        };
        lock().insert(dataset.sha256.clone(), entry);
        opened.map(Some).map_err(DaemonError::FailedPrecondition)
    }

    /// What is known of content `sha256` as a COPC file: `None` before it was looked at.
    fn copc_known(&self, sha256: &str) -> Option<Result<Option<Arc<ReadyStore>>, DaemonError>> {
        let copc = self.copc.lock().unwrap_or_else(|e| e.into_inner());
        copc.get(sha256).map(|entry| match entry {
            CopcEntry::Plain => Ok(None),
            CopcEntry::Ready(store) => Ok(Some(Arc::clone(store))),
            CopcEntry::Failed(reason) => Err(DaemonError::FailedPrecondition(reason.clone())),
        })
    }

    /// [`Self::open_store`], called under `opening`.
    fn open_store_decided(
        &self,
        dataset: &Dataset,
        levels_of_detail: bool,
    ) -> Result<StoreAnswer, DaemonError> {
        let sha = dataset.sha256.clone();
        let points = match self.entry(&sha, |entry| match entry {
            Entry::Counted(points) => Ok(*points),
            Entry::Building { points, .. } => Err(Ok(StoreAnswer::Building { points: *points })),
            Entry::Ready(store) => Err(Ok(StoreAnswer::Ready(Arc::clone(store)))),
            Entry::Failed(reason) => Err(Err(DaemonError::FailedPrecondition(reason.clone()))),
        }) {
            Ok(Some(points)) => points,
            Ok(None) => {
                self.check_files(dataset)?;
                let points = self.point_count(dataset)?;
                self.set(&sha, Entry::Counted(points));
                points
            }
            Err(answer) => return answer,
        };
        let folder = self.folder(&sha);
        let built = StoredLod::is_built(&folder);
        let cut_asked = levels_of_detail || self.is_part(&sha);
        // One COPC file never comes here: `open` answers it with its own hierarchy first.
        let facts = PointSourceFacts {
            points: Some(points),
            one_copc_file: false,
            store_built: built,
            levels_of_detail_asked: cut_asked || !dataset.tiles.is_empty(),
        };
        if frame_points(&facts) == FramePoints::Resident {
            return Ok(StoreAnswer::NotNeeded { points });
        }
        if built {
            let input = self.input_of(dataset)?;
            // Opening a finished store reads its hierarchy and a sample of its coarsest nodes.
            let opened = open_or_build(
                &input,
                &folder,
                self.build_memory_bytes,
                &BuildProgress::new(),
            );
            return match opened {
                Err(damage) if damage.is_store_damage() => self
                    .rebuild_damaged(dataset, None, &damage.to_string())
                    .map(|points| StoreAnswer::Building { points }),
                opened => self
                    .finish(&sha, opened.map_err(|e| e.to_string()))
                    .map(StoreAnswer::Ready),
            };
        }
        self.start_build(dataset, points)
    }

    /// Starts building the store of `dataset`, of `points` points, on a thread of its own.
    /// Called under `opening`.
    fn start_build(&self, dataset: &Dataset, points: u64) -> Result<StoreAnswer, DaemonError> {
        self.check_files(dataset)?;
        let sha = dataset.sha256.clone();
        let folder = self.folder(&sha);
        let input = self.input_of(dataset)?;
        let on_change = self.on_change.clone();
        let progress = Arc::new(match on_change.clone() {
            Some(on_change) => BuildProgress::notifying(move |_| on_change()),
            None => BuildProgress::new(),
        });
        self.set(
            &sha,
            Entry::Building {
                points,
                progress: Arc::clone(&progress),
            },
        );
        let (entries, building) = (Arc::clone(&self.entries), Arc::clone(&self.building));
        let budget = self.build_memory_bytes;
        let id = dataset.id.clone();
        let (gate, ready_gate) = (self.gate.clone(), self.ready_gate.clone());
        let previews = Arc::clone(&self.previews);
        let publisher = self.publisher.clone();
        let (files, updates) = (dataset.files(), Arc::clone(&self.updates));
        let making = self.making(&sha);
        let spawned = std::thread::Builder::new()
            .name("pointfarm-store-build".into())
            .spawn(move || {
                if let Some(gate) = gate {
                    gate.wait();
                }
                let _one_at_a_time = building.lock().unwrap_or_else(|e| e.into_inner());
                tracing::info!(dataset = %id, points, "building the dataset's levels of detail");
                let built =
                    camera_first::make(&making, &folder, budget, &progress, &files, points, &id)
                        .and_then(|made| {
                            made.or_open(|| {
                                grow_or_build(
                                    &input, &folder, budget, &progress, &files, points, &id,
                                )
                            })
                        });
                if let Ok(ready) = &built {
                    resume::log_resumed(&id, ready);
                    if ready.grown.is_some() {
                        updates.fetch_add(1, Ordering::Relaxed);
                    }
                }
                let built = built.map_err(|e| e.to_string());
                if let Some(gate) = ready_gate {
                    gate.wait();
                }
                let entry = match built {
                    Ok(ready) => {
                        // Frames render from the store now: the sample's memory is freed.
                        previews
                            .lock()
                            .unwrap_or_else(|e| e.into_inner())
                            .remove(&sha);
                        let ready = Arc::new(ready);
                        publish::offer(publisher.as_deref(), &sha, &ready);
                        Entry::Ready(ready)
                    }
                    Err(reason) => {
                        tracing::warn!(dataset = %id, %reason, "the dataset's store was not built");
                        Entry::Failed(format!("dataset {id}: {reason}"))
                    }
                };
                entries
                    .lock()
                    .unwrap_or_else(|e| e.into_inner())
                    .insert(sha, entry);
                if let Some(on_change) = on_change {
                    on_change();
                }
            });
        if let Err(e) = spawned {
            self.set(&dataset.sha256, Entry::Counted(points));
            return Err(DaemonError::Internal(format!(
                "starting a store build: {e}"
            )));
        }
        Ok(StoreAnswer::Building { points })
    }

    /// The ready store of `dataset`, for the node requests that follow an open. A COPC
    /// file's hierarchy, or a finished store, not open yet (the daemon restarted under a
    /// worker reading it) is opened.
    pub fn ready(&self, dataset: &Dataset) -> Result<Arc<ReadyStore>, DaemonError> {
        // A COPC file's hierarchy is opened here as an open would (it needs no build); only
        // a dataset not looked at yet waits for `opening`, not every node request.
        let copc = match self.copc_known(&dataset.sha256) {
            Some(known) => known?,
            None => {
                let _one_decision = self.opening.lock().unwrap_or_else(|e| e.into_inner());
                self.open_copc(dataset)?
            }
        };
        if let Some(store) = copc {
            return Ok(store);
        }
        let sha256 = dataset.sha256.as_str();
        let not_open = || {
            DaemonError::FailedPrecondition(
                "the dataset's store is not open: ask OpenDatasetStore first".into(),
            )
        };
        match self.entry(sha256, |entry| match entry {
            Entry::Ready(store) => Err(Some(Arc::clone(store))),
            Entry::Counted(_) => Ok(()),
            Entry::Building { .. } | Entry::Failed(_) => Err(None),
        }) {
            Err(Some(store)) => Ok(store),
            Err(None) => Err(not_open()),
            Ok(_) => {
                let _one_decision = self.opening.lock().unwrap_or_else(|e| e.into_inner());
                if let Some(Entry::Ready(store)) = self.entries_now().get(sha256) {
                    return Ok(Arc::clone(store));
                }
                let folder = self.folder(sha256);
                if !StoredLod::is_built(&folder) {
                    return Err(not_open());
                }
                let (progress, input) = (BuildProgress::new(), StoreInput::Files(Vec::new()));
                match open_or_build(&input, &folder, self.build_memory_bytes, &progress) {
                    Err(damage) if damage.is_store_damage() => {
                        let rebuilding = self.rebuild_damaged(dataset, None, &damage.to_string());
                        Err(rebuilding.map_or_else(|e| e, |_| being_rebuilt(dataset)))
                    }
                    opened => self.finish(sha256, opened.map_err(|e| e.to_string())),
                }
            }
        }
    }

    /// Forgets the store of content `sha256` and removes its folder (no dataset has that
    /// content any more), with the parts built first for its jobs (`camera_first`). A build
    /// under way finishes into a folder removed later.
    pub fn remove(&self, sha256: &str) {
        let mut entries = self.entries.lock().unwrap_or_else(|e| e.into_inner());
        if matches!(entries.get(sha256), Some(Entry::Building { .. })) {
            return;
        }
        entries.remove(sha256);
        drop(entries);
        // A dataset uploaded again later gets a rebuild of its own.
        self.rebuilt
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .remove(sha256);
        self.previews
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .remove(sha256);
        self.copc
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .remove(sha256);
        let folder = self.folder(sha256);
        let _ = std::fs::remove_dir_all(growth::growing_folder(&folder));
        if folder.exists() {
            match std::fs::remove_dir_all(&folder) {
                Ok(()) => tracing::info!(folder = %folder.display(), "store removed"),
                Err(error) => {
                    tracing::warn!(%error, folder = %folder.display(), "removing a store")
                }
            }
        }
        for part in self.forget_parts_of(sha256) {
            self.remove(&part);
        }
    }

    /// Marks the store of content `sha256` as building, having stored what `progress` lists:
    /// tests move a build's version with a build run to its end beforehand, not one racing.
    #[cfg(test)]
    pub(crate) fn hold_building(&self, sha256: &str, points: u64, progress: Arc<BuildProgress>) {
        self.set(sha256, Entry::Building { points, progress });
    }

    /// Runs `look` on the entry of `sha256`; `Ok(None)` when there is none.
    fn entry<T, E>(
        &self,
        sha256: &str,
        look: impl FnOnce(&Entry) -> Result<T, E>,
    ) -> Result<Option<T>, E> {
        let entries = self.entries.lock().unwrap_or_else(|e| e.into_inner());
        entries.get(sha256).map(look).transpose()
    }

    fn entries_now(&self) -> std::sync::MutexGuard<'_, HashMap<String, Entry>> {
        self.entries.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn set(&self, sha256: &str, entry: Entry) {
        self.entries
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .insert(sha256.to_owned(), entry);
    }

    /// Records the outcome of opening a store synchronously.
    fn finish(
        &self,
        sha256: &str,
        opened: Result<ReadyStore, String>,
    ) -> Result<Arc<ReadyStore>, DaemonError> {
        match opened {
            Ok(ready) => {
                let ready = Arc::new(ready);
                publish::offer(self.publisher.as_deref(), sha256, &ready);
                self.set(sha256, Entry::Ready(Arc::clone(&ready)));
                Ok(ready)
            }
            Err(reason) => Err(DaemonError::FailedPrecondition(reason)),
        }
    }
}

/// Opens the COPC file `path` (the dataset's file `name`) through its own hierarchy.
fn open_copc_file(path: &Path, name: &str) -> Result<ReadyStore, String> {
    let opened = open_copc_whole(path).map_err(|e| format!("COPC file {name}: {e}"))?;
    let hierarchy = opened.dataset.hierarchy();
    let copc = CopcServed {
        file_name: name.to_owned(),
        decoder: opened.decoder,
        root_spacing: opened.root_spacing,
        elevation: opened.dataset.elevation(),
        point_spacing: opened.dataset.point_spacing(),
    };
    Ok(ReadyStore {
        hierarchy_record: hierarchy.encode(),
        kept: Kept::Copc(opened.dataset),
        build_ms: 0.0,
        resumed: None,
        copc: Some(copc),
        grown: None,
    })
}

mod camera_first;
pub use camera_first::PartLedger;
mod gate;
pub use gate::StoreBuildGate;
mod growth;
use growth::grow_or_build;
pub use growth::{list_unlisted_stores, Grown};
mod healing;
use healing::being_rebuilt;
mod input;
use input::open_or_build;
mod preview;
mod publish;
mod resume;
#[cfg(test)]
mod tests;

pub use preview::PreviewBytes;
use preview::PreviewState;
pub use publish::{
    store_url, StorePublication, StorePublisher, DEFAULT_PUBLISH_ATTEMPTS, MAX_PUBLISH_ATTEMPTS,
};

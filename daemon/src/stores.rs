//! `DatasetStores`: the level-of-detail stores the daemon keeps, one per dataset content in
//! `DATA/lod/SHA256`, so that workers read the nodes a frame needs instead of downloading
//! and building from the dataset's files. A store is built once, when a request first needs
//! it, on a thread of its own (one build at a time, within a memory budget); a finished store
//! is opened again after a restart without a build.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

use pointfarm_render::color::Stretch;
use pointfarm_render::copc::{is_copc, open_copc, CopcDecoder};
use pointfarm_render::cut::{LodDataset, StoredLod, RESIDENT_MAX_POINTS};
use pointfarm_render::ingest::dataset_point_count;
use pointfarm_render::lod::{LodHierarchy, NodeInfo, NodeKey};

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
    /// Set when the records are a COPC file's LAZ chunks, not a store's.
    pub copc: Option<CopcServed>,
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

    /// Where the store's node records are read from (an export reads them all).
    pub fn node_records(&self) -> &std::sync::Arc<dyn pointfarm_render::lod::NodeRecords> {
        self.dataset().records()
    }

    /// The stored records of `keys`, in order; each must be a node of the hierarchy with
    /// points. A COPC file's records are its LAZ chunks, byte ranges of the file.
    pub fn records(&self, keys: &[NodeKey]) -> Result<Vec<Vec<u8>>, DaemonError> {
        let hierarchy = self.hierarchy();
        let infos: Vec<NodeInfo> = keys
            .iter()
            .map(|&key| match hierarchy.node(key) {
                Some(info) if info.point_count > 0 => Ok(*info),
                _ => Err(DaemonError::invalid(
                    "nodes",
                    format!("node {key} holds no points of this store"),
                )),
            })
            .collect::<Result<_, _>>()?;
        self.dataset()
            .records()
            .read_records(&infos)
            .map_err(|e| DaemonError::Internal(format!("reading the store's nodes: {e}")))
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
    Building(u64),
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
        let files = dataset.files();
        // A file that cannot be read as COPC is reported by the store's build.
        let [file] = files.as_slice() else {
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
            Entry::Building(points) => Err(Ok(StoreAnswer::Building { points: *points })),
            Entry::Ready(store) => Err(Ok(StoreAnswer::Ready(Arc::clone(store)))),
            Entry::Failed(reason) => Err(Err(DaemonError::FailedPrecondition(reason.clone()))),
        }) {
            Ok(Some(points)) => points,
            Ok(None) => {
                let paths: Vec<PathBuf> = dataset.files().into_iter().map(|f| f.path).collect();
                let points = dataset_point_count(&paths).map_err(|e| {
                    DaemonError::FailedPrecondition(format!("dataset {}: {e}", dataset.id))
                })?;
                self.set(&sha, Entry::Counted(points));
                points
            }
            Err(answer) => return answer,
        };
        let folder = self.folder(&sha);
        let built = StoredLod::is_built(&folder);
        if !levels_of_detail && points <= RESIDENT_MAX_POINTS && !built {
            return Ok(StoreAnswer::NotNeeded { points });
        }
        let files: Vec<PathBuf> = dataset.files().into_iter().map(|f| f.path).collect();
        if built {
            // Opening a finished store reads its hierarchy and a sample of its coarsest nodes.
            let ready = self.finish(
                &sha,
                open_or_build(&files, &folder, self.build_memory_bytes),
            );
            return ready.map(StoreAnswer::Ready);
        }
        self.set(&sha, Entry::Building(points));
        let (entries, building) = (Arc::clone(&self.entries), Arc::clone(&self.building));
        let budget = self.build_memory_bytes;
        let id = dataset.id.clone();
        let spawned = std::thread::Builder::new()
            .name("pointfarm-store-build".into())
            .spawn(move || {
                let _one_at_a_time = building.lock().unwrap_or_else(|e| e.into_inner());
                tracing::info!(dataset = %id, points, "building the dataset's levels of detail");
                let entry = match open_or_build(&files, &folder, budget) {
                    Ok(ready) => Entry::Ready(Arc::new(ready)),
                    Err(reason) => {
                        tracing::warn!(dataset = %id, %reason, "the dataset's store was not built");
                        Entry::Failed(format!("dataset {id}: {reason}"))
                    }
                };
                entries
                    .lock()
                    .unwrap_or_else(|e| e.into_inner())
                    .insert(sha, entry);
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
            Entry::Building(_) | Entry::Failed(_) => Err(None),
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
                self.finish(sha256, open_or_build(&[], &folder, self.build_memory_bytes))
            }
        }
    }

    /// Forgets the store of content `sha256` and removes its folder (no dataset has that
    /// content any more). A build under way finishes into a folder removed later.
    pub fn remove(&self, sha256: &str) {
        let mut entries = self.entries.lock().unwrap_or_else(|e| e.into_inner());
        if matches!(entries.get(sha256), Some(Entry::Building(_))) {
            return;
        }
        entries.remove(sha256);
        drop(entries);
        self.copc
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .remove(sha256);
        let folder = self.folder(sha256);
        if folder.exists() {
            match std::fs::remove_dir_all(&folder) {
                Ok(()) => tracing::info!(folder = %folder.display(), "store removed"),
                Err(error) => {
                    tracing::warn!(%error, folder = %folder.display(), "removing a store")
                }
            }
        }
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
                self.set(sha256, Entry::Ready(Arc::clone(&ready)));
                Ok(ready)
            }
            Err(reason) => Err(DaemonError::FailedPrecondition(reason)),
        }
    }
}

/// Opens the store in `folder`, building it from `files` first when it has none.
fn open_or_build(files: &[PathBuf], folder: &Path, budget: u64) -> Result<ReadyStore, String> {
    let lod = StoredLod::open_or_build(files, folder, budget, None, &mut |_| {})
        .map_err(|e| e.to_string())?;
    let build_ms = lod.built.as_ref().map_or(0.0, |(_, seconds)| seconds * 1e3);
    let hierarchy_record = lod.dataset.hierarchy().encode();
    tracing::info!(
        folder = %folder.display(),
        points = lod.dataset.point_count(),
        built = lod.built.is_some(),
        "store ready for workers"
    );
    Ok(ReadyStore {
        kept: Kept::Store(Box::new(lod)),
        hierarchy_record,
        build_ms,
        copc: None,
    })
}

/// Opens the COPC file `path` (the dataset's file `name`) through its own hierarchy.
fn open_copc_file(path: &Path, name: &str) -> Result<ReadyStore, String> {
    let opened = open_copc(path).map_err(|e| format!("COPC file {name}: {e}"))?;
    let hierarchy = opened.dataset.hierarchy();
    let copc = CopcServed {
        file_name: name.to_owned(),
        decoder: opened.decoder,
        root_spacing: opened.info.spacing,
        elevation: opened.dataset.elevation(),
    };
    Ok(ReadyStore {
        hierarchy_record: hierarchy.encode(),
        kept: Kept::Copc(opened.dataset),
        build_ms: 0.0,
        copc: Some(copc),
    })
}

#[cfg(test)]
mod tests {
    use std::time::{Duration, Instant};

    use pointfarm_render::ingest::{write_las, LasWriteOptions};
    use pointfarm_render::lod::{read_nodes, LodError, NodeRecords};
    use pointfarm_render::sample::sample_scene;

    use super::*;
    use crate::model::DatasetFile;

    /// A dataset of the sample scene (`points` of it) written as LAS into `dir`.
    fn scene_dataset(dir: &Path, points: usize, sha256: &str) -> Dataset {
        let path = dir.join("scene.las");
        write_las(&path, &sample_scene(points, 3), &LasWriteOptions::default()).expect("write");
        dataset_of(&path, sha256)
    }

    fn dataset_of(path: &Path, sha256: &str) -> Dataset {
        let size_bytes = std::fs::metadata(path).map_or(0, |m| m.len());
        Dataset {
            id: format!("ds-{sha256}"),
            name: "scene".into(),
            size_bytes,
            sha256: sha256.into(),
            path: path.to_owned(),
            files: vec![DatasetFile {
                name: "scene.las".into(),
                path: path.to_owned(),
                size_bytes,
                sha256: sha256.into(),
            }],
            created_unix_ms: 0,
        }
    }

    /// Asks until the store is ready (or a minute has passed).
    fn wait_ready(stores: &DatasetStores, dataset: &Dataset) -> Arc<ReadyStore> {
        let started = Instant::now();
        loop {
            match stores.open(dataset, true).expect("open") {
                StoreAnswer::Ready(store) => return store,
                StoreAnswer::Building { .. } if started.elapsed() < Duration::from_secs(60) => {
                    std::thread::sleep(Duration::from_millis(50));
                }
                _ => panic!("the store was not built"),
            }
        }
    }

    struct Records<'a>(&'a ReadyStore);

    impl NodeRecords for Records<'_> {
        fn read_records(&self, nodes: &[NodeInfo]) -> Result<Vec<Vec<u8>>, LodError> {
            let keys: Vec<NodeKey> = nodes.iter().map(|n| n.key).collect();
            self.0
                .records(&keys)
                .map_err(|e| LodError::Records(e.to_string()))
        }
    }

    #[test]
    fn a_store_is_built_once_served_by_node_and_removed_with_its_dataset() {
        let dir = tempfile::tempdir().expect("tempdir");
        let dataset = scene_dataset(dir.path(), 20_000, "aa11");
        let stores = DatasetStores::new(dir.path().join("lod"), 64 << 20);

        // Small and not asked for levels of detail: rendered resident, nothing built.
        assert!(matches!(
            stores.open(&dataset, false).expect("open"),
            StoreAnswer::NotNeeded { points: 20_000 }
        ));
        assert!(!dir.path().join("lod").join("aa11").exists());
        assert!(
            stores.ready(&dataset).is_err(),
            "not open before it is asked for"
        );

        let store = wait_ready(&stores, &dataset);
        assert_eq!(store.point_count(), 20_000);
        assert!(store.build_ms > 0.0);
        assert_eq!(
            LodHierarchy::decode(&store.hierarchy_record).expect("decodes"),
            *store.hierarchy()
        );
        // Once built, every request is served from the store.
        assert!(matches!(
            stores.open(&dataset, false).expect("open"),
            StoreAnswer::Ready(_)
        ));

        // The records decode to every point of the store, each checked.
        let keys: Vec<NodeKey> = store.hierarchy().nodes().iter().map(|n| n.key).collect();
        let nodes = read_nodes(&Records(&store), store.hierarchy(), &keys).expect("read");
        assert_eq!(nodes.iter().map(|n| n.len() as u64).sum::<u64>(), 20_000);

        // A node the hierarchy does not hold is refused, naming it.
        let outside = NodeKey::new(3, glam::UVec3::new(7, 7, 7));
        if store.hierarchy().node(outside).is_none() {
            let error = store.records(&[outside]).expect_err("not a node");
            assert!(error.to_string().contains("3-7-7-7"), "{error}");
        }

        // A new daemon opens the finished store without a build (this one's closed first:
        // sled locks its database).
        let record = store.hierarchy_record.clone();
        drop((store, stores));
        let again = DatasetStores::new(dir.path().join("lod"), 64 << 20);
        let StoreAnswer::Ready(reopened) = again.open(&dataset, false).expect("open") else {
            panic!("a finished store opens at once");
        };
        assert_eq!(reopened.build_ms, 0.0);
        assert_eq!(reopened.hierarchy_record, record);
        drop(reopened);

        drop(again);
        // A daemon restarted under a worker that reads the store serves it at once.
        let restarted = DatasetStores::new(dir.path().join("lod"), 64 << 20);
        let served = restarted.ready(&dataset).expect("opened on demand");
        assert_eq!(served.hierarchy_record, record);
        drop(served);
        let again = restarted;
        again.remove("aa11");
        assert!(!dir.path().join("lod").join("aa11").exists());
        assert!(again.ready(&dataset).is_err());
    }

    #[test]
    fn workers_asking_at_once_share_one_build_and_one_opening() {
        let dir = tempfile::tempdir().expect("tempdir");
        let dataset = scene_dataset(dir.path(), 5_000, "cc33");
        let asked_at_once = |stores: &DatasetStores| {
            std::thread::scope(|scope| {
                let asks: Vec<_> = (0..4)
                    .map(|_| scope.spawn(|| stores.open(&dataset, true).map(|_| ())))
                    .collect();
                for ask in asks {
                    ask.join().expect("no panic").expect("every ask answered");
                }
            });
        };
        let stores = DatasetStores::new(dir.path().join("lod"), 64 << 20);
        asked_at_once(&stores);
        let record = wait_ready(&stores, &dataset).hierarchy_record.clone();
        drop(stores);
        // A finished store, opened by four requests at once: one opening, shared.
        let stores = DatasetStores::new(dir.path().join("lod"), 64 << 20);
        asked_at_once(&stores);
        assert_eq!(
            stores.ready(&dataset).expect("open").hierarchy_record,
            record
        );
    }

    /// A COPC file of the repository's test data (`tests/data/copc`), as a dataset.
    fn copc_dataset(path: &Path, sha256: &str) -> Dataset {
        let mut dataset = dataset_of(path, sha256);
        let name = path.file_name().expect("a name").to_string_lossy();
        dataset.files[0].name = name.into_owned();
        dataset
    }

    fn copc_file(name: &str) -> PathBuf {
        PathBuf::from(env!("CARGO_MANIFEST_DIR"))
            .join("../tests/data/copc")
            .join(name)
    }

    #[test]
    fn a_copc_file_is_served_from_its_own_hierarchy_without_a_build() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = copc_file("simple_with_page.copc.laz");
        let dataset = copc_dataset(&path, "dd44");
        let stores = DatasetStores::new(dir.path().join("lod"), 64 << 20);
        // Ready at once, even unasked for levels of detail, as a local render of the file.
        let StoreAnswer::Ready(store) = stores.open(&dataset, false).expect("open") else {
            panic!("a COPC file needs no build");
        };
        assert!(!dir.path().join("lod").exists(), "a store was built");
        assert_eq!(store.point_count(), 1065);
        assert_eq!(store.build_ms, 0.0);
        let copc = store.copc.as_ref().expect("served as COPC");
        assert_eq!(copc.file_name, "simple_with_page.copc.laz");
        assert!(copc.elevation.is_some());
        // The record leaves the COPC spacing out; it is sent beside it.
        let record = LodHierarchy::decode(&store.hierarchy_record).expect("decodes");
        assert_eq!(record.level_spacing(), None);
        assert_eq!(
            record.with_root_spacing(copc.root_spacing),
            *store.hierarchy()
        );

        // Its records are byte ranges of the file, which the decoder sent reads back.
        let file = std::fs::read(&path).expect("read");
        let stored: Vec<NodeInfo> = store
            .hierarchy()
            .nodes()
            .iter()
            .filter(|n| n.point_count > 0)
            .copied()
            .collect();
        let keys: Vec<NodeKey> = stored.iter().map(|n| n.key).collect();
        let records = store.records(&keys).expect("records");
        let mut points = 0;
        for (info, record) in stored.iter().zip(&records) {
            let range = info.byte_range();
            assert_eq!(record[..], file[range.start as usize..range.end as usize]);
            let node = copc
                .decoder
                .decode_chunk(&store.hierarchy().cube, info, record)
                .expect("decodes");
            points += node.len();
        }
        assert_eq!(points, 1065);

        // A daemon restarted under a worker fetching nodes opens the file again, unbuilt.
        drop((store, stores));
        let restarted = DatasetStores::new(dir.path().join("lod"), 64 << 20);
        let served = restarted.ready(&dataset).expect("opened on demand");
        assert!(served.copc.is_some());
        assert!(!dir.path().join("lod").exists());
    }

    #[test]
    fn several_copc_files_and_an_export_build_a_store() {
        let dir = tempfile::tempdir().expect("tempdir");
        let mut two = copc_dataset(&copc_file("simple.copc.laz"), "ee55");
        two.files
            .push(copc_dataset(&copc_file("simple_with_page.copc.laz"), "ee55").files[0].clone());
        let stores = DatasetStores::new(dir.path().join("lod"), 64 << 20);
        let store = wait_ready(&stores, &two);
        assert!(store.copc.is_none(), "two cubes are not one octree");
        assert_eq!(store.point_count(), 2 * 1065);

        let one = copc_dataset(&copc_file("simple.copc.laz"), "ff66");
        assert!(matches!(stores.open(&one, true), Ok(StoreAnswer::Ready(s)) if s.copc.is_some()));
        let started = Instant::now();
        let exported = loop {
            match stores.open_store(&one, true).expect("open") {
                StoreAnswer::Ready(store) => break store,
                _ if started.elapsed() < Duration::from_secs(60) => {
                    std::thread::sleep(Duration::from_millis(50))
                }
                _ => panic!("the store was not built"),
            }
        };
        assert!(exported.copc.is_none(), "an export reads a built store");
        assert!(dir.path().join("lod").join("ff66").exists());
    }

    #[test]
    fn a_damaged_copc_file_is_refused_naming_it_and_nothing_is_built() {
        let dir = tempfile::tempdir().expect("tempdir");
        let mut bytes = std::fs::read(copc_file("simple.copc.laz")).expect("read");
        // The root page's second entry: its chunk moved past the end of the file.
        let info = 375 + 54;
        let page = u64::from_le_bytes(bytes[info + 40..info + 48].try_into().expect("8")) as usize;
        let beyond = bytes.len() as u64 + 1_000;
        bytes[page + 32 + 16..page + 32 + 24].copy_from_slice(&beyond.to_le_bytes());
        let path = dir.path().join("damaged.copc.laz");
        std::fs::write(&path, &bytes).expect("write");
        let dataset = copc_dataset(&path, "ab12");
        let stores = DatasetStores::new(dir.path().join("lod"), 64 << 20);
        for _ in 0..2 {
            let Err(DaemonError::FailedPrecondition(reason)) = stores.open(&dataset, true) else {
                panic!("a damaged COPC file is refused");
            };
            assert!(reason.contains("damaged.copc.laz"), "{reason}");
            assert!(
                reason.contains("COPC hierarchy is inconsistent"),
                "{reason}"
            );
        }
        assert!(stores.ready(&dataset).is_err());
        assert!(!dir.path().join("lod").exists(), "built as plain LAZ");
    }

    #[test]
    fn an_unreadable_file_is_named_and_nothing_is_built() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("broken.las");
        std::fs::write(&path, b"LASF but not really a file").expect("write");
        let dataset = dataset_of(&path, "bb22");
        let stores = DatasetStores::new(dir.path().join("lod"), 64 << 20);
        let Err(DaemonError::FailedPrecondition(reason)) = stores.open(&dataset, true) else {
            panic!("a broken file is refused");
        };
        assert!(reason.contains("broken.las"), "{reason}");
        assert!(!dir.path().join("lod").join("bb22").exists());
    }
}

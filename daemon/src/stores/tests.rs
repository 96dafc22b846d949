//! The daemon's stores against real files: built once, COPC files served from their own
//! hierarchy, damaged files refused.

use std::time::{Duration, Instant};

use pointfarm_render::ingest::{write_las, LasWriteOptions};
use pointfarm_render::lod::codec::Detail;
use pointfarm_render::lod::records::read_nodes_at;
use pointfarm_render::lod::{read_nodes, LodError, NodeInfo, NodeKey, NodeRecords};
use pointfarm_render::sample::sample_scene;
use pointfarm_render::testing::copc_file;

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
        remote: None,
        tiles: Vec::new(),
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

/// The stores in `dir`, with the store of a sample scene dataset (`points` of it) built.
fn scene_store(
    dir: &Path,
    points: usize,
    sha256: &str,
) -> (Dataset, DatasetStores, Arc<ReadyStore>) {
    let dataset = scene_dataset(dir, points, sha256);
    let stores = DatasetStores::new(dir.join("lod"), 64 << 20);
    let store = wait_ready(&stores, &dataset);
    (dataset, stores, store)
}

/// The nodes of `store`'s hierarchy with points, and their keys.
fn stored_nodes(store: &ReadyStore) -> (Vec<NodeInfo>, Vec<NodeKey>) {
    let stored: Vec<NodeInfo> = store.hierarchy().stored_nodes().copied().collect();
    let keys = stored.iter().map(|n| n.key).collect();
    (stored, keys)
}

struct Records<'a>(&'a ReadyStore);

impl NodeRecords for Records<'_> {
    fn read_records(&self, nodes: &[NodeInfo]) -> Result<Vec<Vec<u8>>, LodError> {
        let keys: Vec<NodeKey> = nodes.iter().map(|n| n.key).collect();
        self.0
            .records(&keys, false)
            .map_err(|e| LodError::Records(e.to_string()))
    }

    fn read_coarse_records(&self, nodes: &[NodeInfo]) -> Option<Result<Vec<Vec<u8>>, LodError>> {
        let keys: Vec<NodeKey> = nodes.iter().map(|n| n.key).collect();
        Some(
            self.0
                .records(&keys, true)
                .map_err(|e| LodError::Records(e.to_string())),
        )
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
    // Asked coarse, each record is its coarse section alone, which decodes to the node as a
    // coarse read of the store's own file gives it.
    let coarse =
        read_nodes_at(&Records(&store), store.hierarchy(), &keys, Detail::Coarse).expect("read");
    for (whole, coarse) in nodes.iter().zip(&coarse) {
        assert_eq!(coarse, &whole.coarsened(), "node {}", whole.key);
    }
    let (stored, stored_keys) = stored_nodes(&store);
    let sections = store.records(&stored_keys, true).expect("coarse");
    for (info, section) in stored.iter().zip(&sections) {
        assert_eq!(section.len(), info.head_len as usize, "node {}", info.key);
        assert!(section.len() < info.byte_len as usize, "node {}", info.key);
    }

    // A node the hierarchy does not hold is refused, naming it.
    let outside = NodeKey::new(3, glam::UVec3::new(7, 7, 7));
    if store.hierarchy().node(outside).is_none() {
        let error = store.records(&[outside], false).expect_err("not a node");
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

/// A worker told the store's elevation range colors by the range it would read itself.
#[test]
fn a_stores_elevation_range_is_the_one_a_worker_reads_from_its_coarsest_nodes() {
    use pointfarm_proto::v1 as pb;
    let dir = tempfile::tempdir().expect("tempdir");
    let (_dataset, _stores, store) = scene_store(dir.path(), 40_000, "e1e7");
    let sent = pb::OpenDatasetStoreResponse::from(&StoreAnswer::Ready(Arc::clone(&store)));
    let told = crate::grpc::store_elevation(&sent).expect("a range");
    let hierarchy = LodHierarchy::decode(&store.hierarchy_record).expect("decodes");
    let read =
        LodDataset::with_records(Arc::clone(store.node_records()), hierarchy, store.bounds())
            .expect("reads its coarsest nodes")
            .elevation();
    assert!(read.is_some(), "the scene's coarsest nodes hold points");
    assert_eq!(told, read);
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

/// A COPC file pointfarm exported records its inner nodes' grids: the hierarchy record a
/// worker is sent keeps them, so a worker's cuts of the file are its store's, as a local
/// render's are.
#[test]
fn an_exported_copc_files_node_grids_reach_the_record_workers_are_sent() {
    let dir = tempfile::tempdir().expect("tempdir");
    let exported = pointfarm_render::testing::exported_terrain(dir.path(), 60_000, 1_000);
    let (built, path) = (&exported.hierarchy, &exported.path);
    let stores = DatasetStores::new(dir.path().join("stores"), 64 << 20);
    let StoreAnswer::Ready(served) = stores
        .open(&copc_dataset(path, "ee55"), false)
        .expect("open")
    else {
        panic!("a COPC file needs no build");
    };
    let copc = served.copc.as_ref().expect("served as COPC");
    let record = LodHierarchy::decode(&served.hierarchy_record)
        .expect("decodes")
        .with_root_spacing(copc.root_spacing);
    let mut grids = std::collections::BTreeSet::new();
    for node in built.nodes() {
        let (sent, stored) = (record.spacing(node.key), built.spacing(node.key));
        match (sent, stored) {
            (Some(sent), Some(stored)) => {
                assert!(
                    (sent / stored - 1.0).abs() < 1e-9,
                    "node {}: {sent} against {stored}",
                    node.key
                );
                grids.insert(node.sample_grid);
            }
            _ => assert_eq!(sent, stored, "node {}", node.key),
        }
    }
    assert!(
        grids.len() > 1,
        "inner nodes on grids of several sizes: {grids:?}"
    );
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

    // Its records are byte ranges of the file, which the decoder sent reads back; asked for
    // coarse sections, it sends them whole (a chunk has none).
    let file = std::fs::read(&path).expect("read");
    let (stored, keys) = stored_nodes(&store);
    let records = store.records(&keys, true).expect("records");
    let mut points = 0;
    for (info, record) in stored.iter().zip(&records) {
        let pieces: Vec<_> = info.pieces(info.byte_len).collect();
        assert_eq!(pieces.len(), 1, "a COPC chunk is stored in one piece");
        let range = &pieces[0];
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

/// The preview sample is read once per content; a file whose chunk table is damaged is
/// refused, named, and the stores go on serving others.
#[test]
fn a_preview_sample_is_served_and_a_damaged_chunk_table_is_named() {
    let dir = tempfile::tempdir().expect("tempdir");
    let good = dir.path().join("good.laz");
    write_las(
        &good,
        &sample_scene(120_000, 5),
        &LasWriteOptions::default(),
    )
    .expect("write");
    let stores = DatasetStores::new(dir.path().join("lod"), 64 << 20);
    let sample = stores
        .preview_sample(&dataset_of(&good, "good"))
        .expect("a sample");
    assert_eq!(sample.points_in_files, 120_000);
    let cloud = pointfarm_render::cache::decode_cloud(&sample.cloud).expect("decodes");
    // Three 50,000-point chunks: three chunk starts.
    assert_eq!(cloud.len(), 3);

    // The chunk table's count (after its version, at the offset the points start with)
    // made far larger than the file holds.
    let damaged = dir.path().join("damaged.laz");
    let mut bytes = std::fs::read(&good).expect("read");
    let at = |offset: usize, len: usize| {
        let mut value = [0u8; 8];
        value[..len].copy_from_slice(&bytes[offset..offset + len]);
        u64::from_le_bytes(value) as usize
    };
    let table = at(at(96, 4), 8);
    bytes[table + 4..table + 8].copy_from_slice(&0x7fff_fff0u32.to_le_bytes());
    std::fs::write(&damaged, &bytes).expect("write");
    let refused = stores.preview_sample(&dataset_of(&damaged, "damaged"));
    let Err(DaemonError::FailedPrecondition(reason)) = refused else {
        panic!("not refused: {:?}", refused.map(|s| s.points_in_files));
    };
    assert!(reason.contains("damaged.laz"), "{reason}");
    assert!(reason.contains("chunk"), "{reason}");
    // Said again without reading the file again, and the good dataset is still served.
    std::fs::remove_file(&damaged).expect("remove");
    let again = stores.preview_sample(&dataset_of(&damaged, "damaged"));
    assert!(matches!(again, Err(DaemonError::FailedPrecondition(r)) if r == reason));
    assert!(stores.preview_sample(&dataset_of(&good, "good")).is_ok());
}

/// While a store builds, the preview sample carries the nodes the build has stored so far
/// and their version; it is read again only when the version moves, and the build's version
/// is what leases compare previews with.
#[test]
fn the_preview_sample_carries_the_nodes_stored_so_far_and_their_version() {
    let dir = tempfile::tempdir().expect("tempdir");
    let laz = dir.path().join("scene.laz");
    write_las(&laz, &sample_scene(120_000, 5), &LasWriteOptions::default()).expect("write");
    let dataset = dataset_of(&laz, "cc33");
    let gate = StoreBuildGate::closed();
    let stores = DatasetStores::new(dir.path().join("lod"), 64 << 20).gated(Some(gate.clone()));
    assert_eq!(stores.building_version("cc33"), None, "nothing builds yet");
    assert!(matches!(
        stores.open(&dataset, true).expect("open"),
        StoreAnswer::Building { points: 120_000 }
    ));
    assert_eq!(
        stores.building_version("cc33"),
        Some(0),
        "held at the gate: nothing stored"
    );
    let starts = stores.preview_sample(&dataset).expect("a sample");
    assert_eq!(starts.version, 0);
    let decoded = |sample: &PreviewBytes| {
        pointfarm_render::cache::decode_cloud(&sample.cloud)
            .expect("decodes")
            .len()
    };
    assert_eq!(decoded(&starts), 3, "the chunk starts alone");

    // A build of the same files run to its end beside it: every tenth stored.
    let progress = Arc::new(BuildProgress::new());
    let build = pointfarm_render::cut::StoreBuild {
        folder: &dir.path().join("beside"),
        memory_budget: 64 << 20,
        disk_budget: None,
        on_build: &mut |_| {},
        progress: &progress,
    };
    StoredLod::open_or_build_watched(std::slice::from_ref(&laz), build).expect("build");
    stores.hold_building("cc33", 120_000, Arc::clone(&progress));
    assert_eq!(stores.building_version("cc33"), Some(10));
    let redrawn = stores.preview_sample(&dataset).expect("a sample");
    assert_eq!(redrawn.version, 10);
    let (stored, total) = progress.points();
    assert_eq!((stored, total), (120_000, 120_000));
    assert_eq!(
        decoded(&redrawn),
        3 + 120_000,
        "the chunk starts and every stored point (within the preview's budget)"
    );
    assert_eq!(
        (redrawn.points_in_files, redrawn.framed),
        (starts.points_in_files, starts.framed)
    );
    let again = stores.preview_sample(&dataset).expect("a sample");
    assert!(
        Arc::ptr_eq(&again, &redrawn),
        "kept while the version stands"
    );

    // The gated build goes on and ends: the store is ready, nothing builds.
    gate.open();
    wait_ready(&stores, &dataset);
    assert_eq!(stores.building_version("cc33"), None);
    assert!(
        !stores
            .previews
            .lock()
            .expect("previews")
            .contains_key("cc33"),
        "the sample's memory is freed once the store is ready"
    );
}

/// Flips bits all along the payload file of the store of content `sha256`.
fn damage_payload(dir: &Path, sha256: &str) {
    let payload = dir.join("lod").join(sha256).join("nodes.bin");
    let mut bytes = std::fs::read(&payload).expect("payload");
    for byte in bytes.iter_mut().step_by(53) {
        *byte ^= 0x24;
    }
    std::fs::write(&payload, bytes).expect("damage");
}

/// A store whose records fail their checks as they are served is built again once, and
/// served whole; damage after that rebuild is reported to every request, naming the dataset
/// by its id and file name, and nothing more is built.
#[test]
fn a_damaged_store_is_built_again_once_then_its_damage_is_reported() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (dataset, stores, store) = scene_store(dir.path(), 20_000, "dd44");
    let (_, keys) = stored_nodes(&store);
    let whole = stores.node_records(&dataset, &keys, false).expect("served");
    drop(store);

    damage_payload(dir.path(), "dd44");
    let error = stores
        .node_records(&dataset, &keys, true)
        .expect_err("damage found");
    assert!(error.to_string().contains("being built again"), "{error}");
    assert_eq!(stores.rebuilds(), 1);
    // Another request meanwhile finds it building, or built: one rebuild.
    let _ = stores.node_records(&dataset, &keys, false);
    assert_eq!(stores.rebuilds(), 1);
    let rebuilt = wait_ready(&stores, &dataset);
    assert!(rebuilt.build_ms > 0.0, "built again");
    let (_, rebuilt_keys) = stored_nodes(&rebuilt);
    assert_eq!(rebuilt_keys, keys);
    assert_eq!(
        stores.node_records(&dataset, &keys, false).expect("served"),
        whole
    );
    drop(rebuilt);

    damage_payload(dir.path(), "dd44");
    let error = stores
        .node_records(&dataset, &keys, false)
        .expect_err("damaged again");
    let message = error.to_string();
    assert!(message.contains("failed its checks again"), "{message}");
    assert!(message.contains("dataset ds-dd44 (scene.las)"), "{message}");
    assert!(
        !message.contains(&dir.path().display().to_string()),
        "{message}"
    );
    assert!(matches!(error, DaemonError::FailedPrecondition(_)));
    // Every later request is told so; nothing is built again.
    let opened = stores.open(&dataset, true).err().expect("refused");
    assert_eq!(opened.to_string(), message);
    assert_eq!(stores.rebuilds(), 1);
}

/// A finished store damaged while the daemon was down is built again as it opens.
#[test]
fn a_finished_store_damaged_before_it_opens_is_built_again() {
    let dir = tempfile::tempdir().expect("tempdir");
    let dataset = scene_dataset(dir.path(), 20_000, "ee55");
    let stores = DatasetStores::new(dir.path().join("lod"), 64 << 20);
    drop(wait_ready(&stores, &dataset));
    drop(stores);
    damage_payload(dir.path(), "ee55");
    let restarted = DatasetStores::new(dir.path().join("lod"), 64 << 20);
    assert!(matches!(
        restarted.open(&dataset, true).expect("open"),
        StoreAnswer::Building { points: 20_000 }
    ));
    assert_eq!(restarted.rebuilds(), 1);
    let store = wait_ready(&restarted, &dataset);
    let (_, keys) = stored_nodes(&store);
    assert!(restarted.node_records(&dataset, &keys, false).is_ok());
}

#[test]
fn only_the_unfinished_stores_of_waiting_datasets_are_built_again_at_startup() {
    let dir = tempfile::tempdir().expect("tempdir");
    for scans in ["unfinished", "never"] {
        std::fs::create_dir_all(dir.path().join(scans)).expect("folder");
    }
    let unfinished = scene_dataset(&dir.path().join("unfinished"), 20_000, "unfinished");
    let never_built = scene_dataset(&dir.path().join("never"), 20_000, "never");
    // A folder without a finished store: a build a stopped daemon left.
    std::fs::create_dir_all(dir.path().join("lod").join("unfinished")).expect("folder");
    let gate = StoreBuildGate::closed();
    let stores = DatasetStores::new(dir.path().join("lod"), 64 << 20).gated(Some(gate.clone()));

    let started = stores.resume_builds([unfinished.clone(), never_built.clone()]);
    assert_eq!(started, 1);
    assert!(stores.building_version("unfinished").is_some());
    assert!(
        stores.entries_now().get("never").is_none(),
        "never asked for"
    );
    assert!(!dir.path().join("lod").join("never").exists());
    // Started again, a build under way is not started twice.
    assert_eq!(stores.resume_builds([unfinished.clone()]), 0);

    gate.open();
    let ready = wait_ready(&stores, &unfinished);
    assert_eq!(ready.point_count(), 20_000);
    assert!(StoredLod::is_built(
        &dir.path().join("lod").join("unfinished")
    ));
    // A finished store is opened when asked, not built at startup.
    let again = DatasetStores::new(dir.path().join("lod"), 64 << 20);
    assert_eq!(again.resume_builds([unfinished]), 0);
}

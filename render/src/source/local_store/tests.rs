use super::*;
use crate::ingest::{write_las, LasWriteOptions};
use crate::lod::{LodError, NodeKey};
use crate::source::tests::{damage_payload, Told};

/// The damage a frame's read reports.
fn damage() -> CutError {
    CutError::Store(LodError::CorruptNode {
        key: NodeKey::new(0, glam::UVec3::ZERO),
        reason: "checksum mismatch".into(),
    })
}

/// A scene of 5,000 points in a LAS file of `dir`, and a store cache beside it.
fn scene(dir: &Path, seed: u64) -> (Vec<PathBuf>, StoreCache) {
    let file = dir.join("scene.las");
    let scene = crate::sample::sample_scene(5_000, seed);
    write_las(&file, &scene, &LasWriteOptions::default()).expect("write");
    let cache = StoreCache {
        dir: dir.join("cache"),
        disk_budget: None,
    };
    (vec![file], cache)
}

#[test]
fn a_damaged_store_is_built_again_once_and_a_second_damage_is_the_error() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (files, cache) = scene(dir.path(), 2);
    let folder = cache.folder_of_files(&files).expect("folder");
    let told = Told::default();
    let events = |event: SourceEvent<'_>| told.tell(event);
    let mut store =
        LocalStore::open_or_build(&files, &folder, 64 << 20, None, &events).expect("built");
    let payload = folder.join("nodes.bin");
    let before = std::fs::read(&payload).expect("payload");

    // The payload file cut to nothing: the store is removed and built whole again.
    std::fs::write(&payload, b"").expect("damage");
    store.rebuild_after(damage(), &events).expect("rebuilt");
    assert!(store.stored.built.is_some());
    assert_eq!(
        std::fs::read(&payload).expect("payload").len(),
        before.len()
    );
    assert_eq!(store.stored.dataset.point_count(), 5_000);
    let lines = told.lines();
    assert!(lines.contains("Rebuilding"), "{lines}");
    assert!(lines.contains("checksum mismatch"), "{lines}");

    // A second damage in the same opening is the error, naming the store, and the damaged
    // store is removed for the next opening to build.
    let error = store
        .rebuild_after(damage(), &events)
        .expect_err("not built a second time");
    assert!(matches!(error, SourceError::DamagedAgain { .. }), "{error}");
    let message = error.to_string();
    assert!(
        message.contains("again after they were rebuilt"),
        "{message}"
    );
    assert!(message.contains(&folder.display().to_string()), "{message}");
    assert_eq!(told.count("Rebuilding"), 1, "{}", told.lines());
    assert!(
        !StoredLod::is_built(&folder),
        "the damaged store is removed"
    );
}

#[test]
fn a_store_damaged_before_it_opens_is_built_again_as_it_opens() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (files, cache) = scene(dir.path(), 3);
    let folder = cache.folder_of_files(&files).expect("folder");
    LocalStore::open_or_build(&files, &folder, 64 << 20, None, &super::super::quiet)
        .expect("built");
    damage_payload(&folder);
    let told = Told::default();
    let events = |event: SourceEvent<'_>| told.tell(event);
    let mut store =
        LocalStore::open_or_build(&files, &folder, 64 << 20, None, &events).expect("rebuilt");
    assert!(store.stored.built.is_some(), "built again as it opened");
    assert_eq!(told.count("Rebuilding"), 1, "{}", told.lines());
    // Its one rebuild of the opening is spent.
    assert!(store.rebuild_after(damage(), &events).is_err());
}

#[test]
fn a_damaged_store_opened_without_its_files_is_removed_for_the_next_opening() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (files, cache) = scene(dir.path(), 4);
    let folder = cache.folder_of_dataset("abc");
    LocalStore::open_or_build(&files, &folder, 64 << 20, None, &super::super::quiet)
        .expect("built");
    let mut store = LocalStore::open_or_build(&[], &folder, 64 << 20, None, &super::super::quiet)
        .expect("opened without its files");
    assert_eq!(store.file_count(), 0);
    let error = store
        .rebuild_after(damage(), &super::super::quiet)
        .expect_err("nothing to build it from");
    assert!(
        matches!(error, SourceError::Cut(CutError::Store(_))),
        "{error}"
    );
    assert!(!StoredLod::is_built(&folder));
}

#[test]
fn the_folder_of_local_files_follows_their_contents() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (files, cache) = scene(dir.path(), 5);
    let first = cache.folder_of_files(&files).expect("folder");
    assert_eq!(first, cache.folder_of_files(&files).expect("folder"));
    let scene = crate::sample::sample_scene(4_000, 6);
    write_las(&files[0], &scene, &LasWriteOptions::default()).expect("write");
    assert_ne!(first, cache.folder_of_files(&files).expect("folder"));
    let missing = cache.folder_of_files(&[dir.path().join("gone.las")]);
    assert!(matches!(missing, Err(SourceError::Io { .. })));
}

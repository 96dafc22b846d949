//! Layered payloads end to end: stores grown one from another by linking the earlier payload
//! as layers (as the daemon grows them), read after the earlier stores are gone, refused when
//! a layer changed, compacted into one file, and one-file stores read as before.

use std::path::{Path, PathBuf};

use super::super::compact::compact;
use super::super::layers::{link_layers, list_path, PayloadReader};
use super::super::*;
use super::update::{build, file_points, options, store_points, write_tiles};
use crate::ingest::DatasetSource;

/// A store folder as the daemon keeps one: its sled index and payload file.
struct Folder {
    path: PathBuf,
    db: sled::Db,
    store: LodStore,
}

fn open(path: &Path) -> Folder {
    std::fs::create_dir_all(path).expect("folder");
    let db = sled::open(path.join("index")).expect("sled");
    let tree = db.open_tree("lod").expect("tree");
    let store = LodStore::open(tree, path.join("nodes.bin")).expect("store");
    Folder {
        path: path.to_owned(),
        db,
        store,
    }
}

fn copy_index(from: &Path, into: &Path) {
    std::fs::create_dir_all(into).expect("index folder");
    for entry in std::fs::read_dir(from).expect("index") {
        let entry = entry.expect("entry");
        let target = into.join(entry.file_name());
        match entry.file_type().expect("kind").is_dir() {
            true => copy_index(&entry.path(), &target),
            false => drop(std::fs::copy(entry.path(), target).expect("copy")),
        }
    }
}

/// Grows the store in `from` into `into` with `added`: its index copied, its payload linked
/// as layers, then updated; returns the grown store and the bytes its layers hold.
fn grow(from: Folder, into: &Path, added: &[PathBuf], options: &LodBuildOptions) -> (Folder, u64) {
    from.db.flush().expect("flush");
    let from_path = from.path.clone();
    drop(from);
    copy_index(&from_path.join("index"), &into.join("index"));
    let linked = link_layers(&from_path.join("nodes.bin"), &into.join("nodes.bin")).expect("link");
    let grown = open(into);
    let source = DatasetSource::open(added).expect("open added");
    update_lod(&grown.store, &source, vec!["files now".into()], options).expect("update");
    (grown, linked)
}

/// A scene's tiles in `dir`, its three tiles added one growth each, the options, and the
/// store of the tiles before them, built in `dir/s0`.
fn chain_scene(dir: &Path) -> (Vec<PathBuf>, [usize; 3], LodBuildOptions, Folder) {
    let files = write_tiles(dir, 40_000);
    let added = [5, 6, 10];
    let first: Vec<PathBuf> = (0..files.len())
        .filter(|t| !added.contains(t))
        .map(|t| files[t].clone())
        .collect();
    let options = options(dir);
    let folder = open(&dir.join("s0"));
    build(&first, &folder.store, &options);
    (files, added, options, folder)
}

#[test]
fn a_chain_of_three_growths_reads_the_same_after_the_earlier_stores_are_removed() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (files, added, options, mut folder) = chain_scene(dir.path());
    assert!(!list_path(folder.store.payload_path()).exists(), "one file");
    let mut folders = vec![folder.path.clone()];
    for (i, &tile) in added.iter().enumerate() {
        let before = folder.store.payload_bytes().expect("bytes");
        let into = dir.path().join(format!("s{}", i + 1));
        let (grown, linked) = grow(folder, &into, &[files[tile].clone()], &options);
        assert_eq!(linked, before, "the earlier payload is linked whole");
        assert_eq!(grown.store.payload_files(), i + 2);
        // The grown store's own file holds only what the update appended.
        let own = std::fs::metadata(grown.store.payload_path())
            .expect("own")
            .len();
        assert_eq!(own + linked, grown.store.payload_bytes().expect("bytes"));
        assert!(own * 2 < linked, "{own} bytes appended to {linked}");
        folders.push(into);
        folder = grown;
    }
    let points = store_points(&folder.store);
    assert_eq!(points, file_points(&files));
    let path = folder.path.clone();
    drop(folder);
    for earlier in &folders[..3] {
        std::fs::remove_dir_all(earlier).expect("the earlier store removed");
    }
    let last = open(&path);
    assert_eq!(
        store_points(&last.store),
        points,
        "read again without the earlier stores"
    );

    // Against a fresh build of every tile: the same points and statistics.
    let fresh = open(&dir.path().join("fresh"));
    let report = build(&files, &fresh.store, &options);
    let hierarchy = last.store.read_hierarchy().expect("hierarchy");
    assert_eq!(hierarchy.stats, report.hierarchy.stats);
    assert_eq!(store_points(&fresh.store), points);

    // Compacted: one file of its live records, read the same.
    let compacted = compact(&last.store).expect("compact");
    assert_eq!((compacted.files_before, last.store.payload_files()), (4, 1));
    assert!(
        compacted.bytes_after < compacted.bytes_before,
        "{compacted:?}"
    );
    assert!(!list_path(last.store.payload_path()).exists());
    assert_eq!(store_points(&last.store), points);
    drop(last);
    assert_eq!(
        store_points(&open(&path).store),
        points,
        "compacted, opened again"
    );
}

#[test]
fn a_changed_layer_refuses_the_store_until_it_is_built_again() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (files, added, options, earlier) = chain_scene(dir.path());
    let (grown, _) = grow(
        earlier,
        &dir.path().join("s1"),
        &[files[added[0]].clone()],
        &options,
    );
    let path = grown.path.clone();
    drop(grown);

    // One byte in the middle of the layer: its edges hold, its modification time does not.
    let layer = path.join("nodes.bin.0");
    let mut bytes = std::fs::read(&layer).expect("layer");
    let middle = bytes.len() / 2;
    bytes[middle] ^= 0x55;
    std::thread::sleep(std::time::Duration::from_millis(20));
    std::fs::write(&layer, &bytes).expect("tamper");
    let refused = open(&path);
    let error = refused.store.read_hierarchy().expect_err("refused");
    assert!(matches!(error, LodError::CorruptLayers(_)), "{error}");
    assert!(error.to_string().contains("layer 0 holds"), "{error}");

    // Built again, the store is one file of its own; the earlier store's file, which the
    // layer shared, is left as it was.
    let earlier_len = std::fs::metadata(dir.path().join("s0/nodes.bin"))
        .expect("s0")
        .len();
    let all: Vec<PathBuf> = (0..files.len())
        .filter(|t| !added[1..].contains(t))
        .map(|t| files[t].clone())
        .collect();
    build(&all, &refused.store, &options);
    assert_eq!(refused.store.payload_files(), 1);
    assert!(!layer.exists());
    assert_eq!(store_points(&refused.store), file_points(&all));
    let after = std::fs::metadata(dir.path().join("s0/nodes.bin"))
        .expect("s0")
        .len();
    assert_eq!(after, earlier_len);
}

#[test]
fn a_one_file_store_opens_as_one_layer_and_a_layered_payload_reads_as_its_concatenation() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (files, added, options, earlier) = chain_scene(dir.path());
    let points = store_points(&earlier.store);
    let path = earlier.path.clone();
    drop(earlier);
    let one = open(&path);
    assert_eq!(one.store.payload_files(), 1);
    assert_eq!(store_points(&one.store), points);
    let one_bytes = std::fs::read(path.join("nodes.bin")).expect("payload");
    let reader = PayloadReader::open(&path.join("nodes.bin")).expect("reader");
    assert_eq!(reader.len(), one_bytes.len() as u64);

    let (grown, _) = grow(
        one,
        &dir.path().join("s1"),
        &[files[added[0]].clone()],
        &options,
    );
    let own = std::fs::read(grown.store.payload_path()).expect("own");
    let flattened = [one_bytes, own].concat();
    let reader = PayloadReader::open(grown.store.payload_path()).expect("reader");
    let mut read = vec![0u8; reader.len() as usize];
    reader.read_exact_at(&mut read, 0).expect("read");
    assert!(read == flattened, "the layers read as their concatenation");
    let mut through_store = vec![0u8; read.len()];
    grown
        .store
        .read_payload(&mut through_store, 0)
        .expect("read");
    assert!(through_store == flattened);
}

//! Files taken out of a store by an update: LAS tiles written here, a store built from them,
//! then updated without some (or with one changed), checked point for point against the files
//! that remain and against a fresh build of them.

use std::path::PathBuf;

use super::super::*;
use super::temp_store;
use super::update::{build, file_points, store_points, tile_scene, write_tiles};
use crate::ingest::DatasetSource;

/// The store of `order` (its files, in the order it took them) updated without the files at
/// places `removed` and with `added`.
fn change(
    store: &LodStore,
    order: &[PathBuf],
    removed: &[usize],
    added: &[PathBuf],
    options: &LodBuildOptions,
) -> Result<LodUpdateReport, LodError> {
    let reopen = |places: &[usize]| -> Result<Box<dyn PointSource>, LodError> {
        let paths: Vec<PathBuf> = places.iter().map(|&i| order[i].clone()).collect();
        let source = DatasetSource::open(&paths).map_err(|e| LodError::Source(e.to_string()))?;
        Ok(Box::new(source))
    };
    let source = (!added.is_empty()).then(|| DatasetSource::open(added).expect("open added"));
    let change = StoreChange {
        added: source.as_ref().map(|s| s as &dyn PointSource),
        removed: removed.to_vec(),
        reopen: &reopen,
        files: Vec::new(),
    };
    update_store(store, &change, options)
}

/// `files` without those at `places`.
fn without(files: &[PathBuf], places: &[usize]) -> Vec<PathBuf> {
    (0..files.len())
        .filter(|i| !places.contains(i))
        .map(|i| files[i].clone())
        .collect()
}

/// The store holds exactly the points of `files`, with a fresh build's statistics and about
/// as many nodes.
fn assert_like_a_fresh_build(store: &LodStore, files: &[PathBuf], options: &LodBuildOptions) {
    assert_eq!(store_points(store), file_points(files));
    let fresh_dir = tempfile::tempdir().expect("tempdir");
    let (_db, fresh) = temp_store(fresh_dir.path());
    let fresh = build(files, &fresh, options).hierarchy;
    let updated = store.read_hierarchy().expect("hierarchy");
    assert_eq!(updated.point_count, fresh.point_count);
    assert_eq!(updated.stats, fresh.stats);
    let (a, b) = (updated.nodes().len(), fresh.nodes().len());
    assert!(a.abs_diff(b) * 10 <= b, "{a} nodes updated, {b} fresh");
}

#[test]
fn a_removed_tile_rebuilds_only_the_regions_it_reaches() {
    let (_dir, _db, files, store, options) = tile_scene(60_000, 1);
    build(&files, &store, &options);
    let regions = store.read_regions().expect("read").expect("regions");
    let facts = regions.file_facts.as_ref().expect("file facts");
    assert_eq!(facts.len(), files.len());
    let gone = 5;
    let report = change(&store, &files, &[gone], &[], &options).expect("update");
    assert_eq!(report.points_removed, facts[gone].points);
    assert_eq!(report.files_reread, 0, "tiles do not overlap");
    assert!(report.regions_rebuilt > 0, "{report:?}");
    assert!(report.regions_kept > report.regions_rebuilt, "{report:?}");
    let remaining = without(&files, &[gone]);
    assert_like_a_fresh_build(&store, &remaining, &options);
    let after = store.read_regions().expect("read").expect("regions");
    assert_eq!(after.file_facts.expect("facts").len(), remaining.len());
    // The facts follow the store's order: the next removal names a place in it.
    let report = change(&store, &remaining, &[0], &[], &options).expect("second update");
    assert!(report.points_removed > 0);
    assert_like_a_fresh_build(&store, &remaining[1..], &options);
}

#[test]
fn removing_every_file_of_a_region_removes_the_region() {
    let (_dir, _db, files, store, options) = tile_scene(40_000, 1);
    let built = build(&files, &store, &options);
    let regions = store.read_regions().expect("read").expect("regions");
    let facts = regions.file_facts.clone().expect("facts");
    let cube = built.hierarchy.cube;
    // The region with the fewest files (those whose boxes meet its cube), short of all.
    let files_of = |key: NodeKey| -> Vec<usize> {
        let (min, side) = (cube.node_min(key), cube.side_at(key.level));
        let max = min + glam::DVec3::splat(side);
        (0..facts.len())
            .filter(|&i| facts[i].max.cmpge(min).all() && facts[i].min.cmple(max).all())
            .collect()
    };
    let (key, gone) = regions
        .regions
        .iter()
        .map(|r| (r.key, files_of(r.key)))
        .filter(|(_, f)| f.len() < files.len() / 2)
        .min_by_key(|(_, f)| f.len())
        .expect("a region of few files");
    change(&store, &files, &gone, &[], &options).expect("update");
    let after = store.read_regions().expect("read").expect("regions");
    assert!(after.regions.iter().all(|r| r.key != key), "{key:?} kept");
    assert_eq!(
        after.regions.iter().map(|r| r.points).sum::<u64>(),
        store.read_hierarchy().expect("hierarchy").point_count
    );
    assert_like_a_fresh_build(&store, &without(&files, &gone), &options);
}

#[test]
fn a_changed_tile_is_taken_out_as_it_was_and_in_as_it_is() {
    let (_dir, _db, files, store, options) = tile_scene(60_000, 1);
    build(&files, &store, &options);
    // The same tile of a denser survey of the scene, written over the file.
    let other = tempfile::tempdir().expect("tempdir");
    let changed = 6;
    let denser = write_tiles(other.path(), 75_000);
    std::fs::copy(&denser[changed], &files[changed]).expect("copy");
    let report = change(
        &store,
        &files,
        &[changed],
        std::slice::from_ref(&files[changed]),
        &options,
    )
    .expect("update");
    assert!(report.points_added > report.points_removed, "{report:?}");
    assert_like_a_fresh_build(&store, &files, &options);
}

#[test]
fn a_removed_file_overlapping_others_reads_only_those_again() {
    // Each tile in two files of every other point: they share their box.
    let (_dir, _db, files, store, options) = tile_scene(40_000, 2);
    build(&files, &store, &options);
    let gone = 2 * 5 + 1;
    let report = change(&store, &files, &[gone], &[], &options).expect("update");
    assert_eq!(report.files_reread, 1, "{report:?}");
    assert_like_a_fresh_build(&store, &without(&files, &[gone]), &options);
}

#[test]
fn a_store_without_file_facts_is_refused_a_removal() {
    let (_dir, _db, files, store, options) = tile_scene(8_000, 1);
    let built = build(&files, &store, &options);
    // What a store of an earlier version keeps: regions without the files' facts.
    let mut regions = store.read_regions().expect("read").expect("regions");
    regions.file_facts = None;
    store
        .write_hierarchy_with(&built.hierarchy, Some(&regions))
        .expect("write");
    let error = change(&store, &files, &[3], &[], &options).expect_err("refused");
    assert!(matches!(error, LodError::CannotUpdate(_)), "{error}");
    assert!(error.to_string().contains("does not record"), "{error}");
    assert_eq!(store_points(&store), file_points(&files));
    // Every file removed leaves nothing to update.
    let every: Vec<usize> = (0..files.len()).collect();
    build(&files, &store, &options);
    let error = change(&store, &files, &every, &[], &options).expect_err("refused");
    assert!(
        error.to_string().contains("no point would remain"),
        "{error}"
    );
}

//! Store updates end to end: LAS tiles written here, a store built from some of them, then
//! updated with the rest, checked point for point against the tiles.

use std::path::{Path, PathBuf};

use glam::DVec3;

use super::super::*;
use super::temp_store;
use crate::cloud::{bounds_of, PointCloud};
use crate::ingest::{write_las, DatasetSource, LasWriteOptions};

/// Tiles per axis of the test scene.
const TILES: usize = 4;

/// The tiles of one scene, `TILES` x `TILES` squares of its ground plan, as LAS files in
/// `dir` sharing one grid (the scene's origin and millimetres); file `ty * TILES + tx`.
pub(super) fn write_tiles(dir: &Path, points: usize) -> Vec<PathBuf> {
    write_tile_parts(dir, points, 1)
}

/// [`write_tiles`], each tile as `parts` files of every `parts`-th of its points, which fill
/// the same box; file `(ty * TILES + tx) * parts + part`.
pub(super) fn write_tile_parts(dir: &Path, points: usize, parts: usize) -> Vec<PathBuf> {
    let scene = crate::sample::sample_scene(points, 7);
    let (min, max) = (scene.bounds.min, scene.bounds.max);
    let size = (max - min) / TILES as f64;
    let tile_of = |p: DVec3| {
        let t = ((p - min) / size).floor();
        let clamp = |v: f64| (v.max(0.0) as usize).min(TILES - 1);
        clamp(t.y) * TILES + clamp(t.x)
    };
    let mut files = Vec::new();
    for file in 0..TILES * TILES * parts {
        let (tile, part) = (file / parts, file % parts);
        let keep: Vec<usize> = (0..scene.len())
            .filter(|&i| tile_of(scene.origin + scene.positions[i].as_dvec3()) == tile)
            .enumerate()
            .filter(|(n, _)| n % parts == part)
            .map(|(_, i)| i)
            .collect();
        let mut cloud = PointCloud::with_capacity(
            scene.origin,
            bounds_of(
                keep.iter()
                    .map(|&i| scene.origin + scene.positions[i].as_dvec3()),
            ),
            scene.color_source,
            keep.len(),
        );
        for &i in &keep {
            cloud.positions.push(scene.positions[i]);
            cloud.colors.push(scene.colors[i]);
            cloud.intensity.push(scene.intensity[i]);
            cloud.classification.push(scene.classification[i]);
            cloud.return_number.push(scene.return_number[i]);
        }
        let path = match parts {
            1 => dir.join(format!("tile-{tile:02}.las")),
            _ => dir.join(format!("tile-{tile:02}-{part}.las")),
        };
        write_las(&path, &cloud, &LasWriteOptions::default()).expect("write tile");
        files.push(path);
    }
    files
}

/// A point as a multiset entry: its position on the millimetre grid, attributes and row.
type Entry = ([i64; 3], [u16; 3], u16, u8, u8, Vec<u8>);

fn entry(p: DVec3, rgb: [u16; 3], intensity: u16, class: u8, ret: u8, row: &[u8]) -> Entry {
    let mm = (p * 1000.0).round();
    (
        [mm.x as i64, mm.y as i64, mm.z as i64],
        rgb,
        intensity,
        class,
        ret,
        row.to_vec(),
    )
}

/// Every point of `files`, sorted.
pub(super) fn file_points(files: &[PathBuf]) -> Vec<Entry> {
    let source = DatasetSource::open(files).expect("open");
    let row_bytes = source.attributes().map_or(0, |a| a.row_bytes());
    let mut out = Vec::new();
    source
        .for_each_batch(&mut |b| {
            for i in 0..b.len() {
                let p = b.raw_point(i);
                let row = b.row(i, row_bytes);
                out.push(entry(
                    p.position,
                    p.rgb,
                    p.intensity,
                    p.classification,
                    p.return_number,
                    row,
                ));
            }
            Ok(())
        })
        .expect("read");
    out.sort();
    out
}

/// Every point the store's nodes hold, sorted; checks each node's bound on the way.
pub(super) fn store_points(store: &LodStore) -> Vec<Entry> {
    let hierarchy = store.read_hierarchy().expect("hierarchy");
    let row_bytes = hierarchy.attributes().map_or(0, |a| a.row_bytes());
    let mut out = Vec::new();
    for info in hierarchy.stored_nodes() {
        let node = store.read_node(&hierarchy, info.key).expect("node");
        if info.is_leaf() {
            assert!(info.point_count <= hierarchy.max_leaf_points, "{info:?}");
        }
        let sections = store
            .read_attribute_sections(row_bytes, std::slice::from_ref(info))
            .expect("attributes");
        let rgb = node.rgb.clone().unwrap_or_else(|| vec![[0; 3]; node.len()]);
        for (i, p) in node.world_positions().into_iter().enumerate() {
            let row = &sections[0][i * row_bytes..(i + 1) * row_bytes];
            let (class, ret) = (node.classification[i], node.return_number[i]);
            out.push(entry(p, rgb[i], node.intensity[i], class, ret, row));
        }
    }
    out.sort();
    out
}

/// A scene's tiles written into a folder of their own, with an empty store (and its
/// database, kept open) and the build's options there.
pub(super) type TileScene = (
    tempfile::TempDir,
    sled::Db,
    Vec<PathBuf>,
    LodStore,
    LodBuildOptions,
);

/// The [`TileScene`] of `points` points, each tile in `parts` files ([`write_tile_parts`]).
pub(super) fn tile_scene(points: usize, parts: usize) -> TileScene {
    let dir = tempfile::tempdir().expect("tempdir");
    let files = write_tile_parts(dir.path(), points, parts);
    let (db, store) = temp_store(dir.path());
    let options = options(dir.path());
    (dir, db, files, store, options)
}

pub(super) fn options(dir: &Path) -> LodBuildOptions {
    let mut options = LodBuildOptions::new(dir.join("spill"));
    options.max_leaf_points = 400;
    options.max_partition_points = 3_000;
    options.memory_budget_bytes = options.min_memory_budget_bytes();
    options
}

pub(super) fn build(
    files: &[PathBuf],
    store: &LodStore,
    options: &LodBuildOptions,
) -> LodBuildReport {
    let source = DatasetSource::open(files).expect("open");
    build_lod(&source, store, options).expect("build")
}

fn update(added: &[PathBuf], store: &LodStore, options: &LodBuildOptions) -> LodUpdateReport {
    let source = DatasetSource::open(added).expect("open added");
    update_lod(store, &source, vec!["files now".into()], options).expect("update")
}

#[test]
fn an_added_tile_rebuilds_only_the_regions_it_reaches_and_keeps_every_point_once() {
    let (_dir, _db, files, store, options) = tile_scene(60_000, 1);
    // An inner tile is the new day's: the others span the cube.
    let new_tile = TILES + 1;
    let before: Vec<PathBuf> = (0..files.len())
        .filter(|&t| t != new_tile)
        .map(|t| files[t].clone())
        .collect();
    let built = build(&before, &store, &options);
    assert!(built.partitions > 4, "{} partitions", built.partitions);
    let regions = store.read_regions().expect("read").expect("regions kept");
    assert_eq!(
        regions.regions.iter().map(|r| r.points).sum::<u64>(),
        built.hierarchy.point_count
    );
    assert!(regions.grid.is_some());

    let report = update(&[files[new_tile].clone()], &store, &options);
    assert!(report.points_added > 0);
    assert!(report.regions_rebuilt + report.regions_added > 0);
    assert!(report.regions_kept > report.regions_rebuilt, "{report:?}");
    assert_eq!(store_points(&store), file_points(&files));

    // Against a fresh build of all the tiles: the same points, statistics and bounds on
    // nodes, and about as many nodes.
    let fresh_dir = tempfile::tempdir().expect("tempdir");
    let (_fresh_db, fresh) = temp_store(fresh_dir.path());
    let fresh_report = build(&files, &fresh, &options);
    let updated = store.read_hierarchy().expect("hierarchy");
    assert_eq!(updated.point_count, fresh_report.hierarchy.point_count);
    assert_eq!(updated.stats, fresh_report.hierarchy.stats);
    let (a, b) = (updated.nodes().len(), fresh_report.hierarchy.nodes().len());
    assert!(a.abs_diff(b) * 10 <= b, "{a} nodes updated, {b} fresh");
    assert!(
        report.stored_bytes * 2 < fresh_report.stored_bytes,
        "{} bytes appended, a fresh build stores {}",
        report.stored_bytes,
        fresh_report.stored_bytes
    );
}

#[test]
fn updates_follow_one_another_and_fill_empty_parts_of_the_cube() {
    let (_dir, _db, files, store, options) = tile_scene(40_000, 1);
    // The corner tile lies within the others' cube (their bounds reach its x and y), in a
    // part of it no region holds; the inner one is added after it.
    let (corner, inner) = (0, 2 * TILES + 2);
    let first: Vec<PathBuf> = (0..files.len())
        .filter(|&t| t != corner && t != inner)
        .map(|t| files[t].clone())
        .collect();
    build(&first, &store, &options);
    let report = update(&[files[corner].clone()], &store, &options);
    assert!(report.regions_added > 0, "{report:?}");
    let report = update(&[files[inner].clone()], &store, &options);
    assert!(report.dead_bytes > 0, "replaced nodes leave dead bytes");
    assert_eq!(store_points(&store), file_points(&files));
}

#[test]
fn points_outside_the_cube_are_refused_and_the_store_is_left_as_it_was() {
    let (dir, _db, files, store, options) = tile_scene(20_000, 1);
    build(&files, &store, &options);
    let before = store.read_hierarchy().expect("hierarchy");
    // The scene again, 10 km east: beyond the cube's side.
    let mut far = crate::sample::sample_scene(2_000, 9);
    far.origin += DVec3::new(10_000.0, 0.0, 0.0);
    far.bounds.min += DVec3::new(10_000.0, 0.0, 0.0);
    far.bounds.max += DVec3::new(10_000.0, 0.0, 0.0);
    let far_file = dir.path().join("far.las");
    write_las(&far_file, &far, &LasWriteOptions::default()).expect("write");
    let source = DatasetSource::open(&[far_file]).expect("open");
    let error = update_lod(&store, &source, Vec::new(), &options).expect_err("refused");
    assert!(matches!(error, LodError::CannotUpdate(_)), "{error}");
    assert!(
        error.to_string().contains("outside the store's cube"),
        "{error}"
    );
    assert_eq!(store.read_hierarchy().expect("hierarchy"), before);
    assert_eq!(store_points(&store), file_points(&files));
}

#[test]
fn a_store_without_regions_is_refused() {
    let (_dir, _db, files, store, options) = tile_scene(8_000, 1);
    let built = build(&files[1..], &store, &options);
    // What a resumed build leaves: the hierarchy alone.
    store.write_hierarchy(&built.hierarchy).expect("write");
    let source = DatasetSource::open(&files[..1]).expect("open");
    let error = update_lod(&store, &source, Vec::new(), &options).expect_err("refused");
    assert!(error.to_string().contains("keeps no regions"), "{error}");
}

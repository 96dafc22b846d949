//! A dataset of many files loads as the one file they were cut from: the same origin, bounds,
//! colors and points, so it renders the same image.

use std::path::{Path, PathBuf};

use crate::camera::Camera;
use crate::cloud::{ColorSource, PointCloud};
use crate::ingest::{load_dataset, load_point_cloud, write_las, IngestError, LasWriteOptions};
use crate::raster::{FrameSettings, Renderer};
use crate::sample::sample_scene;
use crate::testing::{gpu, shared_data, write_empty_files};

/// The points of `cloud` as sortable records: world position bits, color and attributes.
fn records(cloud: &PointCloud) -> Vec<([u64; 3], u32, u16, u8, u8)> {
    let mut records: Vec<_> = (0..cloud.len())
        .map(|i| {
            let world = cloud.origin + cloud.positions[i].as_dvec3();
            (
                [world.x.to_bits(), world.y.to_bits(), world.z.to_bits()],
                cloud.colors[i],
                cloud.intensity[i],
                cloud.classification[i],
                cloud.return_number[i],
            )
        })
        .collect();
    records.sort_unstable();
    records
}

/// Writes `cloud` cut into `columns` x `rows` tiles on x and y (empty tiles left out), each
/// with `options`; returns their paths.
fn write_tiles(
    cloud: &PointCloud,
    dir: &Path,
    (columns, rows): (usize, usize),
    options: &[LasWriteOptions],
) -> Vec<PathBuf> {
    let size = cloud.bounds.size();
    let cell = |value: f64, min: f64, extent: f64, cells: usize| {
        (((value - min) / extent * cells as f64) as usize).min(cells - 1)
    };
    let mut tiles = vec![Vec::new(); columns * rows];
    for (i, position) in cloud.positions.iter().enumerate() {
        let world = cloud.origin + position.as_dvec3();
        let column = cell(world.x, cloud.bounds.min.x, size.x, columns);
        let row = cell(world.y, cloud.bounds.min.y, size.y, rows);
        tiles[row * columns + column].push(i);
    }
    tiles
        .iter()
        .filter(|indices| !indices.is_empty())
        .enumerate()
        .map(|(n, indices)| {
            let options = &options[n % options.len()];
            let extension = if n % 2 == 0 { "laz" } else { "las" };
            let path = dir.join(format!("tile_{n:02}.{extension}"));
            write_las(&path, &cloud.select(indices), options).expect("write tile");
            path
        })
        .collect()
}

fn render(cloud: &PointCloud) -> image::RgbaImage {
    let mut renderer = Renderer::new(gpu());
    let resident = renderer.upload(cloud).expect("upload");
    let camera = Camera::auto(&cloud.bounds, 4.0 / 3.0);
    renderer
        .render(&resident, &FrameSettings::new(160, 120, camera))
        .expect("render")
        .image
}

fn assert_same_cloud(tiles: &PointCloud, whole: &PointCloud) {
    assert_eq!(tiles.len(), whole.len());
    assert_eq!(tiles.origin, whole.origin);
    assert_eq!(tiles.bounds, whole.bounds);
    assert_eq!(tiles.color_source, whole.color_source);
    assert!(
        records(tiles) == records(whole),
        "the tiles hold other points"
    );
    assert!(
        render(tiles) == render(whole),
        "the tiles render differently"
    );
}

#[test]
fn tiles_of_a_scene_load_and_render_as_the_whole_file() {
    let dir = tempfile::tempdir().expect("tempdir");
    let scene = sample_scene(40_000, 11);
    let whole_path = dir.path().join("whole.las");
    write_las(&whole_path, &scene, &LasWriteOptions::default()).expect("write whole");
    let whole = load_point_cloud(&whole_path).expect("load whole");
    // The same scale and offset in every tile, in LAS 1.2 and 1.4 and LAS and LAZ alike.
    let versions = [
        LasWriteOptions::default(),
        LasWriteOptions {
            version: (1, 4),
            point_format: 7,
            ..LasWriteOptions::default()
        },
    ];
    let tiles = write_tiles(&whole, dir.path(), (3, 2), &versions);
    assert!(tiles.len() >= 4, "{} tiles", tiles.len());
    let loaded = load_dataset(&tiles).expect("load tiles");
    assert_same_cloud(&loaded, &whole);
}

#[test]
fn tiles_of_a_real_scan_render_as_the_scan() {
    let Some(scan) = shared_data("autzen_trim.laz") else {
        eprintln!("skipped: shared/data/autzen_trim.laz is not in this checkout");
        return;
    };
    let dir = tempfile::tempdir().expect("tempdir");
    let whole = load_point_cloud(&scan).expect("load scan");
    // Rewritten at the file's own 0.01 scale, so the tiles hold its very coordinates.
    let options = LasWriteOptions {
        scale: 0.01,
        ..LasWriteOptions::default()
    };
    let whole_path = dir.path().join("whole.laz");
    write_las(&whole_path, &whole, &options).expect("write");
    let whole = load_point_cloud(&whole_path).expect("load rewritten");
    let tiles = write_tiles(&whole, dir.path(), (2, 2), &[options]);
    let loaded = load_dataset(&tiles).expect("load tiles");
    assert_same_cloud(&loaded, &whole);
}

#[test]
fn files_of_other_scales_formats_and_colors_mix() {
    let dir = tempfile::tempdir().expect("tempdir");
    let scene = sample_scene(20_000, 5);
    let half = scene.len() / 2;
    let first: Vec<usize> = (0..half).collect();
    let second: Vec<usize> = (half..scene.len()).collect();
    let a = dir.path().join("a.laz");
    let b = dir.path().join("b.las");
    write_las(&a, &scene.select(&first), &LasWriteOptions::default()).expect("a");
    // No RGB in the second file: the dataset falls back to intensity for every point.
    let b_options = LasWriteOptions {
        version: (1, 4),
        point_format: 6,
        scale: 0.0001,
    };
    write_las(&b, &scene.select(&second), &b_options).expect("b");
    let loaded = load_dataset(&[a.clone(), b.clone()]).expect("load");
    assert_eq!(loaded.len(), scene.len());
    assert_ne!(loaded.color_source, ColorSource::Rgb16);
    assert_ne!(loaded.color_source, ColorSource::Rgb8In16Bit);
    let slack = glam::DVec3::splat(0.002);
    assert!((loaded.bounds.min - scene.bounds.min)
        .abs()
        .cmple(slack)
        .all());
    assert!((loaded.bounds.max - scene.bounds.max)
        .abs()
        .cmple(slack)
        .all());
    let with_color = load_dataset(std::slice::from_ref(&a)).expect("a alone");
    assert!(matches!(
        with_color.color_source,
        ColorSource::Rgb16 | ColorSource::Rgb8In16Bit
    ));
}

#[test]
fn a_bad_file_fails_the_dataset_naming_it() {
    let dir = tempfile::tempdir().expect("tempdir");
    let good = dir.path().join("good.las");
    write_las(&good, &sample_scene(1_000, 2), &LasWriteOptions::default()).expect("good");
    let bad = dir.path().join("bad.laz");
    std::fs::write(&bad, b"LASF but not really").expect("bad");
    let error = load_dataset(&[good.clone(), bad.clone()]).expect_err("bad tile");
    assert!(error.to_string().contains("bad.laz"), "{error}");
    assert!(matches!(load_dataset(&[]), Err(IngestError::NoFiles)));
}

#[test]
fn empty_files_in_a_dataset_change_nothing() {
    use crate::lod::PointSource;
    let dir = tempfile::tempdir().expect("tempdir");
    let scene = sample_scene(20_000, 7);
    let tiles = write_tiles(&scene, dir.path(), (2, 2), &[LasWriteOptions::default()]);
    // Without RGB, at other scales, in LAS 1.4 too: were they to decide, the color, the
    // grid and the attributes would change.
    let empties = write_empty_files(dir.path(), &["empty_0.laz", "empty_1.las"]);
    // An empty file first, where the first file used to decide the grid.
    let mut with_empties = empties.clone();
    with_empties.insert(1, tiles[0].clone());
    with_empties.extend(tiles[1..].iter().cloned());

    let alone = load_dataset(&tiles).expect("tiles");
    let mixed = load_dataset(&with_empties).expect("tiles and empty files");
    assert_same_cloud(&mixed, &alone);

    let alone = crate::ingest::DatasetSource::open(&tiles).expect("source of tiles");
    let mixed = crate::ingest::DatasetSource::open(&with_empties).expect("mixed source");
    assert_eq!(mixed.point_count(), alone.point_count());
    assert_eq!(mixed.bounds(), alone.bounds());
    assert_eq!(mixed.attributes(), alone.attributes());
    assert!(
        alone.position_grid().is_some(),
        "tiles of one grid share it"
    );
    assert_eq!(mixed.position_grid(), alone.position_grid());
    // One part a file, the empty ones empty, so a store's parts stay its file list's.
    assert_eq!(mixed.part_starts().len(), with_empties.len());
}

#[test]
fn a_dataset_of_empty_files_is_an_error_naming_them() {
    let dir = tempfile::tempdir().expect("tempdir");
    let empties = write_empty_files(dir.path(), &["empty_0.laz", "empty_1.las"]);
    match load_dataset(&empties[..1]) {
        Err(IngestError::NoPoints { path }) => assert_eq!(path, empties[0]),
        other => panic!("expected no points, got {:?}", other.map(|c| c.len())),
    }
    let error = load_dataset(&empties).expect_err("no points");
    assert!(
        matches!(error, IngestError::NoPointsInFiles { files: 2 }),
        "{error}"
    );
    // A preview sample of them says the same.
    assert!(crate::ingest::sample_chunk_starts(&empties).is_err());
}

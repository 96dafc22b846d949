//! Clouds and files shared by the ingest tests.

use std::path::{Path, PathBuf};

use glam::DVec3;

use crate::cloud::{pack_rgba8, PointCloud};
use crate::ingest::{load_point_cloud, write_las, IngestError, LasWriteOptions};

/// A small cloud in survey-like coordinates with varied attributes; its coordinates are on
/// the millimetre grid, so a file written at scale 0.001 stores them exactly.
pub(super) fn test_cloud(points: usize) -> PointCloud {
    let world: Vec<DVec3> = (0..points)
        .map(|i| {
            let i = i as f64;
            DVec3::new(
                636_000.0 + (i * 0.731).rem_euclid(40.0),
                849_000.0 + (i * 1.913).rem_euclid(25.0),
                120.0 + (i * 0.057).rem_euclid(9.0),
            )
        })
        .map(|p| (p * 1000.0).round() / 1000.0)
        .collect();
    let colors = (0..points)
        .map(|i| pack_rgba8((i * 7) as u8, (i * 13 + 50) as u8, (255 - i % 256) as u8))
        .collect();
    let mut cloud = PointCloud::from_world_points(&world, colors);
    cloud.intensity = (0..points).map(|i| (i * 37 % 4000) as u16).collect();
    cloud.classification = (0..points).map(|i| [1, 2, 5, 6][i % 4]).collect();
    cloud.return_number = (0..points).map(|i| (i % 3 + 1) as u8).collect();
    cloud
}

pub(super) fn world_positions(cloud: &PointCloud) -> impl Iterator<Item = DVec3> + '_ {
    cloud.positions.iter().map(|p| cloud.origin + p.as_dvec3())
}

pub(super) fn max_position_error(a: &PointCloud, b: &PointCloud) -> f64 {
    world_positions(a)
        .zip(world_positions(b))
        .map(|(a, b)| (a - b).abs().max_element())
        .fold(0.0, f64::max)
}

pub(super) fn file_name(path: &Path) -> String {
    path.file_name()
        .map(|name| name.to_string_lossy().into_owned())
        .unwrap_or_default()
}

/// Loads a file that must fail, and checks that the message names it.
pub(super) fn load_error(path: &Path) -> IngestError {
    let error = match load_point_cloud(path) {
        Ok(cloud) => panic!(
            "{} loaded {} points, expected an error",
            path.display(),
            cloud.len()
        ),
        Err(error) => error,
    };
    let message = error.to_string();
    assert!(
        message.contains(&file_name(path)),
        "message does not name the file: {message}"
    );
    error
}

/// Loads a file that must fail as corrupt (naming the file), and gives what is corrupt.
pub(super) fn corrupt_message(path: &Path) -> String {
    match load_error(path) {
        IngestError::Corrupt { what, .. } => what,
        other => panic!("expected a corrupt-file error, got {other}"),
    }
}

pub(super) fn write(
    dir: &Path,
    name: &str,
    cloud: &PointCloud,
    options: &LasWriteOptions,
) -> PathBuf {
    let path = dir.join(name);
    write_las(&path, cloud, options).expect("write test file");
    path
}

/// A LAS 1.4 file of `points` points in `point_format`: its path and its bytes.
pub(super) fn written_1_4(
    dir: &Path,
    name: &str,
    points: usize,
    point_format: u8,
) -> (PathBuf, Vec<u8>) {
    let options = LasWriteOptions {
        version: (1, 4),
        point_format,
        scale: 0.001,
    };
    let path = write(dir, name, &test_cloud(points), &options);
    let bytes = std::fs::read(&path).expect("read back");
    (path, bytes)
}

/// `write` with the default options (`LasWriteOptions::default`); LAZ where `name` ends in `.laz`.
pub(super) fn write_default(dir: &Path, name: &str, cloud: &PointCloud) -> PathBuf {
    write(dir, name, cloud, &LasWriteOptions::default())
}

/// A test file of `points` points written with the default options, to be cut or patched:
/// its path and its bytes.
pub(super) fn file_to_cut(dir: &Path, name: &str, points: usize) -> (PathBuf, Vec<u8>) {
    let path = write_default(dir, name, &test_cloud(points));
    let bytes = std::fs::read(&path).expect("read back");
    (path, bytes)
}

// Byte offsets of header fields patched below (LAS 1.0–1.4 public header block).
pub(super) const VERSION_MINOR_OFFSET: usize = 25;
/// Header offset of the offset to the point data.
pub(super) const OFFSET_TO_POINT_DATA: usize = 96;
/// Header offset of the x scale factor; y, z and the offsets follow 8 bytes apart.
pub(super) const X_SCALE_OFFSET: usize = 131;

pub(super) const LEGACY_POINT_COUNT_OFFSET: usize = 107;

pub(super) const POINT_COUNT_OFFSET_1_4: usize = 247;

/// The real scans in `shared/data` next to the repository, if this checkout has them.
pub(super) fn shared_data_dir() -> Option<PathBuf> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data");
    dir.is_dir().then_some(dir)
}

//! Helpers for tests, this crate's and (with the `testing` feature) other crates': one shared
//! GPU, image comparison with diff output, the location of the real scans, and a generated
//! terrain exported as a COPC file.

use std::path::{Path, PathBuf};
use std::sync::{Arc, OnceLock};

use image::RgbaImage;

use glam::DVec3;

use crate::camera::{Camera, Projection};
use crate::gpu::{AdapterChoice, GpuContext};

/// One GPU context for all tests of the process (device creation is slow on lavapipe).
/// Fails loudly when there is no adapter: the renderer's tests must not pass by skipping.
pub fn gpu() -> Arc<GpuContext> {
    static GPU: OnceLock<Arc<GpuContext>> = OnceLock::new();
    GPU.get_or_init(|| {
        let choice = AdapterChoice::from_env().expect("valid POINTFARM_ADAPTER");
        let gpu = GpuContext::new(choice).unwrap_or_else(|e| {
            panic!("GPU tests need an adapter (run deploy/setup.sh for lavapipe): {e}")
        });
        eprintln!("testing on {}", gpu.describe());
        Arc::new(gpu)
    })
    .clone()
}

/// A Z-up perspective camera at `position` looking at `target`, with a vertical field of view
/// of `fov_y_deg` and the clip planes `(near, far)`.
pub fn perspective_camera(
    position: DVec3,
    target: DVec3,
    fov_y_deg: f64,
    clip: (f64, f64),
) -> Camera {
    Camera {
        position,
        target,
        up: DVec3::Z,
        projection: Projection::Perspective { fov_y_deg },
        near: clip.0,
        far: clip.1,
    }
}

/// An orthographic camera `altitude` above `target`, looking straight down with +Y up the
/// image, `height` world units high, with the clip planes `(near, far)`.
pub fn top_down_camera(target: DVec3, altitude: f64, height: f64, clip: (f64, f64)) -> Camera {
    Camera {
        position: target + DVec3::new(0.0, 0.0, altitude),
        target,
        up: DVec3::Y,
        projection: Projection::Orthographic { height },
        near: clip.0,
        far: clip.1,
    }
}

/// A COPC file of the repository's test data (`tests/data/copc`).
pub fn copc_file(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../tests/data/copc")
        .join(name)
}

/// `../shared/data` next to the repository, or None (with a message) when it is absent.
pub fn shared_data(file: &str) -> Option<PathBuf> {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../../shared/data")
        .join(file);
    if path.is_file() {
        Some(path)
    } else {
        eprintln!(
            "skipped: {} not found (the real scans live in ../shared/data)",
            path.display()
        );
        None
    }
}

/// How two images differ.
#[derive(Debug, Clone, Copy)]
pub struct ImageDiff {
    pub pixels: usize,
    pub differing: usize,
}

impl ImageDiff {
    pub fn equal_fraction(&self) -> f64 {
        1.0 - self.differing as f64 / self.pixels as f64
    }
}

/// Largest difference of any channel of any pixel.
pub fn max_channel_difference(a: &RgbaImage, b: &RgbaImage) -> u8 {
    a.as_raw()
        .iter()
        .zip(b.as_raw())
        .map(|(x, y)| x.abs_diff(*y))
        .max()
        .unwrap_or(0)
}

/// Compares two images pixel by pixel. When they differ, writes `<name>-actual.png`,
/// `<name>-expected.png` and `<name>-diff.png` (differing pixels in magenta) to
/// `target/test-output/` so a failure can be looked at.
pub fn compare_images(name: &str, actual: &RgbaImage, expected: &RgbaImage) -> ImageDiff {
    compare_images_within(name, actual, expected, 0)
}

/// Like [`compare_images`], counting only pixels where some channel differs by more than
/// `tolerance` levels (magenta in the diff image; smaller differences in yellow).
pub fn compare_images_within(
    name: &str,
    actual: &RgbaImage,
    expected: &RgbaImage,
    tolerance: u8,
) -> ImageDiff {
    assert_eq!(
        actual.dimensions(),
        expected.dimensions(),
        "{name}: image sizes differ"
    );
    let mut diff = RgbaImage::new(actual.width(), actual.height());
    let mut differing = 0;
    for ((a, e), d) in actual
        .pixels()
        .zip(expected.pixels())
        .zip(diff.pixels_mut())
    {
        let largest = (0..4).map(|c| a.0[c].abs_diff(e.0[c])).max().unwrap_or(0);
        if largest > tolerance {
            differing += 1;
            d.0 = [255, 0, 255, 255];
        } else if largest > 0 {
            d.0 = [255, 255, 0, 255];
        } else {
            let grey = (e.0[0] as u16 + e.0[1] as u16 + e.0[2] as u16) / 6;
            d.0 = [grey as u8, grey as u8, grey as u8, 255];
        }
    }
    if differing > 0 {
        let dir = test_output_dir();
        if std::fs::create_dir_all(&dir).is_ok() {
            let _ = actual.save(dir.join(format!("{name}-actual.png")));
            let _ = expected.save(dir.join(format!("{name}-expected.png")));
            let _ = diff.save(dir.join(format!("{name}-diff.png")));
            eprintln!(
                "{name}: {differing} pixels differ by more than {tolerance}; images in {}",
                dir.display()
            );
        }
    }
    ImageDiff {
        pixels: (actual.width() * actual.height()) as usize,
        differing,
    }
}

/// Where failing image comparisons leave their images.
pub fn test_output_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../target/test-output")
}

/// The world positions of the points `las` read, in f64, as the file stores them.
pub fn las_world_positions(points: &las::PointData) -> Vec<DVec3> {
    let xyz = points.x().zip(points.y()).zip(points.z());
    xyz.map(|((x, y), z)| DVec3::new(x, y, z)).collect()
}

/// A generated terrain's store and the COPC file exported from it.
pub struct ExportedTerrain {
    _db: sled::Db,
    pub store: crate::lod::LodStore,
    pub hierarchy: crate::lod::LodHierarchy,
    pub path: PathBuf,
}

/// A generated terrain of `points` built in `dir` with leaves of at most `max_leaf_points`
/// and exported as `dir/terrain.copc.laz`.
pub fn exported_terrain(dir: &Path, points: u64, max_leaf_points: usize) -> ExportedTerrain {
    use crate::lod::copc_export::{export_copc, ExportSettings};
    use crate::lod::{build_lod, GeneratedSource, LodBuildOptions, LodStore};

    let source = GeneratedSource::terrain(points, 7);
    let db = sled::open(dir.join("db")).expect("sled");
    let store =
        LodStore::open(db.open_tree("lod").expect("tree"), dir.join("lod.bin")).expect("store");
    let mut options = LodBuildOptions::new(dir.join("spill"));
    options.max_leaf_points = max_leaf_points;
    let hierarchy = build_lod(&source, &store, &options)
        .expect("build")
        .hierarchy;
    let path = dir.join("terrain.copc.laz");
    let settings = ExportSettings::fixed(&hierarchy.cube);
    export_copc(&hierarchy, &store, &settings, &path, &mut |_| {}).expect("export");
    ExportedTerrain {
        _db: db,
        store,
        hierarchy,
        path,
    }
}

/// Writes `count` LAZ tiles `t1.laz`, `t2.laz`, ... of `points`-point generated scenes (one
/// seed a tile) into `dir`, made if missing: a generated campaign of several files.
pub fn write_scene_tiles(dir: &Path, points: usize, count: u64) -> Vec<PathBuf> {
    use crate::ingest::{write_las, LasWriteOptions};
    use crate::sample::sample_scene;

    std::fs::create_dir_all(dir).expect("the tiles' folder");
    (1..=count)
        .map(|seed| {
            let path = dir.join(format!("t{seed}.laz"));
            let scene = sample_scene(points, seed);
            write_las(&path, &scene, &LasWriteOptions::default()).expect("tile");
            path
        })
        .collect()
}

/// Files that declare no points (empty tiles) at `names` in `dir`, alternately LAS 1.4
/// format 6 at centimetres and LAS 1.2 format 0 at millimetres: other versions, formats and
/// scales than [`write_scene_tiles`]' and most tests' files, without RGB, so that a file
/// without points that decided anything for its dataset would change it.
pub fn write_empty_files(dir: &Path, names: &[&str]) -> Vec<PathBuf> {
    use crate::ingest::{write_las, LasWriteOptions};
    use crate::sample::sample_scene;

    let empty = sample_scene(100, 1).select(&[]);
    let options = [
        LasWriteOptions {
            version: (1, 4),
            point_format: 6,
            scale: 0.01,
        },
        LasWriteOptions {
            point_format: 0,
            ..LasWriteOptions::default()
        },
    ];
    (names.iter().zip(options.iter().cycle()))
        .map(|(name, options)| {
            let path = dir.join(name);
            write_las(&path, &empty, options).expect("an empty file");
            path
        })
        .collect()
}

/// How [`laz_of_las`] cuts a file's points into LAZ chunks.
pub enum LazChunks<'a> {
    /// Chunks of this many points (the `las` writer's are always 50,000).
    Fixed(u32),
    /// Chunks of these many points each, recorded in the chunk table (as COPC's are).
    Variable(&'a [usize]),
}

/// `las`, an uncompressed LAS file without VLRs, compressed as point-wise LAZ in `chunks`.
pub fn laz_of_las(las: &[u8], chunks: LazChunks<'_>) -> Vec<u8> {
    use std::io::{Cursor, Seek, SeekFrom};
    let u32_at = |at: usize| u32::from_le_bytes(las[at..at + 4].try_into().expect("4 bytes"));
    let data_start = u32_at(96) as usize;
    assert_eq!(u32_at(100), 0, "a file without VLRs");
    let format = las[104];
    let record_len = u16::from_le_bytes([las[105], las[106]]);
    let format_len = las::point::Format::new(format).expect("point format").len();
    let builder = laz::LazVlrBuilder::default()
        .with_point_format(format, record_len - format_len)
        .expect("items");
    let vlr = match chunks {
        LazChunks::Fixed(points) => builder.with_fixed_chunk_size(points),
        LazChunks::Variable(_) => builder.with_variable_chunk_size(),
    }
    .build();
    let mut vlr_data = Vec::new();
    vlr.write_to(&mut vlr_data).expect("VLR");
    let mut prefix = las[..data_start].to_vec();
    prefix.extend(0u16.to_le_bytes());
    let mut user_id = [0u8; 16];
    user_id[..14].copy_from_slice(b"laszip encoded");
    prefix.extend(user_id);
    prefix.extend(22204u16.to_le_bytes());
    prefix.extend(
        u16::try_from(vlr_data.len())
            .expect("VLR size")
            .to_le_bytes(),
    );
    prefix.extend([0u8; 32]);
    prefix.extend(&vlr_data);
    let new_start = u32::try_from(prefix.len()).expect("offset");
    prefix[96..100].copy_from_slice(&new_start.to_le_bytes());
    prefix[100..104].copy_from_slice(&1u32.to_le_bytes());
    prefix[104] = format | 0x80;
    // The compressor writes the chunk table's absolute offset: it starts after the prefix.
    let mut out = Cursor::new(prefix);
    out.seek(SeekFrom::End(0)).expect("seek");
    let mut compressor = laz::LasZipCompressor::new(&mut out, vlr).expect("compressor");
    let records = &las[data_start..];
    match chunks {
        LazChunks::Fixed(_) => compressor.compress_many(records).expect("compress"),
        LazChunks::Variable(counts) => {
            let mut points = records.chunks_exact(usize::from(record_len));
            for &count in counts {
                for point in points.by_ref().take(count) {
                    compressor.compress_one(point).expect("compress");
                }
                compressor.finish_current_chunk().expect("chunk");
            }
        }
    }
    compressor.done().expect("done");
    drop(compressor);
    out.into_inner()
}

//! Cuts rendered on the GPU against the resident cloud of the same file, cold and warm caches,
//! the budgets, the read-ahead, a damaged node, point sizes and weights; the fixtures they
//! share.

mod caches;
mod coarse;
mod exact;
mod pixel_error;
mod point_sizes;
mod weights;

use std::path::Path;

use super::*;
use crate::camera::{Camera, Projection};
use crate::cloud::PointCloud;
use crate::color::ColorMode;
use crate::ingest::{load_point_cloud, write_las, DatasetSource, LasWriteOptions};
use crate::lod::{build_lod, LodBuildOptions, LodStore, PointSource};
use crate::raster::{FillSettings, Quality, Shading};
use crate::request::{PointSize, RenderOptions};
use crate::sample::sample_scene;
use crate::testing::{compare_images_within, gpu};

struct Fixture {
    _dir: tempfile::TempDir,
    cloud: PointCloud,
    store: LodStore,
    dataset: LodDataset,
}

fn open_store(dir: &Path) -> LodStore {
    let db = sled::open(dir.join("db")).expect("sled");
    LodStore::open(db.open_tree("lod").expect("tree"), dir.join("lod.bin")).expect("store")
}

/// A sample scene written as LAS, loaded whole and built into a store of small nodes.
fn fixture(points: usize) -> Fixture {
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("scene.las");
    write_las(&path, &sample_scene(points, 5), &LasWriteOptions::default()).expect("write");
    let cloud = load_point_cloud(&path).expect("load");
    let source = DatasetSource::open(&[path]).expect("source");
    let store = open_store(dir.path());
    let mut options = LodBuildOptions::new(dir.path().join("spill"));
    options.max_leaf_points = 3_000;
    build_lod(&source, &store, &options).expect("build");
    let dataset = LodDataset::open(store.clone(), source.bounds()).expect("open");
    assert_eq!(dataset.origin(), cloud.origin, "one origin for both paths");
    Fixture {
        _dir: dir,
        cloud,
        store,
        dataset,
    }
}

/// The request's defaults without shading: what these tests compare is the points drawn.
fn basic() -> RenderOptions {
    RenderOptions {
        shading: Shading::None,
        ..RenderOptions::default()
    }
}

fn settings(fixture: &Fixture, options: &RenderOptions) -> FrameSettings {
    let camera = Camera::auto(&fixture.cloud.bounds, 4.0 / 3.0);
    let mut settings = FrameSettings::new(200, 150, camera).with_point_size(
        options.point_size,
        &fixture.cloud.bounds,
        None,
    );
    settings.quality = options.quality;
    settings.shading = options.shading;
    settings.fill = options.fill;
    settings.supersample = options.supersample;
    settings
}

/// A fixture of `points`, a renderer, and the default frame of its automatic camera.
fn basic_frame(points: usize) -> (Fixture, Renderer, FrameSettings) {
    let fixture = fixture(points);
    let first = settings(&fixture, &basic());
    (fixture, Renderer::new(gpu()), first)
}

/// A frame of `fixture` in RGB from a new cut renderer at `lod_error`, its caches cold.
fn fresh_cut(
    renderer: &mut Renderer,
    fixture: &Fixture,
    lod_error: f64,
    settings: &FrameSettings,
) -> (Frame, CutReport) {
    let mut cut = cut_renderer(renderer, fixture, lod_error);
    cut.render_rgb(renderer, &fixture.dataset, settings)
        .expect("cut frame")
}

fn resident_image(
    fixture: &Fixture,
    settings: &FrameSettings,
    mode: ColorMode,
) -> image::RgbaImage {
    let mut cloud = fixture.cloud.clone();
    cloud.colors = crate::color::point_colors(&cloud, mode.into());
    let mut renderer = Renderer::new(gpu());
    let resident = renderer.upload(&cloud).expect("upload");
    renderer.render(&resident, settings).expect("render").image
}

fn cut_renderer(renderer: &Renderer, fixture: &Fixture, lod_error: f64) -> CutRenderer {
    let options = CutOptions {
        lod_error,
        ..CutOptions::default()
    };
    CutRenderer::new(renderer, &fixture.dataset, options).expect("cut renderer")
}

/// The share of pixels within 8/255 of the expected image.
fn close_share(name: &str, actual: &image::RgbaImage, expected: &image::RgbaImage) -> f64 {
    compare_images_within(name, actual, expected, 8).equal_fraction()
}

const BATCH_POINTS_U64: u64 = crate::raster::BATCH_POINTS as u64;

/// The share of the covered pixels of `full` that `cut` renders within 8/255.
fn fidelity(name: &str, cut: &image::RgbaImage, full: &image::RgbaImage) -> f64 {
    let covered = full
        .pixels()
        .filter(|p| p.0 != crate::raster::DEFAULT_BACKGROUND)
        .count();
    let differing = compare_images_within(name, cut, full, 8).differing;
    1.0 - differing as f64 / covered.max(1) as f64
}

/// `count` points on pixel centres of the columns `columns` of a `settings` frame, a point in
/// every third pixel each way, at depths spread over the view.
fn pixel_centre_points(
    settings: &FrameSettings,
    origin: glam::DVec3,
    columns: std::ops::Range<u32>,
) -> Vec<glam::DVec3> {
    let t = settings
        .camera
        .transform(origin, settings.width, settings.height);
    let inverse = t.view_proj.inverse();
    let unproject = |ndc_x: f64, ndc_y: f64, z: f64| {
        let p = inverse * glam::DVec4::new(ndc_x, ndc_y, z, 1.0);
        p.truncate() / p.w
    };
    let depth = |p: glam::DVec3| t.depth_row.dot(p.extend(1.0));
    let mut points = Vec::new();
    for (i, (x, y)) in columns
        .step_by(3)
        .flat_map(|x| (0..settings.height).step_by(3).map(move |y| (x, y)))
        .enumerate()
    {
        let ndc_x = (f64::from(x) + 0.5) / f64::from(settings.width) * 2.0 - 1.0;
        let ndc_y = 1.0 - (f64::from(y) + 0.5) / f64::from(settings.height) * 2.0;
        let (near, far) = (unproject(ndc_x, ndc_y, 0.0), unproject(ndc_x, ndc_y, 1.0));
        // Depths from 4 to about 40, where the sizes below run from 1 to the largest.
        let wanted = 4.0 + (i * 7919 % 97) as f64 * 0.37;
        let s = (wanted - depth(near)) / (depth(far) - depth(near));
        points.push(origin + near + (far - near) * s);
    }
    points
}

/// A 96 x 64 frame's camera 10 m in front of the origin, looking at it along +Y.
fn side_view() -> Camera {
    Camera {
        position: glam::DVec3::new(0.0, -10.0, 0.0),
        target: glam::DVec3::ZERO,
        up: glam::DVec3::Z,
        projection: Projection::Perspective { fov_y_deg: 50.0 },
        near: 1.0,
        far: 100.0,
    }
}

/// Pixels that are not the default background.
fn covered(image: &image::RgbaImage) -> usize {
    image
        .pixels()
        .filter(|p| p.0 != crate::raster::DEFAULT_BACKGROUND)
        .count()
}

/// Writes `data` into `cache` as node `key`, prepared from its whole record.
fn insert_whole(
    cache: &mut super::gpu_cache::GpuNodeCache,
    renderer: &Renderer,
    key: NodeKey,
    data: &SegmentData,
    keep: &HashSet<NodeKey>,
) {
    cache
        .insert(
            renderer.gpu(),
            key,
            crate::lod::codec::Detail::Full,
            data,
            keep,
        )
        .expect("insert");
}

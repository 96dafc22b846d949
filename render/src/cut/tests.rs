//! Cuts rendered on the GPU against the resident cloud of the same file, cold and warm caches,
//! the budgets, the read-ahead and a damaged node.

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
    rgb_frame(&mut cut, renderer, fixture, settings).expect("cut frame")
}

/// A frame of `fixture` in RGB, every point kept, from `cut`.
fn rgb_frame(
    cut: &mut CutRenderer,
    renderer: &mut Renderer,
    fixture: &Fixture,
    settings: &FrameSettings,
) -> Result<(Frame, CutReport), CutError> {
    cut.render(
        renderer,
        &fixture.dataset,
        settings,
        ColorMode::Rgb,
        &PointFilter::default(),
    )
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

#[test]
fn every_mode_at_lod_error_zero_renders_as_the_resident_cloud() {
    let fixture = fixture(60_000);
    let mut renderer = Renderer::new(gpu());
    let mut cut = cut_renderer(&renderer, &fixture, 0.0);
    let default = basic;
    let filled = |shading| RenderOptions {
        fill: Some(FillSettings::default()),
        shading,
        ..default()
    };
    let high_quality = RenderOptions {
        quality: Quality::HIGH,
        point_size: PointSize::Fixed(2),
        ..default()
    };
    let options_in_rgb = [
        ("basic", default()),
        ("high-quality", high_quality),
        ("fill-edl", filled(Shading::EDL)),
        ("pintus", filled(Shading::PINTUS)),
        (
            "supersampled",
            RenderOptions {
                supersample: 2,
                ..default()
            },
        ),
    ];
    let colors_by_default = [
        ("intensity", ColorMode::Intensity),
        ("classes", ColorMode::Classification),
        ("returns", ColorMode::ReturnNumber),
        ("fixed", ColorMode::Fixed([255, 128, 0])),
        ("elevation", ColorMode::Elevation),
    ];
    let modes = (options_in_rgb.map(|(name, options)| (name, options, ColorMode::Rgb)))
        .into_iter()
        .chain(colors_by_default.map(|(name, mode)| (name, default(), mode)));
    for (name, options, color_mode) in modes {
        let settings = settings(&fixture, &options);
        let (frame, report) = cut
            .render(
                &mut renderer,
                &fixture.dataset,
                &settings,
                color_mode,
                &PointFilter::default(),
            )
            .expect("cut");
        assert_eq!(
            report.counts.points_rendered, report.counts.points_total,
            "{name}: lod 0 draws all"
        );
        let expected = resident_image(&fixture, &settings, color_mode);
        let share = close_share(&format!("cut-{name}"), &frame.image, &expected);
        // Elevation takes its range from a sample of the store, the resident cloud from every
        // point: a few colours shift by a level or two.
        assert!(
            share >= 0.99,
            "{name}: only {share:.4} of pixels within 8/255"
        );
    }
}

#[test]
fn filtered_cuts_at_lod_error_zero_draw_the_filtered_resident_cloud() {
    use crate::filter::{ClipBox, CodeSet, IntensityRange};
    let fixture = fixture(60_000);
    let mut renderer = Renderer::new(gpu());
    let mut cut = cut_renderer(&renderer, &fixture, 0.0);
    let bounds = fixture.cloud.bounds;
    // The half of the scene with the lower x.
    let half = ClipBox {
        min: bounds.min.to_array(),
        max: [bounds.center().x, bounds.max.y, bounds.max.z],
    };
    let classes = fixture.cloud.classification.iter().copied();
    let common_class = classes.max_by_key(|&c| {
        fixture
            .cloud
            .classification
            .iter()
            .filter(|&&d| d == c)
            .count()
    });
    let mut intensities = fixture.cloud.intensity.clone();
    intensities.sort_unstable();
    let median_intensity = intensities[intensities.len() / 2];
    let filters = [
        (
            "classes",
            PointFilter {
                classes: Some(CodeSet::of(common_class)),
                ..Default::default()
            },
        ),
        (
            "intensity",
            PointFilter {
                intensity: Some(IntensityRange {
                    min: 0,
                    max: median_intensity - 1,
                }),
                ..Default::default()
            },
        ),
        (
            "clip",
            PointFilter {
                clip: Some(half),
                ..Default::default()
            },
        ),
    ];
    let (_, everything) = cut
        .render(
            &mut renderer,
            &fixture.dataset,
            &settings(&fixture, &basic()),
            ColorMode::Rgb,
            &PointFilter::default(),
        )
        .expect("unfiltered");
    for (name, filter) in filters {
        let mut kept = fixture.cloud.clone();
        let count = filter.apply(&mut kept).expect("inside");
        assert!(
            count > 0 && count < fixture.cloud.len(),
            "{name}: {count} kept"
        );
        // Both paths frame the same bounds: the clip box's part of the dataset.
        let framing = filter
            .framing_bounds(&fixture.dataset.bounds())
            .expect("inside");
        let camera = Camera::auto(&framing, 4.0 / 3.0);
        let settings = FrameSettings::new(200, 150, camera);
        let (frame, report) = cut
            .render(
                &mut renderer,
                &fixture.dataset,
                &settings,
                ColorMode::Rgb,
                &filter,
            )
            .expect("filtered cut");
        assert_eq!(
            report.counts.points_rendered, count as u64,
            "{name}: what the filter kept"
        );
        let mut resident = Renderer::new(gpu());
        let uploaded = resident.upload(&kept).expect("upload");
        let expected = resident.render(&uploaded, &settings).expect("render").image;
        let share = close_share(&format!("cut-filter-{name}"), &frame.image, &expected);
        assert!(
            share >= 0.99,
            "{name}: only {share:.4} of pixels within 8/255"
        );
        if name == "clip" {
            assert!(
                report.counts.nodes < everything.counts.nodes,
                "the box leaves nodes outside it uncut: {} of {}",
                report.counts.nodes,
                everything.counts.nodes
            );
        }
    }
}

#[test]
fn a_frame_is_the_same_from_a_cold_and_a_warm_cache() {
    let (fixture, mut renderer, first) = basic_frame(40_000);
    let mut other = first;
    other.camera = Camera::framing(
        &fixture.cloud.bounds,
        4.0 / 3.0,
        40.0,
        50.0,
        Projection::Perspective { fov_y_deg: 40.0 },
    );
    let mut cut = cut_renderer(&renderer, &fixture, DEFAULT_LOD_ERROR_PX);
    let (cold, cold_report) = rgb_frame(&mut cut, &mut renderer, &fixture, &first).expect("cold");
    assert_eq!(cold_report.counts.gpu_hits, 0);
    assert!(cold_report.counts.nodes_read > 0 && cold_report.counts.bytes_read > 0);
    rgb_frame(&mut cut, &mut renderer, &fixture, &other).expect("other");
    let (warm, warm_report) = rgb_frame(&mut cut, &mut renderer, &fixture, &first).expect("warm");
    assert_eq!(warm_report.counts.nodes_read, 0, "{warm_report:?}");
    assert_eq!(warm_report.counts.gpu_hits, warm_report.counts.nodes);
    assert!(
        cold.image == warm.image,
        "the warm frame differs from the cold one"
    );
}

#[test]
fn a_cut_too_large_for_one_pass_is_drawn_in_tiles_as_in_one() {
    let (fixture, mut renderer, first) = basic_frame(40_000);
    let settings = FrameSettings {
        shading: Shading::EDL,
        ..first
    };
    let (whole, whole_report) = fresh_cut(&mut renderer, &fixture, DEFAULT_LOD_ERROR_PX, &settings);
    let mut tiled = Renderer::new(gpu());
    tiled.set_tile_limit_bytes(200 * 150 * 8 / 4);
    assert!(tiled.tile_grid(&settings).is_some(), "drawn in tiles");
    let (frame, report) = fresh_cut(&mut tiled, &fixture, DEFAULT_LOD_ERROR_PX, &settings);
    assert_eq!(
        report.counts.points_rendered,
        whole_report.counts.points_rendered
    );
    // As in `raster/tests/tiles.rs`: a point within rounding of a pixel's edge may move.
    let diff = compare_images_within("cut-tiles", &frame.image, &whole.image, 0);
    assert!(
        diff.differing <= 200 * 150 / 2000,
        "{} pixels differ",
        diff.differing
    );
}

#[test]
fn the_caches_stay_within_their_budgets_and_evict() {
    let fixture = fixture(120_000);
    let mut renderer = Renderer::new(gpu());
    let budgets = CacheBudgets {
        host_bytes: 600 << 10,
        gpu_bytes: 30 * SLOT_BYTES,
    };
    let mut cut =
        CutRenderer::with_budgets(&renderer, &fixture.dataset, CutOptions::default(), budgets);
    let mut evicted = 0;
    for step in 0..6 {
        let mut settings = settings(&fixture, &basic());
        settings.camera = Camera::framing(
            &fixture.cloud.bounds,
            4.0 / 3.0,
            f64::from(step) * 60.0,
            35.0,
            Projection::Perspective { fov_y_deg: 30.0 },
        );
        let again = settings;
        let (frame, report) =
            rgb_frame(&mut cut, &mut renderer, &fixture, &settings).expect("frame");
        assert!(report.gpu_cache_bytes <= budgets.gpu_bytes, "{report:?}");
        assert!(report.host_cache_bytes <= budgets.host_bytes, "{report:?}");
        assert!(
            report.counts.points_rendered <= 30 * BATCH_POINTS_U64,
            "{report:?}"
        );
        evicted += report.counts.gpu_evicted;
        // The same view again, after whatever the budget evicted: the same image.
        let (repeat, _) = rgb_frame(&mut cut, &mut renderer, &fixture, &again).expect("repeat");
        assert!(
            repeat.image == frame.image,
            "step {step}: a repeated frame differs"
        );
    }
    assert!(evicted > 0, "a small GPU budget evicts as the camera turns");
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

#[test]
fn a_coarser_pixel_error_draws_fewer_points_and_the_default_keeps_the_image() {
    let fixture = fixture(120_000);
    let mut renderer = Renderer::new(gpu());
    for (quality, least) in [(Quality::Basic, 0.96), (Quality::HIGH, 0.99)] {
        let mut settings = settings(&fixture, &basic());
        settings.quality = quality;
        let (full_frame, full_report) = fresh_cut(&mut renderer, &fixture, 0.0, &settings);
        let (frame, report) = fresh_cut(&mut renderer, &fixture, DEFAULT_LOD_ERROR_PX, &settings);
        let share = fidelity("cut-default-error", &frame.image, &full_frame.image);
        assert!(
            share >= least,
            "{quality:?}: {share:.4} of covered pixels within 8/255"
        );
        assert!(report.counts.points_rendered <= full_report.counts.points_rendered);
    }
    // Far away, a coarser error draws fewer points.
    let mut settings = settings(&fixture, &basic());
    let target = fixture.cloud.bounds.center();
    settings.camera.position = target + (settings.camera.position - target) * 3.0;
    settings.camera.far *= 4.0;
    let points = |lod_error: f64, renderer: &mut Renderer| {
        let mut cut = cut_renderer(renderer, &fixture, lod_error);
        cut.render(
            renderer,
            &fixture.dataset,
            &settings,
            ColorMode::Rgb,
            &PointFilter::default(),
        )
        .expect("frame")
        .1
        .counts
        .points_rendered
    };
    let (full, default, coarse) = (
        points(0.0, &mut renderer),
        points(DEFAULT_LOD_ERROR_PX, &mut renderer),
        points(2.0, &mut renderer),
    );
    assert!(
        coarse < default && default < full,
        "{coarse} {default} {full}"
    );
}

/// A small image of many points: the pixel error alone would draw them all, the cut stops at
/// the points its pixels warrant; at 0 px every point is drawn all the same.
#[test]
fn a_cut_draws_at_most_its_pixels_worth_of_points_unless_asked_for_every_point() {
    let fixture = fixture(60_000);
    let mut renderer = Renderer::new(gpu());
    let mut settings = settings(&fixture, &basic());
    (settings.width, settings.height) = (20, 15);
    let cap = 20 * 15 * crate::cut::MAX_CUT_POINTS_PER_PIXEL;
    let (_, capped) = fresh_cut(&mut renderer, &fixture, 0.05, &settings);
    assert!(capped.counts.limited_by_budget, "{:?}", capped.counts);
    assert!(
        capped.counts.points_rendered <= cap && capped.counts.points_rendered > cap / 2,
        "{} points for a cap of {cap}",
        capped.counts.points_rendered
    );
    let (_, full) = fresh_cut(&mut renderer, &fixture, 0.0, &settings);
    assert!(!full.counts.limited_by_budget);
    assert!(full.counts.points_rendered > 4 * cap, "{:?}", full.counts);
}

#[test]
fn a_read_ahead_fills_the_host_cache_and_changes_no_pixel() {
    let (fixture, mut renderer, first) = basic_frame(40_000);
    let mut next = first;
    next.camera.position =
        first.camera.target + (first.camera.position - first.camera.target) * 0.5;
    let (expected, _) = fresh_cut(&mut renderer, &fixture, 0.0, &next);

    let mut cut = CutRenderer::with_budgets(
        &renderer,
        &fixture.dataset,
        CutOptions {
            lod_error: 0.0,
            ..CutOptions::default()
        },
        CacheBudgets {
            host_bytes: 64 << 20,
            gpu_bytes: 64 << 20,
        },
    );
    cut.render(
        &mut renderer,
        &fixture.dataset,
        &first,
        ColorMode::Intensity,
        &PointFilter::default(),
    )
    .expect("first");
    // Another colour mode empties the GPU cache, so the next frame needs every node.
    cut.read_ahead(&fixture.dataset, &next, &PointFilter::default());
    let (frame, report) = rgb_frame(&mut cut, &mut renderer, &fixture, &next).expect("next");
    assert_eq!(report.counts.gpu_hits, 0);
    assert_eq!(
        report.counts.nodes_read, 0,
        "every node came from the host cache: {report:?}"
    );
    assert!(report.counts.host_hits > 0);
    assert!(frame.image == expected.image);
}

#[test]
fn a_damaged_node_is_reported_not_drawn() {
    let fixture = fixture(20_000);
    let hierarchy = fixture.dataset.hierarchy();
    let node = hierarchy
        .nodes()
        .iter()
        .find(|n| n.point_count > 100)
        .copied()
        .expect("a node");
    let store = &fixture.store;
    let mut bytes = store
        .node_bytes(hierarchy, node.key)
        .expect("read")
        .expect("bytes");
    let middle = bytes.len() / 2;
    bytes[middle] ^= 0x55;
    // The same length: damaged in place, where the dataset's hierarchy points.
    store
        .overwrite_node_bytes(&mut hierarchy.clone(), node.key, &bytes)
        .expect("damage");
    let mut renderer = Renderer::new(gpu());
    let mut cut = cut_renderer(&renderer, &fixture, 0.0);
    let settings = settings(&fixture, &basic());
    let Err(error) = rgb_frame(&mut cut, &mut renderer, &fixture, &settings) else {
        panic!("a damaged node fails the frame");
    };
    assert!(
        matches!(error, CutError::Store(LodError::CorruptNode { .. })),
        "{error}"
    );
    assert!(error.to_string().contains(&node.key.to_string()), "{error}");
}

/// The fidelity table of docs/perf/lod-fidelity.md: `cargo test -p pointfarm-render --lib
/// cut::tests::fidelity_by_pixel_error -- --ignored --nocapture`.
#[test]
#[ignore]
fn fidelity_by_pixel_error() {
    let fixture = fixture(400_000);
    let mut renderer = Renderer::new(gpu());
    let views = [
        (1.0, Quality::Basic),
        (3.0, Quality::Basic),
        (1.0, Quality::HIGH),
        (3.0, Quality::HIGH),
    ];
    for (distance, quality) in views {
        let mut settings = settings(&fixture, &basic());
        settings.quality = quality;
        let target = fixture.cloud.bounds.center();
        settings.camera.position = target + (settings.camera.position - target) * distance;
        settings.camera.far *= 4.0;
        let (full_frame, _) = fresh_cut(&mut renderer, &fixture, 0.0, &settings);
        for error in [0.1, 0.25, 0.5, 1.0, 2.0] {
            let (frame, report) = fresh_cut(&mut renderer, &fixture, error, &settings);
            let share = fidelity("fidelity", &frame.image, &full_frame.image);
            eprintln!(
                "distance {distance} {quality:?} error {error}: {} of {} points, {share:.4}",
                report.counts.points_rendered, report.counts.points_total
            );
        }
    }
}

/// Adaptive points are as large from a store as from the whole cloud: the leaves' spacing is
/// the points' spacing.
#[test]
fn a_store_and_its_cloud_have_one_spacing() {
    let fixture = fixture(60_000);
    let from_points = fixture.cloud.spacing().expect("the cloud's spacing");
    let from_leaves = fixture
        .dataset
        .hierarchy()
        .point_spacing()
        .expect("the store's spacing");
    let ratio = from_leaves / from_points;
    assert!(
        (0.7..1.5).contains(&ratio),
        "leaves {from_leaves}, points {from_points}"
    );
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

/// Batches drawn with a size factor are sized as the reference sizes their points at that
/// factor times the frame's adaptive size: two nodes side by side, the right one at twice the
/// left's size, match the references of each half.
#[test]
fn batches_take_their_own_point_size_factor() {
    use super::gpu_cache::GpuNodeCache;

    let mut settings = FrameSettings::new(96, 64, side_view());
    settings.background = [0, 0, 0, 0];
    settings.adaptive_size = Some(16.0);
    settings.point_size = crate::raster::MAX_ADAPTIVE_POINT_SIZE;
    let origin = glam::DVec3::ZERO;
    // Left and right halves, 12 pixels apart: no square of one reaches the other's pixels.
    let left = pixel_centre_points(&settings, origin, 0..42);
    let right = pixel_centre_points(&settings, origin, 54..96);
    let world: Vec<glam::DVec3> = left.iter().chain(&right).copied().collect();
    let colors = (0..world.len() as u32)
        .map(|i| crate::cloud::pack_rgba8((i * 37) as u8, (i * 91) as u8, 200))
        .collect();
    let cloud = PointCloud::from_world_points(&world, colors);
    let halves = [
        cloud.select(&(0..left.len()).collect::<Vec<_>>()),
        cloud.select(&(left.len()..world.len()).collect::<Vec<_>>()),
    ];
    assert!(halves
        .iter()
        .all(|h| h.len() <= crate::raster::BATCH_POINTS));

    let renderer = &mut Renderer::new(gpu());
    let mut cache = GpuNodeCache::new(cloud.origin, 64 << 20, 1 << 16);
    let keys = [NodeKey::ROOT.child(0), NodeKey::ROOT.child(7)];
    let keep: HashSet<NodeKey> = keys.into_iter().collect();
    for (key, half) in keys.iter().zip(&halves) {
        let data = ChunkData::new(&half.positions, half.colors.iter().copied());
        cache
            .insert(renderer.gpu(), *key, &data, &keep)
            .expect("insert");
    }
    let factor_of = |key: NodeKey| if key == keys[0] { 1.0 } else { 2.0 };
    let mut factor = |key: NodeKey, _: &GpuBatch| factor_of(key);
    let gpu_cloud = cache.frame_cloud(renderer.gpu(), &keys, 0.0, Some(&mut factor));
    let frame = renderer.render(gpu_cloud, &settings).expect("render");

    let mut expected = image::RgbaImage::new(settings.width, settings.height);
    let mut sides = std::collections::BTreeSet::new();
    for (key, half) in keys.iter().zip(&halves) {
        let sized = FrameSettings {
            adaptive_size: Some(16.0 * factor_of(*key)),
            ..settings
        };
        let t = sized
            .camera
            .transform(half.origin, sized.width, sized.height);
        sides.extend(
            half.positions
                .iter()
                .filter_map(|p| t.project(p.as_dvec3()))
                .map(|(_, _, depth)| sized.point_side_at(depth as f32)),
        );
        let reference = crate::reference::render_basic(half, &sized).image;
        for (out, drawn) in expected.pixels_mut().zip(reference.pixels()) {
            if drawn.0 != settings.background {
                *out = *drawn;
            }
        }
    }
    assert_eq!(sides, (1..=8).collect(), "the halves span every side");
    let diff = crate::testing::compare_images("batch-size-factors", &frame.image, &expected);
    assert_eq!(diff.differing, 0, "{} pixels differ", diff.differing);
}

/// Pixels that are not the default background.
fn covered(image: &image::RgbaImage) -> usize {
    image
        .pixels()
        .filter(|p| p.0 != crate::raster::DEFAULT_BACKGROUND)
        .count()
}

/// Where a cut stops at coarse nodes, adaptive points take those nodes' spacing: a coarse
/// pixel error covers the surface about as full detail does, not with the holes that points
/// sized for the finest nodes leave (at 6 px those cover 53% of full detail's pixels; with
/// each node's spacing 94%, the rest being gaps where a cell's point lies off its centre).
#[test]
fn adaptive_points_of_a_coarse_cut_close_the_surface() {
    let fixture = fixture(120_000);
    let mut renderer = Renderer::new(gpu());
    let spacing = fixture.dataset.point_spacing();
    let camera = Camera::auto(&fixture.cloud.bounds, 4.0 / 3.0);
    let settings = FrameSettings::new(200, 150, camera).with_point_size(
        PointSize::Adaptive,
        &fixture.cloud.bounds,
        spacing,
    );
    let (full, full_report) = fresh_cut(&mut renderer, &fixture, 0.0, &settings);
    let (coarse, coarse_report) = fresh_cut(&mut renderer, &fixture, 6.0, &settings);
    assert!(
        coarse_report.counts.points_rendered * 4 < full_report.counts.points_rendered,
        "the coarse cut draws far fewer points: {:?}",
        coarse_report.counts
    );
    let (full, coarse) = (covered(&full.image), covered(&coarse.image));

    assert!(
        coarse as f64 >= 0.9 * full as f64,
        "covered pixels: full detail {full}, coarse cut {coarse}"
    );
}

/// A batch of the root takes the root's own spacing where the cut stops at it, and the
/// spacing of the deepest nodes below it where the cut reaches them.
#[test]
fn a_batch_takes_the_spacing_of_the_deepest_nodes_drawn_where_it_lies() {
    let fixture = fixture(60_000);
    let hierarchy = fixture.dataset.hierarchy();
    let reference = fixture.dataset.point_spacing().expect("spacing");
    let settings = settings(&fixture, &basic());
    let transform =
        settings
            .camera
            .transform(fixture.dataset.origin(), settings.width, settings.height);
    let bounds = &fixture.cloud.bounds;
    let whole = GpuBatch {
        min: (bounds.min - fixture.dataset.origin()).as_vec3().to_array(),
        first: 0,
        max: (bounds.max - fixture.dataset.origin()).as_vec3().to_array(),
        count: 1,
    };
    let root_factor = |lod_error: f64| {
        let view = CutView {
            camera: &settings.camera,
            origin: fixture.dataset.origin(),
            width: settings.width,
            height: settings.height,
            point_size: 1,
            lod_error,
            max_batches: usize::MAX,
            max_points: None,
            clip: None,
        };
        let cut = select_cut(hierarchy, &view);
        let mut sizes = CutPointSizes::new(
            hierarchy,
            &cut,
            NodesInView::new(hierarchy, &view, &transform),
            &transform,
            fixture.dataset.origin(),
            reference,
            1.0,
        );
        (cut.nodes.len(), sizes.factor(NodeKey::ROOT, &whole) as f64)
    };
    let root_cell = hierarchy.spacing(NodeKey::ROOT).expect("an inner root");
    let (nodes, coarse) = root_factor(1e9);
    assert_eq!(nodes, 1, "only the root");
    assert!((coarse - root_cell / reference).abs() < 1e-5, "{coarse}");

    let (nodes, full) = root_factor(0.0);
    assert_eq!(
        nodes,
        hierarchy
            .nodes()
            .iter()
            .filter(|n| n.point_count > 0)
            .count()
    );
    let coarsest_leaf = hierarchy
        .nodes()
        .iter()
        .filter(|n| n.is_leaf())
        .filter_map(|n| hierarchy.points_spacing(n.key))
        .fold(0.0, f64::max);
    assert!(
        full < coarse && (full - coarsest_leaf / reference).abs() < 1e-5,
        "every node drawn: {full}, the coarsest leaf {}",
        coarsest_leaf / reference
    );
}

/// High quality on a cut's pages adds each point as many times as its weight where its
/// node's child below it is not drawn, once where it is: the frame matches the weighted
/// reference within a level, on the packed sums (light points, pixels under and over their
/// 256) and the wide ones (heavy points), and the 64-bit path matches the 32-bit one to the
/// bit. The root and a grandchild are drawn, the child between them left without points (its
/// parent took them all), so not listed: the root's points in that child's octant count once.
#[test]
fn weighted_high_quality_matches_the_weighted_reference() {
    use super::gpu_cache::GpuNodeCache;
    use crate::lod::weights::{decode_weight, encode_weight, WEIGHT_CODE_BITS};
    use crate::raster::AtomicsMode;

    let camera = side_view();
    let mut settings = FrameSettings::new(96, 64, camera);
    settings.quality = Quality::High { depth_band: 0.5 };
    settings.point_size = 1;
    let origin = glam::DVec3::ZERO;
    let columns = pixel_centre_points(&settings, origin, 0..96);
    let mut state = 0x9e37_79b9_7f4a_7c15u64;
    let mut next = |n: u64| {
        state = state
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        (state >> 33) % n
    };
    // Per pixel 1 to 60 points along its ray, 1.0 to 1.3 times the first's depth; weights
    // mostly light, some heavy, so that pixels fill the packed sums and spill past them.
    let mut world = Vec::new();
    let mut bits = Vec::new();
    for (p, first) in columns.iter().enumerate() {
        let ray = (*first - camera.position).normalize();
        let depth = (*first - camera.position).length();
        for k in 0..=next(60) {
            let along = if k == 0 {
                0.0
            } else {
                depth * (1 + next(300)) as f64 / 1000.0
            };
            world.push(*first + ray * along);
            let weight = match next(10) {
                0..=5 => 1 + next(16) as u32,
                6..=7 => 17 + next(300) as u32,
                8 => 1 + next(3) as u32,
                _ => 1000 + next(50_000) as u32,
            };
            let octant = (p as u16 + k as u16) % 8;
            bits.push(encode_weight(weight) | octant << WEIGHT_CODE_BITS);
        }
    }
    let colors: Vec<u32> = (0..world.len())
        .map(|_| crate::cloud::pack_rgba8(next(256) as u8, next(256) as u8, next(256) as u8))
        .collect();
    let cloud = PointCloud::from_world_points(&world, colors);
    // The root holds the first half of the points, a node below its child 0 the rest.
    let half = world.len() / 2;
    let parts = [
        (NodeKey::ROOT, 0..half),
        (NodeKey::ROOT.child(0).child(3), half..world.len()),
    ];
    let renderer = &mut Renderer::new(gpu());
    let mut cache = GpuNodeCache::new(cloud.origin, 64 << 20, 1 << 16);
    let keys: Vec<NodeKey> = parts.iter().map(|(k, _)| *k).collect();
    let keep: HashSet<NodeKey> = keys.iter().copied().collect();
    for (key, range) in &parts {
        let mut data = ChunkData::new(
            &cloud.positions[range.clone()],
            cloud.colors[range.clone()].iter().copied(),
        );
        data.weights = bits[range.clone()].to_vec();
        data.weights
            .resize(data.weights.len().next_multiple_of(2), 0);
        cache
            .insert(renderer.gpu(), *key, &data, &keep)
            .expect("insert");
    }
    // What each point counts for: the root's points in octant 0 once (drawn below child 0).
    let weights: Vec<u32> = bits
        .iter()
        .enumerate()
        .map(|(i, &b)| {
            let drawn_child = i < half && b >> WEIGHT_CODE_BITS == 0;
            if drawn_child {
                1
            } else {
                decode_weight(b)
            }
        })
        .collect();
    assert!(weights.iter().any(|&w| w > 256) && weights.iter().filter(|&&w| w == 1).count() > 100);
    let expected =
        crate::reference::render_high_quality_weighted(&cloud, &settings, 0.5, &weights).image;
    let unweighted = crate::reference::render_high_quality(&cloud, &settings, 0.5).image;
    let gpu_cloud = cache.frame_cloud(renderer.gpu(), &keys, 0.0, None);
    let auto = renderer.render(gpu_cloud, &settings).expect("render").image;
    let forced = FrameSettings {
        atomics: AtomicsMode::Force32,
        ..settings
    };
    let with_32 = renderer.render(gpu_cloud, &forced).expect("render").image;
    let difference = |a: &image::RgbaImage, b: &image::RgbaImage| {
        a.as_raw()
            .iter()
            .zip(b.as_raw())
            .map(|(x, y)| x.abs_diff(*y))
            .max()
            .unwrap_or(0)
    };
    assert!(
        difference(&expected, &unweighted) > 32,
        "the weights matter"
    );
    assert_eq!(difference(&auto, &with_32), 0, "64-bit against 32-bit sums");
    let off = difference(&auto, &expected);
    assert!(off <= 1, "differs from the weighted reference by {off}/255");
}

//! Frames drawn in tiles against the same frames drawn in one pass: a renderer whose tile
//! limit is lowered splits small frames into several tiles, and every mode must come out as
//! the untiled frame does. Only a point within about a millionth of a pixel of a pixel's edge
//! may land in the neighbouring pixel (the tile's projection rounds differently in f32), so
//! the generated scene, whose points lie anywhere, allows one pixel in 2000 to differ (a few
//! did, in high quality and supersampled, where every point of a pixel counts); points on
//! pixel centres must match exactly.

use super::*;
use crate::sample::sample_scene;
use crate::testing::compare_images_within;

/// The generated scene and a view of it that leaves background around it.
fn scene(points: usize) -> (PointCloud, Camera) {
    let cloud = sample_scene(points, 3);
    let camera = Camera::auto(&cloud.bounds, 1.5);
    (cloud, camera)
}

/// `settings`' frame in one pass and in tiles of at most a quarter of its largest buffer.
fn untiled_and_tiled(cloud: &PointCloud, settings: &FrameSettings) -> (Frame, Frame) {
    let (mut whole, resident) = uploaded(cloud);
    assert!(
        whole.tile_grid(settings).is_none(),
        "small frames fit one pass"
    );
    let untiled = whole.render(&resident, settings).expect("untiled");

    let mut tiled_renderer = Renderer::new(gpu());
    let drawn = settings.scaled_for_supersampling();
    let frame_bytes = u64::from(drawn.width)
        * u64::from(drawn.height)
        * crate::raster::tiles::bytes_per_pixel(drawn.quality);
    tiled_renderer.set_tile_limit_bytes(frame_bytes / 4);
    let grid = tiled_renderer.tile_grid(settings).expect("tiled");
    assert!(grid.columns() * grid.rows() >= 4, "{grid:?}");
    let resident = tiled_renderer.upload(cloud).expect("upload");
    let tiled = tiled_renderer.render(&resident, settings).expect("tiled");
    (untiled, tiled)
}

/// At most `allowed` pixels differ, each by any amount (a point that moved to the next
/// pixel); the depth images, when read, differ in as many pixels at most.
fn assert_tiles_match(name: &str, cloud: &PointCloud, settings: &FrameSettings, allowed: usize) {
    let (untiled, tiled) = untiled_and_tiled(cloud, settings);
    assert_eq!(tiled.image.dimensions(), (settings.width, settings.height));
    let diff = compare_images_within(name, &tiled.image, &untiled.image, 0);
    assert!(
        diff.differing <= allowed,
        "{name}: {} pixels differ in tiles (at most {allowed})",
        diff.differing
    );
    assert!(
        untiled.image.pixels().any(|p| p.0 != settings.background),
        "{name}: the scene is in view"
    );
    match (&untiled.depth, &tiled.depth) {
        (Some(expected), Some(actual)) => {
            assert_eq!(actual.len(), expected.len());
            let differing = actual
                .iter()
                .zip(expected)
                .filter(|(a, e)| a.to_bits() != e.to_bits())
                .count();
            assert!(
                differing <= allowed,
                "{name}: {differing} depths differ in tiles"
            );
        }
        (None, None) => {}
        _ => panic!("{name}: a depth image in one frame only"),
    }
}

/// The generated scene's frames may differ in this many pixels: one in 2000.
const ROUNDED: usize = 240 * 160 / 2000;

fn base(camera: Camera) -> FrameSettings {
    FrameSettings {
        point_size: 2,
        ..FrameSettings::new(240, 160, camera)
    }
}

#[test]
fn tiled_basic_frames_match_one_pass_pixel_for_pixel_on_pixel_centres() {
    // Each pixel's points on its centre: no rounding can move one, so nothing may differ.
    let settings = FrameSettings {
        read_depth: true,
        ..perspective_settings(200, 150)
    };
    let cloud = pixel_centre_scene(&settings, 3, 21);
    assert_tiles_match("tiles-centres", &cloud, &settings, 0);
    let high = FrameSettings {
        quality: Quality::HIGH,
        ..settings
    };
    assert_tiles_match(
        "tiles-centres-high",
        &surface_with_depth_noise(&high, 22),
        &high,
        0,
    );
}

/// A mode of the generated scene: its name, the scene's points, and its settings given the
/// scene and the view of it.
type Mode = (
    &'static str,
    usize,
    fn(&PointCloud, Camera) -> FrameSettings,
);

const MODES: [Mode; 6] = [
    ("tiles-basic", 150_000, |_, camera| base(camera)),
    ("tiles-high", 150_000, |_, camera| FrameSettings {
        quality: Quality::HIGH,
        read_depth: true,
        ..base(camera)
    }),
    ("tiles-edl", 60_000, |_, camera| FrameSettings {
        shading: Shading::Edl {
            strength: 1.0,
            radius: 3.0,
        },
        ..base(camera)
    }),
    ("tiles-fill-pintus", 60_000, |_, camera| FrameSettings {
        point_size: 1,
        fill: Some(FillSettings::default()),
        shading: Shading::PINTUS,
        read_depth: true,
        ..base(camera)
    }),
    ("tiles-ortho", 100_000, |cloud, _| {
        let ortho = Camera::fitted(
            &cloud.bounds,
            1.5,
            -60.0,
            40.0,
            Projection::Orthographic { height: 1.0 },
        );
        FrameSettings {
            shading: Shading::EDL,
            read_depth: true,
            ..base(ortho)
        }
    }),
    ("tiles-ssaa", 100_000, |_, camera| FrameSettings {
        supersample: 2,
        quality: Quality::HIGH,
        shading: Shading::EDL,
        read_depth: true,
        ..base(camera)
    }),
];

#[test]
fn tiled_frames_of_every_mode_match_one_pass() {
    for (name, points, settings) in MODES {
        let (cloud, camera) = scene(points);
        assert_tiles_match(name, &cloud, &settings(&cloud, camera), ROUNDED);
    }
}

#[test]
fn a_tiled_frame_reports_its_stages_once_and_its_counts_over_all_tiles() {
    let (cloud, camera) = scene(50_000);
    let settings = FrameSettings {
        fill: Some(FillSettings::default()),
        supersample: 2,
        ..base(camera)
    };
    let (mut renderer, resident) = uploaded(&cloud);
    renderer.render(&resident, &settings).expect("untiled");
    let listed = renderer.listed_points();
    renderer.set_tile_limit_bytes(240 * 160 * 4 * 8 / 4);
    let grid = renderer.tile_grid(&settings).expect("tiled");
    let frame = renderer.render(&resident, &settings).expect("tiled");
    let mut seen = std::collections::HashSet::new();
    for timing in &frame.timings.stages {
        assert!(seen.insert(timing.stage), "{:?} twice", timing.stage);
    }
    for stage in [
        Stage::Cull,
        Stage::Rasterize,
        Stage::Resolve,
        Stage::Visibility,
        Stage::Fill,
        Stage::Downsample,
        Stage::Readback,
    ] {
        assert!(frame.timings.get(stage).is_some(), "{stage:?} timed");
    }
    // Every tile lists what its window can see: together at least the whole frame's points.
    assert!(grid.columns() * grid.rows() > 1);
    assert!(renderer.listed_points() >= listed, "{listed}");
    assert!(renderer.listed_batches() > 0);
    renderer.occlusion_skipped().expect("counts");
}

#[test]
fn a_frame_no_tile_fits_is_refused_before_any_gpu_work() {
    let mut renderer = Renderer::new(gpu());
    renderer.set_tile_limit_bytes(64);
    let settings = perspective_settings(64, 48);
    assert!(matches!(
        renderer.validate(&settings),
        Err(RenderError::ImageTooLarge { .. })
    ));
}

/// A frame wider than the binding limit allows in one pass on lavapipe (16384 x 1100 basic
/// needs 137 MiB of framebuffer; lavapipe binds 128 MiB): each point of a sparse grid on
/// pixel centres, across the seams of whatever tiles the adapter needs, shows in its pixel.
#[test]
fn the_largest_side_renders() {
    let settings = FrameSettings {
        read_depth: true,
        ..perspective_settings(MAX_IMAGE_SIDE, 1100)
    };
    let mut points = Vec::new();
    let (near, far) = (settings.camera.near, settings.camera.far);
    let cloud = pixel_centre_scene_by_pixel(&settings, 5, |_, x, y| {
        if x % 97 == 0 && y % 89 == 0 {
            points.push((x, y));
            vec![near + (far - near) * 0.3]
        } else {
            Vec::new()
        }
    });
    let (mut renderer, resident) = uploaded(&cloud);
    if gpu().capabilities.max_storage_binding_bytes < u64::from(MAX_IMAGE_SIDE) * 1100 * 8 {
        assert!(renderer.tile_grid(&settings).is_some(), "drawn in tiles");
    }
    let frame = renderer.render(&resident, &settings).expect("render");
    assert_eq!(frame.image.dimensions(), (MAX_IMAGE_SIDE, 1100));
    let depth = frame.depth.as_ref().expect("depth");
    for &(x, y) in &points {
        assert_ne!(
            frame.image.get_pixel(x, y).0,
            settings.background,
            "{x}, {y}"
        );
        assert!(depth[(y * MAX_IMAGE_SIDE + x) as usize].is_finite());
        assert_eq!(frame.image.get_pixel(x + 1, y).0, settings.background);
    }
    let drawn = frame
        .image
        .pixels()
        .filter(|p| p.0 != settings.background)
        .count();
    assert_eq!(drawn, points.len());
}

//! The rasterizer against the CPU reference, one file per mode or feature; here, the scenes
//! and helpers they share. Synthetic scenes put points exactly on pixel centres, where the
//! basic mode must match the reference pixel for pixel; `real_scans.rs` and `golden.rs` use
//! the real scans.

mod atomics;
mod basic;
mod culling;
mod exposure;
mod fill_and_shading;
mod filters;
mod golden;
mod high_quality;
mod outputs;
mod point_shapes;
mod real_scans;
mod tiles;
mod upload;

use glam::{DVec3, DVec4};
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::*;
use crate::camera::Camera;
use crate::camera::Projection;
use crate::cloud::pack_rgba8;
use crate::reference;
use crate::testing::{compare_images, gpu, max_channel_difference};

/// Survey-like coordinates, far from zero, so that the recentring path is always exercised.
const SURVEY_ORIGIN: DVec3 = DVec3::new(515_370.0, 4_918_340.0, 2_200.0);

fn camera(projection: Projection) -> Camera {
    Camera {
        position: SURVEY_ORIGIN + DVec3::new(-40.0, -30.0, 25.0),
        target: SURVEY_ORIGIN,
        up: DVec3::Z,
        projection,
        near: 5.0,
        far: 150.0,
    }
}

/// A `width` x `height` frame through the tests' camera with a 50° perspective, the view
/// most tests use.
fn perspective_settings(width: u32, height: u32) -> FrameSettings {
    FrameSettings::new(
        width,
        height,
        camera(Projection::Perspective { fov_y_deg: 50.0 }),
    )
}

/// Points placed exactly on pixel centres (so no rounding can move them to another pixel),
/// `layers` per covered pixel at well-separated depths, in shuffled order, plus points that
/// must be culled: behind the camera, beyond `far`, before `near` and beside the image.
fn pixel_centre_scene(settings: &FrameSettings, layers: usize, seed: u64) -> PointCloud {
    let (near, far) = (settings.camera.near, settings.camera.far);
    pixel_centre_scene_with(settings, seed, |rng| {
        (0..layers)
            .map(|layer| {
                // Depth slots are 10% of the range apart: no f32 rounding can reorder them.
                let slot = (layer as f64 + rng.random_range(0.2..0.8)) / layers as f64;
                near + (far - near) * (0.02 + 0.96 * slot)
            })
            .collect()
    })
}

/// Like [`pixel_centre_scene`], with the depths of each covered pixel's points chosen by
/// `depths`.
fn pixel_centre_scene_with(
    settings: &FrameSettings,
    seed: u64,
    mut depths: impl FnMut(&mut ChaCha8Rng) -> Vec<f64>,
) -> PointCloud {
    pixel_centre_scene_by_pixel(settings, seed, |rng, _, _| {
        if rng.random_bool(0.25) {
            // Leave holes so the background shows.
            Vec::new()
        } else {
            depths(rng)
        }
    })
}

/// Points on pixel centres at the depths `depths` gives for each pixel (x, y), plus the
/// points [`pixel_centre_scene`] places to be culled (red), in shuffled order.
fn pixel_centre_scene_by_pixel(
    settings: &FrameSettings,
    seed: u64,
    mut depths: impl FnMut(&mut ChaCha8Rng, u32, u32) -> Vec<f64>,
) -> PointCloud {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let cam = settings.camera;
    let (w, h) = (settings.width, settings.height);
    let t = cam.transform(SURVEY_ORIGIN, w, h);
    let inverse = t.view_proj.inverse();
    let depth_of = |p: DVec3| t.depth_row.dot(p.extend(1.0));
    // The point on the ray through NDC (x, y) at linear depth `depth`, relative to the origin.
    let at_depth = |ndc_x: f64, ndc_y: f64, depth: f64| {
        let unproject = |z: f64| {
            let p: DVec4 = inverse * DVec4::new(ndc_x, ndc_y, z, 1.0);
            p.truncate() / p.w
        };
        let (a, b) = (unproject(0.0), unproject(1.0));
        a + (b - a) * ((depth - depth_of(a)) / (depth_of(b) - depth_of(a)))
    };
    let mut points = Vec::new();
    let mut colors = Vec::new();
    let random_color = |rng: &mut ChaCha8Rng| pack_rgba8(rng.random(), rng.random(), rng.random());
    for y in 0..h {
        for x in 0..w {
            let ndc_x = (x as f64 + 0.5) / w as f64 * 2.0 - 1.0;
            let ndc_y = 1.0 - (y as f64 + 0.5) / h as f64 * 2.0;
            for depth in depths(&mut rng, x, y) {
                points.push(SURVEY_ORIGIN + at_depth(ndc_x, ndc_y, depth));
                colors.push(random_color(&mut rng));
            }
        }
    }
    // Points that must not appear.
    let centre_ray = |depth: f64| SURVEY_ORIGIN + at_depth(0.1, -0.2, depth);
    for depth in [-10.0, -1.0, 0.5 * cam.near, cam.far * 1.01, cam.far * 3.0] {
        points.push(centre_ray(depth));
        colors.push(pack_rgba8(255, 0, 0));
    }
    for ndc in [(-1.3, 0.0), (1.3, 0.2), (0.0, 1.4), (0.3, -1.5)] {
        points.push(SURVEY_ORIGIN + at_depth(ndc.0, ndc.1, 40.0));
        colors.push(pack_rgba8(255, 0, 0));
    }
    let mut order: Vec<usize> = (0..points.len()).collect();
    order.shuffle(&mut rng);
    let points: Vec<DVec3> = order.iter().map(|&i| points[i]).collect();
    let colors: Vec<u32> = order.iter().map(|&i| colors[i]).collect();
    PointCloud::from_world_points(&points, colors)
}

/// A renderer on the shared GPU and `cloud` uploaded to it.
fn uploaded(cloud: &PointCloud) -> (Renderer, GpuPointCloud) {
    let renderer = Renderer::new(gpu());
    let resident = renderer.upload(cloud).expect("upload");
    (renderer, resident)
}

pub(super) fn render_gpu(cloud: &PointCloud, settings: &FrameSettings) -> Frame {
    let mut renderer = Renderer::new(gpu());
    let resident = renderer.upload(cloud).expect("upload");
    renderer.render(&resident, settings).expect("render")
}

/// `settings`' frame of `resident` through the `atomics` path.
fn render_with_atomics(
    renderer: &mut Renderer,
    resident: &GpuPointCloud,
    settings: &FrameSettings,
    atomics: AtomicsMode,
) -> Frame {
    let settings = FrameSettings {
        atomics,
        ..*settings
    };
    renderer.render(resident, &settings).expect("render")
}

fn assert_matches_reference(name: &str, cloud: &PointCloud, settings: &FrameSettings) -> Frame {
    let frame = render_gpu(cloud, settings);
    let expected = reference::render_basic(cloud, settings);
    let diff = compare_images(name, &frame.image, &expected.image);
    assert_eq!(
        diff.differing, 0,
        "{name}: GPU and reference differ in {} pixels",
        diff.differing
    );
    frame
}

/// Per pixel: a front surface of several points spread over 0.5% of depth (inside the default
/// 1% band) and points clearly behind it (2% to 30%), which the average must leave out.
fn surface_with_depth_noise(settings: &FrameSettings, seed: u64) -> PointCloud {
    let (near, far) = (settings.camera.near, settings.camera.far);
    pixel_centre_scene_with(settings, seed, |rng| {
        let front = near + (far - near) * rng.random_range(0.1..0.6);
        let mut depths = vec![front];
        depths.extend((0..rng.random_range(1..8)).map(|_| front * rng.random_range(1.0005..1.005)));
        depths.extend((0..rng.random_range(0..4)).map(|_| front * rng.random_range(1.02..1.3)));
        depths
    })
}

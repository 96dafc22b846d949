//! The rasterizer against the CPU reference on synthetic scenes, where the basic mode must
//! match it pixel for pixel. (Real scans are compared in `crate::ingest`'s neighbours:
//! see `real_scan_tests` below.)

use glam::{DVec3, DVec4};
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::*;
use crate::camera::Camera;
use crate::camera::Projection;
use crate::cloud::pack_rgba8;
use crate::reference;
use crate::testing::{compare_images, gpu};

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

pub(super) fn render_gpu(cloud: &PointCloud, settings: &FrameSettings) -> Frame {
    let mut renderer = Renderer::new(gpu());
    let resident = renderer.upload(cloud).expect("upload");
    renderer.render(&resident, settings).expect("render")
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

#[test]
fn basic_mode_equals_the_reference_pixel_for_pixel() {
    let settings = FrameSettings::new(
        160,
        120,
        camera(Projection::Perspective { fov_y_deg: 50.0 }),
    );
    let cloud = pixel_centre_scene(&settings, 3, 1);
    let frame = assert_matches_reference("basic-perspective", &cloud, &settings);
    // The scene really exercises the depth test and the background.
    let background = frame
        .image
        .pixels()
        .filter(|p| p.0 == settings.background)
        .count();
    assert!(
        background > 1000 && background < 160 * 120 / 2,
        "{background} background pixels"
    );
}

/// Bytes per point on the GPU, from the sizes of the buffers that hold the cloud: quantised
/// positions, packed colours and the batch tables.
#[test]
fn points_take_at_most_12_bytes_each_on_the_gpu() {
    let mut renderer = Renderer::new(gpu());
    let cloud = crate::bench::uniform_cube(50_000, 7);
    for chunk_points in [usize::MAX, 3 * BATCH_POINTS] {
        renderer.set_max_chunk_points(chunk_points);
        let resident = renderer.upload(&cloud).expect("upload");
        let per_point = resident.gpu_bytes_per_point();
        assert!(
            (POINT_BYTES as f64..=12.0).contains(&per_point),
            "{per_point} bytes per point in {} chunks",
            resident.chunk_count()
        );
    }
}

/// A cloud uploaded chunk by chunk renders like the same points uploaded whole.
#[test]
fn a_streamed_upload_renders_like_a_whole_one() {
    let settings = FrameSettings::new(96, 64, camera(Projection::Perspective { fov_y_deg: 50.0 }));
    let cloud = pixel_centre_scene(&settings, 2, 21);
    let mut renderer = Renderer::new(gpu());
    let whole = renderer.upload(&cloud).expect("upload");
    let mut next = 0;
    let streamed = renderer
        .upload_chunks(cloud.origin, &mut |n| {
            let range = next..(next + n.min(5000)).min(cloud.len());
            next = range.end;
            (!range.is_empty()).then(|| {
                (
                    cloud.positions[range.clone()].to_vec(),
                    cloud.colors[range].to_vec(),
                )
            })
        })
        .expect("streamed upload");
    assert_eq!(streamed.len(), cloud.len());
    let a = renderer.render(&whole, &settings).expect("render");
    let b = renderer.render(&streamed, &settings).expect("render");
    let diff = compare_images("streamed-upload", &b.image, &a.image);
    assert_eq!(diff.differing, 0);
}

#[test]
fn orthographic_camera_equals_the_reference() {
    let settings = FrameSettings::new(128, 96, camera(Projection::Orthographic { height: 30.0 }));
    let cloud = pixel_centre_scene(&settings, 2, 2);
    assert_matches_reference("basic-orthographic", &cloud, &settings);
}

#[test]
fn large_points_cover_squares_like_the_reference() {
    for point_size in [2, 3, 6] {
        let mut settings =
            FrameSettings::new(96, 64, camera(Projection::Perspective { fov_y_deg: 40.0 }));
        settings.point_size = point_size;
        settings.background = [0, 0, 0, 0];
        let cloud = pixel_centre_scene(&settings, 1, 3);
        // Thin the cloud so the squares overlap partly and leave gaps.
        let sparse: Vec<usize> = (0..cloud.len()).step_by(7).collect();
        assert_matches_reference(
            &format!("point-size-{point_size}"),
            &cloud.select(&sparse),
            &settings,
        );
    }
}

#[test]
fn large_points_centred_off_the_image_draw_their_squares_inside_part() {
    // Splat corners left of and above the image: pixel coordinates below zero, which the
    // shaders turn into integers without WGSL's clamping conversion (`floor_to_i32`).
    let mut settings =
        FrameSettings::new(64, 48, camera(Projection::Perspective { fov_y_deg: 40.0 }));
    settings.point_size = 7;
    settings.background = [0, 0, 0, 0];
    let t = settings
        .camera
        .transform(SURVEY_ORIGIN, settings.width, settings.height);
    let inverse = t.view_proj.inverse();
    let (w, h) = (f64::from(settings.width), f64::from(settings.height));
    let mut points = Vec::new();
    let mut colors = Vec::new();
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    // A ring of pixel centres from 6 pixels outside each edge to 2 inside it.
    for y in -6..(settings.height as i32 + 6) {
        for x in -6..(settings.width as i32 + 6) {
            let inside =
                x >= 2 && y >= 2 && x < settings.width as i32 - 2 && y < settings.height as i32 - 2;
            if inside || rng.random_bool(0.6) {
                continue;
            }
            let ndc_x = (f64::from(x) + 0.5) / w * 2.0 - 1.0;
            let ndc_y = 1.0 - (f64::from(y) + 0.5) / h * 2.0;
            let p: DVec4 = inverse * DVec4::new(ndc_x, ndc_y, rng.random_range(0.2..0.8), 1.0);
            points.push(SURVEY_ORIGIN + p.truncate() / p.w);
            colors.push(pack_rgba8(rng.random(), rng.random(), rng.random()));
        }
    }
    let cloud = PointCloud::from_world_points(&points, colors);
    assert_matches_reference("point-size-7-off-edges", &cloud, &settings);
}

#[test]
fn fallback_32_bit_path_renders_the_same_image_as_the_64_bit_path() {
    let gpu = gpu();
    assert!(
        gpu.capabilities.int64_atomics,
        "this adapter lacks 64-bit atomics; the comparison needs both paths"
    );
    let mut settings = FrameSettings::new(
        160,
        120,
        camera(Projection::Perspective { fov_y_deg: 50.0 }),
    );
    settings.read_depth = true;
    // Many points per pixel, including exact depth ties broken by colour.
    let mut cloud = pixel_centre_scene(&settings, 4, 4);
    let duplicates: Vec<usize> = (0..cloud.len())
        .chain((0..cloud.len()).step_by(3))
        .collect();
    cloud = cloud.select(&duplicates);
    for (i, c) in cloud
        .colors
        .iter_mut()
        .enumerate()
        .skip(cloud.positions.len() * 3 / 4)
    {
        *c = pack_rgba8(i as u8, 0, 255 - i as u8);
    }
    let mut renderer = Renderer::new(gpu);
    let resident = renderer.upload(&cloud).expect("upload");
    let wide = renderer.render(&resident, &settings).expect("64-bit");
    settings.atomics = AtomicsMode::Force32;
    let narrow = renderer.render(&resident, &settings).expect("32-bit");
    assert_eq!(wide.atomics, AtomicsPath::Atomic64);
    assert_eq!(narrow.atomics, AtomicsPath::Atomic32);
    let diff = compare_images("fallback-vs-64", &narrow.image, &wide.image);
    assert_eq!(diff.differing, 0);
    assert_eq!(narrow.depth, wide.depth);
    // Against the reference, exactly, except at a few depth ties: a point and its copy in
    // another batch are quantised apart by a rounding error, and a real GPU's fused
    // multiply-adds can put either in front (seen at 1 of ~4,800 tied pixels on an H200).
    let expected = reference::render_basic(&cloud, &settings).image;
    let ties = reference::depth_ties(&cloud, &settings, 1e-5);
    let tied = ties.iter().filter(|&&t| t).count();
    let differing: Vec<usize> = narrow
        .image
        .pixels()
        .zip(expected.pixels())
        .enumerate()
        .filter(|(_, (a, e))| a != e)
        .map(|(pixel, _)| pixel)
        .collect();
    if !differing.is_empty() {
        compare_images("fallback-vs-reference", &narrow.image, &expected);
    }
    assert!(
        differing.iter().all(|&pixel| ties[pixel]),
        "pixels without a depth tie differ from the reference"
    );
    assert!(
        tied > 1000 && differing.len() <= tied / 500,
        "{} of {tied} tied pixels differ from the reference",
        differing.len()
    );
}

/// The point passes' workgroup size depends on the adapter (one subgroup on lavapipe, 128 on
/// GPUs: `point_workgroup.rs`). Every size renders the same image, in both modes and on both
/// atomics paths, with several chunks and point sizes.
#[test]
fn every_point_workgroup_size_renders_the_same_image() {
    let gpu = gpu();
    let mut settings = FrameSettings::new(
        160,
        120,
        camera(Projection::Perspective { fov_y_deg: 50.0 }),
    );
    settings.read_depth = true;
    let cloud = surface_with_depth_noise(&settings, 11);
    let sizes = [4, 8, 32, 128, 256];
    let mut renderers: Vec<_> = sizes
        .iter()
        .map(|&size| {
            let mut renderer = Renderer::with_point_workgroup_size(gpu.clone(), size);
            renderer.set_max_chunk_points(2 * BATCH_POINTS);
            let resident = renderer.upload(&cloud).expect("upload");
            (renderer, resident)
        })
        .collect();
    assert!(renderers[0].1.chunk_count() > 1);
    for quality in [Quality::Basic, Quality::HIGH] {
        for atomics in [AtomicsMode::Auto, AtomicsMode::Force32] {
            for point_size in [1, 2] {
                let settings = FrameSettings {
                    quality,
                    atomics,
                    point_size,
                    ..settings
                };
                let frames: Vec<Frame> = renderers
                    .iter_mut()
                    .map(|(renderer, resident)| {
                        renderer.render(resident, &settings).expect("render")
                    })
                    .collect();
                for (size, frame) in sizes.iter().zip(&frames).skip(1) {
                    let name = format!("workgroup-{size}-{quality:?}-{atomics:?}-{point_size}");
                    let diff = compare_images(&name, &frame.image, &frames[0].image);
                    assert_eq!(diff.differing, 0, "{name}");
                    assert_eq!(frame.depth, frames[0].depth, "{name}");
                }
            }
        }
    }
}

/// The resolves take runs of consecutive pixels per invocation (`resolve_pass.rs`): at image
/// sizes whose pixel runs end in a partial one, both modes still equal the reference, and
/// the framebuffer is emptied for the next frame (a frame after a different view equals the
/// first).
#[test]
fn odd_image_sizes_resolve_their_last_pixels_and_empty_the_framebuffer() {
    let mut renderer = Renderer::new(gpu());
    for (width, height) in [(101, 77), (37, 29)] {
        let basic = FrameSettings::new(
            width,
            height,
            camera(Projection::Perspective { fov_y_deg: 50.0 }),
        );
        let high = FrameSettings {
            quality: Quality::HIGH,
            read_depth: true,
            ..basic
        };
        let elsewhere = |settings: FrameSettings| FrameSettings {
            camera: settings.camera.moved_sideways(9.0, 4.0),
            ..settings
        };
        for (settings, cloud) in [
            (basic, pixel_centre_scene(&basic, 3, 5)),
            (high, surface_with_depth_noise(&high, 6)),
        ] {
            let name = format!("odd-size-{width}x{height}-{:?}", settings.quality);
            let resident = renderer.upload(&cloud).expect("upload");
            let first = renderer.render(&resident, &settings).expect("render");
            let expected = reference::render(&cloud, &settings);
            let difference = max_channel_difference(&first.image, &expected.image);
            let allowed = u8::from(settings.quality != Quality::Basic);
            assert!(difference <= allowed, "{name}: differs by {difference}/255");
            let moved = renderer
                .render(&resident, &elsewhere(settings))
                .expect("render");
            let fresh = render_gpu(&cloud, &elsewhere(settings));
            let diff = compare_images(&format!("{name}-moved"), &moved.image, &fresh.image);
            assert_eq!(diff.differing, 0, "{name}: the moved view");
            let again = renderer.render(&resident, &settings).expect("render");
            let diff = compare_images(&format!("{name}-again"), &again.image, &first.image);
            assert_eq!(diff.differing, 0, "{name}: the first view again");
            assert_eq!(again.depth, first.depth, "{name}");
        }
    }
}

/// The resolve visits only the pixels this frame's or the last frame's points can touch
/// (`targets.rs`). Frames rendered one after another on one renderer, with the cloud moving
/// across the image and out of it, and the background, mode, depth read-back, point size,
/// filling and shading changing, equal the same frames rendered on fresh renderers.
#[test]
fn consecutive_frames_equal_fresh_ones_while_the_resolve_skips_clean_pixels() {
    let gpu = gpu();
    let centre = FrameSettings::new(
        160,
        120,
        camera(Projection::Perspective { fov_y_deg: 50.0 }),
    );
    // A noisy surface near the target's depth, without the points placed to be culled, which
    // would stretch their batches' boxes over the whole image.
    let surface = pixel_centre_scene_with(&centre, 13, |rng| {
        let front = rng.random_range(50.0..54.0);
        let mut depths = vec![front];
        depths.extend((0..rng.random_range(1..6)).map(|_| front * rng.random_range(1.0005..1.005)));
        depths.extend((0..rng.random_range(0..3)).map(|_| front * rng.random_range(1.02..1.1)));
        depths
    });
    let kept: Vec<usize> = (0..surface.len())
        .filter(|&i| surface.colors[i] != pack_rgba8(255, 0, 0))
        .collect();
    let cloud = surface.select(&kept);
    // The camera slid sideways by `right` and `up` (in units of the view's width at the
    // target): the cloud moves towards a corner of the image, or out of it.
    let slid = |right: f64, up: f64, settings: FrameSettings| {
        let c = settings.camera;
        let width = 2.0 * (c.target - c.position).length() * (25f64.to_radians()).tan() * 4.0 / 3.0;
        FrameSettings {
            camera: c.moved_sideways(right * width, up * width),
            ..settings
        }
    };
    let sequence = [
        centre,
        slid(0.0, 0.6, centre),
        FrameSettings {
            read_depth: true,
            ..slid(0.0, 0.6, centre)
        },
        slid(0.4, 0.3, centre),
        slid(-0.5, -0.2, centre),
        slid(3.0, 0.0, centre),
        slid(0.3, 0.0, centre),
        FrameSettings {
            background: [200, 210, 220, 255],
            ..slid(0.3, 0.0, centre)
        },
        FrameSettings {
            quality: Quality::HIGH,
            read_depth: true,
            ..slid(-0.4, 0.2, centre)
        },
        FrameSettings {
            read_depth: true,
            ..slid(0.4, -0.3, centre)
        },
        FrameSettings {
            shading: Shading::EDL,
            ..slid(0.2, 0.2, centre)
        },
        slid(-0.3, -0.3, centre),
        FrameSettings {
            fill: Some(FillSettings::default()),
            read_depth: true,
            ..slid(0.3, 0.1, centre)
        },
        FrameSettings {
            point_size: 3,
            ..slid(-0.2, 0.4, centre)
        },
        FrameSettings {
            quality: Quality::HIGH,
            ..slid(0.5, 0.4, centre)
        },
        centre,
    ];
    let mut renderer = Renderer::new(gpu);
    let resident = renderer.upload(&cloud).expect("upload");
    let mut partly_covered = 0;
    for (step, settings) in sequence.iter().enumerate() {
        let frame = renderer.render(&resident, settings).expect("render");
        let fresh = render_gpu(&cloud, settings);
        let name = format!("sequence-{step}");
        let diff = compare_images(&name, &frame.image, &fresh.image);
        assert_eq!(diff.differing, 0, "{name}: {settings:?}");
        assert_eq!(frame.depth, fresh.depth, "{name}");
        let covered = frame
            .image
            .pixels()
            .filter(|p| p.0 != settings.background)
            .count();
        partly_covered += usize::from(covered > 0 && covered < 160 * 120 / 2);
    }
    assert!(
        partly_covered >= 6,
        "only {partly_covered} frames cover part of the image"
    );
}

#[test]
fn a_cloud_larger_than_one_binding_renders_in_chunks() {
    let settings = FrameSettings::new(
        160,
        120,
        camera(Projection::Perspective { fov_y_deg: 50.0 }),
    );
    let cloud = pixel_centre_scene(&settings, 3, 5);
    let mut renderer = Renderer::new(gpu());
    // Lower the binding limit to two batches per chunk.
    renderer.set_max_chunk_points(2 * BATCH_POINTS);
    let resident = renderer.upload(&cloud).expect("upload");
    assert!(
        resident.chunk_count() >= 4,
        "only {} chunks",
        resident.chunk_count()
    );
    for atomics in [AtomicsMode::Auto, AtomicsMode::Force32] {
        let frame = renderer
            .render(
                &resident,
                &FrameSettings {
                    atomics,
                    ..settings
                },
            )
            .expect("render");
        let expected = reference::render_basic(&cloud, &settings);
        assert_eq!(
            compare_images("chunked", &frame.image, &expected.image).differing,
            0
        );
    }
}

#[test]
fn batch_culling_keeps_every_point_that_is_in_view() {
    // A wide field of scattered clusters, seen through a narrow camera: most batches are
    // culled, and the image must still equal the reference.
    let mut rng = ChaCha8Rng::seed_from_u64(6);
    let mut points = Vec::new();
    for _ in 0..40_000 {
        points.push(
            SURVEY_ORIGIN
                + DVec3::new(
                    rng.random_range(-500.0..500.0),
                    rng.random_range(-500.0..500.0),
                    rng.random_range(-5.0..5.0),
                ),
        );
    }
    let colors = (0..points.len())
        .map(|i| pack_rgba8(i as u8, (i >> 8) as u8, 200))
        .collect();
    let cloud = PointCloud::from_world_points(&points, colors);
    let cam = Camera {
        position: SURVEY_ORIGIN + DVec3::new(0.0, -120.0, 60.0),
        target: SURVEY_ORIGIN,
        up: DVec3::Z,
        projection: Projection::Perspective { fov_y_deg: 30.0 },
        near: 1.0,
        far: 400.0,
    };
    let mut settings = FrameSettings::new(200, 150, cam);
    settings.point_size = 2;
    let frame = assert_matches_reference("culling", &cloud, &settings);
    assert!(
        frame.image.pixels().any(|p| p.0 != settings.background),
        "something is in view"
    );
}

#[test]
fn depth_image_holds_linear_depth() {
    let mut settings =
        FrameSettings::new(64, 48, camera(Projection::Perspective { fov_y_deg: 50.0 }));
    settings.read_depth = true;
    let cloud = pixel_centre_scene(&settings, 2, 7);
    let frame = render_gpu(&cloud, &settings);
    let expected = reference::render_basic(&cloud, &settings);
    let depth = frame.depth.expect("depth was requested");
    for (gpu_depth, reference_depth) in depth.iter().zip(&expected.depth) {
        if reference_depth.is_infinite() {
            assert!(gpu_depth.is_infinite());
        } else {
            assert!(
                (gpu_depth - reference_depth).abs() <= reference_depth * 1e-5,
                "{gpu_depth} vs {reference_depth}"
            );
        }
    }
}

#[test]
fn every_frame_reports_its_stage_timings() {
    let settings = FrameSettings::new(64, 48, camera(Projection::Perspective { fov_y_deg: 50.0 }));
    let cloud = pixel_centre_scene(&settings, 1, 8);
    let mut renderer = Renderer::new(gpu());
    let resident = renderer.upload(&cloud).expect("upload");
    let mut first = renderer.render(&resident, &settings).expect("render");
    let second = renderer.render(&resident, &settings).expect("render");
    for frame in [&first, &second] {
        for stage in [
            Stage::Upload,
            Stage::Cull,
            Stage::Rasterize,
            Stage::Resolve,
            Stage::Readback,
        ] {
            let ms = frame.timings.get(stage).expect("stage timed");
            assert!(ms.is_finite() && ms >= 0.0, "{stage:?}: {ms}");
        }
    }
    let expected_clock = if gpu().capabilities.timestamps {
        Clock::Gpu
    } else {
        Clock::Host
    };
    let rasterize = first
        .timings
        .stages
        .iter()
        .find(|t| t.stage == Stage::Rasterize);
    assert_eq!(rasterize.map(|t| t.clock), Some(expected_clock));
    // The point upload is reported once, by the first frame; later frames reuse the buffers.
    assert!(first.timings.get(Stage::Upload) > second.timings.get(Stage::Upload));
    let dir = tempfile::tempdir().expect("tempdir");
    crate::encode::save_png(&mut first, &dir.path().join("frame.png")).expect("png");
    assert!(first.timings.get(Stage::Encode).is_some());
    let line = first.timings.to_string();
    assert!(
        line.contains("rasterize") && line.contains("encode"),
        "{line}"
    );
}

#[test]
fn host_clocks_time_the_passes_without_timestamp_queries() {
    let settings = FrameSettings::new(64, 48, camera(Projection::Perspective { fov_y_deg: 50.0 }));
    let cloud = pixel_centre_scene(&settings, 1, 9);
    let mut renderer = Renderer::new(gpu());
    renderer.use_host_clocks();
    let resident = renderer.upload(&cloud).expect("upload");
    let frame = renderer.render(&resident, &settings).expect("render");
    for stage in [Stage::Rasterize, Stage::Resolve] {
        let timing = frame
            .timings
            .stages
            .iter()
            .find(|t| t.stage == stage)
            .expect("timed");
        assert_eq!(timing.clock, Clock::Host);
        assert!(timing.ms > 0.0);
    }
    let expected = reference::render_basic(&cloud, &settings);
    assert_eq!(
        compare_images("host-clocks", &frame.image, &expected.image).differing,
        0
    );
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

/// Largest difference of any channel of any pixel.
fn max_channel_difference(a: &image::RgbaImage, b: &image::RgbaImage) -> u8 {
    a.as_raw()
        .iter()
        .zip(b.as_raw())
        .map(|(x, y)| x.abs_diff(*y))
        .max()
        .unwrap_or(0)
}

/// The high-quality accumulation adds its sums with 64-bit atomics where the device has them
/// (`hq_pass.rs`) and with 32-bit ones otherwise: both give the reference's image, the same to
/// the bit, with and without large points.
#[test]
fn high_quality_sums_are_the_same_with_64_and_32_bit_atomics() {
    let gpu = gpu();
    eprintln!(
        "64-bit atomicAdd on this adapter: {}",
        gpu.capabilities.int64_atomic_add
    );
    let mut renderer = Renderer::new(gpu);
    for point_size in [1, 3] {
        let mut settings =
            FrameSettings::new(96, 64, camera(Projection::Perspective { fov_y_deg: 50.0 }));
        settings.quality = Quality::HIGH;
        settings.read_depth = true;
        settings.point_size = point_size;
        let cloud = surface_with_depth_noise(&settings, 11);
        let resident = renderer.upload(&cloud).expect("upload");
        let auto = renderer.render(&resident, &settings).expect("render");
        let forced = FrameSettings {
            atomics: AtomicsMode::Force32,
            ..settings
        };
        let with_32 = renderer.render(&resident, &forced).expect("render");
        let name = format!("hq-sums-size-{point_size}");
        let diff = compare_images(&name, &auto.image, &with_32.image);
        assert_eq!(diff.differing, 0, "{name}");
        assert_eq!(auto.depth, with_32.depth, "{name}");
        let expected = reference::render(&cloud, &settings);
        let difference = max_channel_difference(&auto.image, &expected.image);
        assert!(difference <= 1, "{name}: differs by {difference}/255");
    }
}

/// Pixels with more points in the depth band than the packed sums hold (256) spill into the
/// wide sums (`shaders/hq_sums_atomic64.wgsl`): their averages stay exact, the same as the
/// 32-bit path's to the bit and the reference's, frame after frame.
#[test]
fn high_quality_averages_pixels_deeper_than_the_packed_sums() {
    let mut renderer = Renderer::new(gpu());
    let mut settings =
        FrameSettings::new(24, 16, camera(Projection::Perspective { fov_y_deg: 50.0 }));
    settings.quality = Quality::HIGH;
    let (near, far) = (settings.camera.near, settings.camera.far);
    // From one point to a thousand in a pixel's band: some fit the packed sums, most not.
    let cloud = pixel_centre_scene_with(&settings, 12, |rng| {
        let front = near + (far - near) * rng.random_range(0.1..0.6);
        let points = rng.random_range(1..1000);
        (0..points)
            .map(|_| front * rng.random_range(1.0..1.005))
            .collect()
    });
    // Bright colours, so that a channel's sum over more than 257 points overflows 16 bits.
    let mut rng = ChaCha8Rng::seed_from_u64(13);
    let mut cloud = cloud;
    for color in &mut cloud.colors {
        let mut channel = || rng.random_range(224..=255);
        *color = pack_rgba8(channel(), channel(), channel());
    }
    let resident = renderer.upload(&cloud).expect("upload");
    let expected = reference::render(&cloud, &settings);
    let forced = FrameSettings {
        atomics: AtomicsMode::Force32,
        ..settings
    };
    for round in 0..2 {
        let auto = renderer.render(&resident, &settings).expect("render");
        let with_32 = renderer.render(&resident, &forced).expect("render");
        let name = format!("hq-deep-pixels-{round}");
        let diff = compare_images(&name, &auto.image, &with_32.image);
        assert_eq!(diff.differing, 0, "{name}");
        let difference = max_channel_difference(&auto.image, &expected.image);
        assert!(difference <= 1, "{name}: differs by {difference}/255");
    }
}

#[test]
fn high_quality_mode_averages_the_front_surface_like_the_reference() {
    let mut settings = FrameSettings::new(
        160,
        120,
        camera(Projection::Perspective { fov_y_deg: 50.0 }),
    );
    settings.quality = Quality::HIGH;
    settings.read_depth = true;
    let cloud = surface_with_depth_noise(&settings, 10);
    let mut renderer = Renderer::new(gpu());
    let resident = renderer.upload(&cloud).expect("upload");
    let frame = renderer.render(&resident, &settings).expect("render");
    let expected = reference::render(&cloud, &settings);
    let difference = max_channel_difference(&frame.image, &expected.image);
    let diff = compare_images("hq-average", &frame.image, &expected.image);
    eprintln!(
        "high quality: {} pixels differ, by at most {difference}/255",
        diff.differing
    );
    assert!(difference <= 1, "a channel differs by {difference}/255");
    let depth = frame.depth.as_deref().expect("depth was requested");
    for (gpu_depth, reference_depth) in depth.iter().zip(&expected.depth) {
        assert!(
            gpu_depth == reference_depth
                || (gpu_depth - reference_depth).abs() <= reference_depth * 1e-5
        );
    }
    assert!(
        frame.timings.get(Stage::Accumulate).is_some(),
        "{}",
        frame.timings
    );

    // The average really is not the nearest point's colour.
    let basic = renderer
        .render(
            &resident,
            &FrameSettings {
                quality: Quality::Basic,
                ..settings
            },
        )
        .expect("basic");
    let changed = compare_images("hq-vs-basic", &frame.image, &basic.image).differing;
    assert!(
        changed > 160 * 120 / 4,
        "only {changed} pixels differ from the basic mode"
    );
}

#[test]
fn high_quality_band_is_configurable() {
    let mut settings =
        FrameSettings::new(96, 64, camera(Projection::Perspective { fov_y_deg: 50.0 }));
    let cloud = surface_with_depth_noise(&settings, 11);
    let mut renderer = Renderer::new(gpu());
    let resident = renderer.upload(&cloud).expect("upload");
    // A zero band averages only points at exactly the nearest depth: the basic image, up to
    // ties; a 50% band takes in the points behind the surface as well.
    for depth_band in [0.0, 0.5] {
        settings.quality = Quality::High { depth_band };
        let frame = renderer.render(&resident, &settings).expect("render");
        let expected = reference::render(&cloud, &settings);
        assert!(
            max_channel_difference(&frame.image, &expected.image) <= 1,
            "band {depth_band}"
        );
    }
    settings.quality = Quality::High { depth_band: 0.0 };
    let zero_band = renderer.render(&resident, &settings).expect("render");
    settings.quality = Quality::Basic;
    let basic = renderer.render(&resident, &settings).expect("render");
    assert_eq!(
        compare_images("hq-zero-band", &zero_band.image, &basic.image).differing,
        0
    );
    for bad in [f32::NAN, -0.1, 2.0] {
        settings.quality = Quality::High { depth_band: bad };
        assert!(matches!(
            renderer.validate(&settings),
            Err(RenderError::DepthBand(_))
        ));
    }
}

#[test]
fn eye_dome_lighting_matches_the_reference_and_outlines_silhouettes() {
    let mut settings = FrameSettings::new(
        160,
        120,
        camera(Projection::Perspective { fov_y_deg: 50.0 }),
    );
    let cloud = pixel_centre_scene(&settings, 2, 12);
    let mut renderer = Renderer::new(gpu());
    let resident = renderer.upload(&cloud).expect("upload");
    let plain = renderer.render(&resident, &settings).expect("plain");
    for (quality, shading) in [
        (Quality::Basic, Shading::EDL),
        (
            Quality::Basic,
            Shading::Edl {
                strength: 0.3,
                radius: 3.0,
            },
        ),
        (Quality::HIGH, Shading::EDL),
    ] {
        settings.quality = quality;
        settings.shading = shading;
        let frame = renderer.render(&resident, &settings).expect("render");
        let expected = reference::render(&cloud, &settings);
        let difference = max_channel_difference(&frame.image, &expected.image);
        assert!(
            difference <= 1,
            "{shading:?}: a channel differs by {difference}/255"
        );
        assert!(frame.timings.get(Stage::Shade).is_some());
        if quality == Quality::Basic {
            let darkened = compare_images("edl-vs-plain", &frame.image, &plain.image).differing;
            assert!(
                darkened > 160 * 120 / 10,
                "{shading:?}: only {darkened} pixels shaded"
            );
        }
    }
    settings.shading = Shading::Edl {
        strength: f32::NAN,
        radius: 1.0,
    };
    assert!(matches!(
        renderer.validate(&settings),
        Err(RenderError::Edl { .. })
    ));
}

#[test]
fn supersampling_renders_larger_and_averages_blocks() {
    let mut settings =
        FrameSettings::new(80, 60, camera(Projection::Perspective { fov_y_deg: 50.0 }));
    settings.supersample = 2;
    settings.read_depth = true;
    let big = settings.scaled_for_supersampling();
    assert_eq!((big.width, big.height, big.point_size), (160, 120, 2));
    let cloud = pixel_centre_scene(&big, 2, 13);
    let frame = render_gpu(&cloud, &settings);
    assert_eq!(frame.image.dimensions(), (80, 60));
    assert!(frame.timings.get(Stage::Downsample).is_some());
    let reference = reference::render(&cloud, &big);
    let expected = downsample(
        Frame {
            image: reference.image,
            depth: Some(reference.depth),
            timings: StageTimings::default(),
            atomics: AtomicsPath::Atomic32,
        },
        2,
    );
    assert_eq!(
        compare_images("ssaa", &frame.image, &expected.image).differing,
        0
    );
    // Edges are blended: some pixels hold colours no single point has.
    let blended = frame
        .image
        .pixels()
        .filter(|p| p.0[3] != 255 || p.0 == [0, 0, 0, 0])
        .count();
    assert!(
        frame.image.pixels().any(|p| p.0 != settings.background),
        "{blended}"
    );
    let mut invalid = settings;
    invalid.supersample = 9;
    assert!(matches!(
        Renderer::new(gpu()).validate(&invalid),
        Err(RenderError::Supersample(9))
    ));
}

#[test]
fn depth_image_is_written_as_16_bit_png() {
    let mut settings =
        FrameSettings::new(64, 48, camera(Projection::Perspective { fov_y_deg: 50.0 }));
    settings.read_depth = true;
    let cloud = pixel_centre_scene(&settings, 1, 14);
    let frame = render_gpu(&cloud, &settings);
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("depth.png");
    crate::encode::save_depth_png16(&frame, &path, settings.camera.near, settings.camera.far)
        .expect("write");
    let read = image::open(&path).expect("read").into_luma16();
    let depth = frame.depth.as_ref().expect("depth");
    for (i, value) in read.pixels().enumerate() {
        let d = depth[i];
        if d.is_finite() {
            let expected = 1.0
                + (d as f64 - settings.camera.near) / (settings.camera.far - settings.camera.near)
                    * 65534.0;
            assert!(
                (value.0[0] as f64 - expected).abs() <= 1.0,
                "{} vs {expected}",
                value.0[0]
            );
        } else {
            assert_eq!(value.0[0], 0, "background is 0");
        }
    }
}

#[test]
fn invalid_settings_are_refused_before_any_gpu_work() {
    let renderer = Renderer::new(gpu());
    let good = FrameSettings::new(64, 48, camera(Projection::Perspective { fov_y_deg: 50.0 }));
    renderer.validate(&good).expect("good settings");
    let huge = FrameSettings {
        width: 100_000,
        height: 100_000,
        ..good
    };
    assert!(matches!(
        renderer.validate(&huge),
        Err(RenderError::ImageSize { .. })
    ));
    let too_many_pixels = FrameSettings {
        width: 16_000,
        height: 16_000,
        ..good
    };
    // 2 GB of framebuffer: over most adapters' binding limit (lavapipe's is 128 MiB), not
    // over every one's (an H200's is 4 GiB).
    let result = renderer.validate(&too_many_pixels);
    if gpu().capabilities.max_storage_binding_bytes < 16_000 * 16_000 * 8 {
        assert!(
            matches!(result, Err(RenderError::ImageTooLarge { .. })),
            "{result:?}"
        );
    } else {
        result.expect("within this adapter's binding limit");
    }
    let zero = FrameSettings { width: 0, ..good };
    assert!(renderer.validate(&zero).is_err());
    let mut nan = good;
    nan.camera.position.x = f64::NAN;
    let err = renderer.validate(&nan).expect_err("NaN camera");
    assert!(err.to_string().contains("position"), "{err}");
    assert!(matches!(
        renderer.validate(&FrameSettings {
            point_size: 0,
            ..good
        }),
        Err(RenderError::PointSize(0))
    ));
    assert!(matches!(
        renderer.upload(&PointCloud::from_world_points(&[], vec![])),
        Err(RenderError::EmptyCloud)
    ));
}

/// A wall with a window in front of a deep block of points: the batches behind the wall are
/// skipped whole (occlusion culling), the ones seen through the window are drawn, and every
/// mode renders what the reference does.
#[test]
fn batches_hidden_behind_a_wall_are_skipped_and_the_image_is_unchanged() {
    // Looking straight down, so that the near-to-far order draws the wall first.
    let base = FrameSettings::new(
        256,
        192,
        Camera {
            position: SURVEY_ORIGIN + DVec3::new(0.0, 0.0, 200.0),
            target: SURVEY_ORIGIN,
            up: DVec3::Y,
            projection: Projection::Orthographic { height: 15.0 },
            near: 5.0,
            far: 300.0,
        },
    );
    let window = |x: u32, y: u32| x < 40 && y < 30;
    let scene = pixel_centre_scene_by_pixel(&base, 17, |rng, x, y| {
        // The wall at depth 20 (none in the window), then 12 points a pixel between 60 and 140.
        let mut depths = if window(x, y) { vec![] } else { vec![20.0] };
        depths.extend((0..12).map(|_| rng.random_range(60.0..140.0)));
        depths
    });
    // Without the points placed to be culled, whose batches would span the whole view.
    let kept: Vec<usize> = (0..scene.len())
        .filter(|&i| scene.colors[i] != pack_rgba8(255, 0, 0))
        .collect();
    let cloud = scene.select(&kept);
    let batches = cloud.len().div_ceil(BATCH_POINTS) as u32;

    let mut renderer = Renderer::new(gpu());
    let resident = renderer.upload(&cloud).expect("upload");
    let expected = reference::render(&cloud, &base);
    for atomics in [AtomicsMode::Auto, AtomicsMode::Force32] {
        let settings = FrameSettings { atomics, ..base };
        let frame = renderer.render(&resident, &settings).expect("render");
        let name = format!("occlusion-{atomics:?}");
        assert_eq!(
            compare_images(&name, &frame.image, &expected.image).differing,
            0,
            "{name}"
        );
        let skipped = renderer.occlusion_skipped().expect("counts");
        eprintln!("{name}: {skipped:?} of {batches} batches skipped");
        // The far block's batches behind the wall, drawn after the first phase.
        assert!(
            skipped.depth_pass * 3 >= batches,
            "{name}: only {skipped:?} of {batches} batches skipped"
        );
        if atomics == AtomicsMode::Force32 {
            assert!(
                skipped.later_passes > skipped.depth_pass,
                "{name}: {skipped:?}"
            );
        }
    }

    let settings = FrameSettings {
        quality: Quality::HIGH,
        ..base
    };
    let frame = renderer.render(&resident, &settings).expect("render");
    let expected = reference::render(&cloud, &settings);
    assert!(max_channel_difference(&frame.image, &expected.image) <= 1);
    let skipped = renderer.occlusion_skipped().expect("counts");
    eprintln!("high quality: {skipped:?} of {batches} batches skipped");
    // The accumulation tests against the final depths: every batch behind the wall but not
    // behind the window is skipped.
    assert!(
        skipped.later_passes * 2 >= batches,
        "high quality: only {skipped:?} of {batches} batches skipped"
    );
    // The points seen through the window are drawn: the window shows the block, not the
    // background.
    let inside = frame.image.get_pixel(10, 10);
    assert_ne!(inside.0, base.background, "the window shows nothing");
}

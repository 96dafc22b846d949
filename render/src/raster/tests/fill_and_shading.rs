//! Visibility, filling and shading (Eye-Dome Lighting; Pintus et al. 2011) against the CPU
//! reference and against the ground truth of analytic scenes.

use glam::{DVec3, DVec4};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::render_gpu;
use super::*;
use crate::camera::Camera;
use crate::camera::Projection;
use crate::cloud::pack_rgba8;
use crate::reference;
use crate::testing::compare_images;

const ORIGIN: DVec3 = DVec3::new(515_370.0, 4_918_340.0, 2_200.0);
const WIDTH: u32 = 160;
const HEIGHT: u32 = 120;

/// The sphere scene's camera at another size (the golden images).
pub(super) fn sphere_settings(width: u32, height: u32) -> FrameSettings {
    FrameSettings {
        width,
        height,
        read_depth: false,
        ..settings(Projection::Perspective { fov_y_deg: 50.0 })
    }
}

fn settings(projection: Projection) -> FrameSettings {
    let camera = Camera {
        position: ORIGIN + DVec3::new(0.0, -10.0, 0.0),
        target: ORIGIN,
        up: DVec3::Z,
        projection,
        near: 1.0,
        far: 100.0,
    };
    let mut settings = FrameSettings::new(WIDTH, HEIGHT, camera);
    settings.read_depth = true;
    settings
}

/// The world point on the ray through pixel centre (x, y) at linear depth `depth`, and the
/// ray itself (world origin and unit direction).
struct Rays {
    inverse: glam::DMat4,
    depth_row: DVec4,
    width: f64,
    height: f64,
}

impl Rays {
    fn new(settings: &FrameSettings) -> Self {
        let t = settings
            .camera
            .transform(ORIGIN, settings.width, settings.height);
        Self {
            inverse: t.view_proj.inverse(),
            depth_row: t.depth_row,
            width: settings.width as f64,
            height: settings.height as f64,
        }
    }

    /// Two points (relative to ORIGIN) on the ray through (px, py) in pixels.
    fn ray(&self, px: f64, py: f64) -> (DVec3, DVec3) {
        let ndc_x = px / self.width * 2.0 - 1.0;
        let ndc_y = 1.0 - py / self.height * 2.0;
        let at = |z: f64| {
            let p = self.inverse * DVec4::new(ndc_x, ndc_y, z, 1.0);
            p.truncate() / p.w
        };
        (at(0.0), at(1.0))
    }

    fn depth_of(&self, p: DVec3) -> f64 {
        self.depth_row.dot(p.extend(1.0))
    }

    fn at_depth(&self, px: f64, py: f64, depth: f64) -> DVec3 {
        let (a, b) = self.ray(px, py);
        ORIGIN + a + (b - a) * ((depth - self.depth_of(a)) / (self.depth_of(b) - self.depth_of(a)))
    }

    /// Linear depth where the ray through the pixel centre first meets the sphere.
    fn sphere_depth(&self, x: u32, y: u32, centre: DVec3, radius: f64) -> Option<f64> {
        let (a, b) = self.ray(x as f64 + 0.5, y as f64 + 0.5);
        let dir = (b - a).normalize();
        let oc = a - (centre - ORIGIN);
        let half_b = oc.dot(dir);
        let c = oc.length_squared() - radius * radius;
        let disc = half_b * half_b - c;
        (disc >= 0.0).then(|| self.depth_of(a + dir * (-half_b - disc.sqrt())))
    }
}

fn random_color(rng: &mut ChaCha8Rng) -> u32 {
    pack_rgba8(
        rng.random_range(60..200),
        rng.random_range(60..200),
        rng.random(),
    )
}

/// A sparse front plane (30% of its pixels, on pixel centres, depth 20) over a dense back
/// plane (every pixel, depth 40). The front plane covers the rectangle `FRONT`.
const FRONT: (std::ops::Range<u32>, std::ops::Range<u32>) = (40..120, 30..90);

fn two_planes(settings: &FrameSettings) -> PointCloud {
    let rays = Rays::new(settings);
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let (mut points, mut colors) = (Vec::new(), Vec::new());
    for y in 0..settings.height {
        for x in 0..settings.width {
            let (px, py) = (x as f64 + 0.5, y as f64 + 0.5);
            points.push(rays.at_depth(px, py, 40.0));
            colors.push(pack_rgba8(200, 40, 40));
            if FRONT.0.contains(&x) && FRONT.1.contains(&y) && rng.random_bool(0.3) {
                points.push(rays.at_depth(px, py, 20.0));
                colors.push(random_color(&mut rng));
            }
        }
    }
    PointCloud::from_world_points(&points, colors)
}

const SPHERE_RADIUS: f64 = 3.0;

/// Points uniformly at random over a whole sphere (front and back), about one per pixel of
/// its image: holes of a few pixels, and back points behind them.
pub(super) fn holey_sphere(settings: &FrameSettings) -> PointCloud {
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let (mut points, mut colors) = (Vec::new(), Vec::new());
    for _ in 0..48_000 {
        let z: f64 = rng.random_range(-1.0..1.0);
        let phi: f64 = rng.random_range(0.0..std::f64::consts::TAU);
        let s = (1.0 - z * z).sqrt();
        let unit = DVec3::new(s * phi.cos(), s * phi.sin(), z);
        points.push(ORIGIN + unit * SPHERE_RADIUS);
        // Smooth bands with some noise, like a scanned surface's color.
        let mut band = |v: f64| (150.0 + 60.0 * v + rng.random_range(-12.0..12.0)) as u8;
        colors.push(pack_rgba8(band(unit.z), band(unit.x), band(-unit.z)));
    }
    let _ = settings;
    PointCloud::from_world_points(&points, colors)
}

fn with_fill(mut settings: FrameSettings, kernel: u32) -> FrameSettings {
    settings.fill = Some(FillSettings { kernel });
    settings
}

fn depth_of(frame: &Frame) -> &[f32] {
    frame.depth.as_deref().expect("depth was read back")
}

/// Pixels of the front rectangle, less a `margin` on each side, whose depth is the back
/// plane's.
fn back_showing_through(depth: &[f32], margin: u32) -> (usize, usize) {
    let mut through = 0;
    let mut total = 0;
    for y in FRONT.1.start + margin..FRONT.1.end - margin {
        for x in FRONT.0.start + margin..FRONT.0.end - margin {
            total += 1;
            if (depth[(y * WIDTH + x) as usize] - 40.0).abs() < 1.0 {
                through += 1;
            }
        }
    }
    (through, total)
}

#[test]
fn visibility_removes_back_points_seen_through_a_sparse_front_plane() {
    let plain = settings(Projection::Perspective { fov_y_deg: 50.0 });
    let cloud = two_planes(&plain);
    let without = render_gpu(&cloud, &plain);
    let filled = render_gpu(&cloud, &with_fill(plain, 7));
    let filled_9 = render_gpu(&cloud, &with_fill(plain, 9));
    let fraction = |frame: &Frame, margin| {
        let (through, total) = back_showing_through(depth_of(frame), margin);
        through as f64 / total as f64
    };
    // Within a kernel radius of the front plane's edge a back point has open sectors on the
    // outer side and is rightly kept; the interior is where the operator must work.
    let (before, after, after_9) = (
        fraction(&without, 3),
        fraction(&filled, 3),
        fraction(&filled_9, 4),
    );
    eprintln!(
        "back plane showing through the front plane's interior: {:.1}% without visibility, \
         {:.2}% with a 7x7 kernel, {:.2}% with 9x9 (whole rectangle, 7x7: {:.1}%)",
        before * 100.0,
        after * 100.0,
        after_9 * 100.0,
        fraction(&filled, 0) * 100.0
    );
    assert!(before > 0.6, "{before}");
    // 30% density leaves about one of the 8 sectors of a 7x7 kernel empty on average, so a few
    // back points see 4 open sectors (a half-space) and pass; a 9x9 kernel closes them all.
    assert!(after < 0.03, "{after}");
    assert!(after_9 < 0.005, "{after_9}");
    let total = (FRONT.0.len() * FRONT.1.len()) as f64;
    // The holes took the front plane's depth, and the back plane around it is untouched.
    let depth = depth_of(&filled);
    let front = FRONT
        .1
        .clone()
        .flat_map(|y| {
            FRONT
                .0
                .clone()
                .map(move |x| depth[(y * WIDTH + x) as usize])
        })
        .filter(|d| (d - 20.0).abs() < 0.2)
        .count();
    assert!(front as f64 > 0.9 * total, "{front} of {total}");
    assert_eq!(depth[5 * WIDTH as usize + 5], 40.0);
}

#[test]
fn filling_reconstructs_a_holey_sphere_without_growing_its_silhouette() {
    let mut results = Vec::new();
    for kernel in [5, 7] {
        let settings = with_fill(
            settings(Projection::Perspective { fov_y_deg: 50.0 }),
            kernel,
        );
        let cloud = holey_sphere(&settings);
        let rays = Rays::new(&settings);
        let truth: Vec<Option<f64>> = (0..HEIGHT)
            .flat_map(|y| (0..WIDTH).map(move |x| (x, y)))
            .map(|(x, y)| rays.sphere_depth(x, y, ORIGIN, SPHERE_RADIUS))
            .collect();
        let unfilled = render_gpu(
            &cloud,
            &FrameSettings {
                fill: None,
                ..settings
            },
        );
        let frame = render_gpu(&cloud, &settings);
        let within = |depth: &[f32], tolerance: f64| {
            let covered = truth.iter().filter(|t| t.is_some()).count();
            let good = truth
                .iter()
                .zip(depth)
                .filter(|(t, &d)| t.is_some_and(|t| (d as f64 - t).abs() <= tolerance * t))
                .count();
            good as f64 / covered as f64
        };
        // At the rim the depth changes by more than 2% across a pixel, and a point may lie
        // anywhere in its pixel while the truth is taken at the pixel's centre.
        let before = within(depth_of(&unfilled), 0.02);
        let after = within(depth_of(&frame), 0.02);
        // Silhouette growth: Chebyshev distance of each filled background pixel to the sphere.
        let mut growth = 0;
        for (pixel, &d) in depth_of(&frame).iter().enumerate() {
            if d.is_finite() && truth[pixel].is_none() {
                let (x, y) = ((pixel as u32 % WIDTH) as i64, (pixel as u32 / WIDTH) as i64);
                let nearest = truth
                    .iter()
                    .enumerate()
                    .filter(|(_, t)| t.is_some())
                    .map(|(p, _)| {
                        let (px, py) = ((p as u32 % WIDTH) as i64, (p as u32 / WIDTH) as i64);
                        (px - x).abs().max((py - y).abs())
                    })
                    .min()
                    .unwrap_or(i64::MAX);
                growth = growth.max(nearest);
            }
        }
        eprintln!(
            "kernel {kernel}: depth within 2% of the sphere on {:.1}% of its pixels before \
             filling, {:.1}% after; silhouette grew by at most {growth} pixels",
            before * 100.0,
            after * 100.0
        );
        results.push((kernel, before, after, growth));
    }
    for (kernel, before, after, growth) in results {
        assert!(before < 0.9, "kernel {kernel}: {before}");
        assert!(after >= 0.95, "kernel {kernel}: {after}");
        assert!(growth <= kernel as i64, "kernel {kernel}: {growth}");
    }
}

/// Pixels of `a` and `b` with a channel more than 2 levels apart.
fn colors_apart(a: &image::RgbaImage, b: &image::RgbaImage) -> usize {
    a.pixels()
        .zip(b.pixels())
        .filter(|(a, b)| (0..4).any(|c| a.0[c].abs_diff(b.0[c]) > 2))
        .count()
}

/// GPU and reference agree within `tolerance` levels per channel on all but `allowed` pixels,
/// and in depth within 1e-4 relative on all but `allowed` pixels.
fn assert_close_to_reference(name: &str, cloud: &PointCloud, settings: &FrameSettings) {
    let frame = render_gpu(cloud, settings);
    let expected = reference::render(cloud, settings);
    compare_images(name, &frame.image, &expected.image);
    let pixels = (settings.width * settings.height) as usize;
    let far_colors = colors_apart(&frame.image, &expected.image);
    let far_depths = depth_of(&frame)
        .iter()
        .zip(&expected.depth)
        .filter(|(&a, &b)| !(a == b || (a - b).abs() <= 1e-4 * b.abs()))
        .count();
    eprintln!(
        "{name}: {far_colors} pixels differ by more than 2 levels, {far_depths} in depth by \
         more than 1e-4, of {pixels}"
    );
    assert!(
        far_colors * 1000 <= pixels,
        "{name}: {far_colors} colors differ"
    );
    assert!(
        far_depths * 1000 <= pixels,
        "{name}: {far_depths} depths differ"
    );
}

#[test]
fn visibility_and_filling_match_the_reference() {
    let perspective = settings(Projection::Perspective { fov_y_deg: 50.0 });
    assert_close_to_reference(
        "fill-planes",
        &two_planes(&perspective),
        &with_fill(perspective, 7),
    );
    assert_close_to_reference(
        "fill-sphere",
        &holey_sphere(&perspective),
        &with_fill(perspective, 5),
    );
    let orthographic = settings(Projection::Orthographic { height: 8.0 });
    assert_close_to_reference(
        "fill-sphere-orthographic",
        &holey_sphere(&orthographic),
        &with_fill(orthographic, 9),
    );
}

#[test]
fn filling_a_small_cloud_after_one_that_filled_the_image_matches_the_reference() {
    // The visibility pass classifies only the frame's footprint grown by its kernel, and the
    // filling reads the fill buffers around the mutable pixels only: what an earlier frame
    // with a wider footprint left in those buffers must not show.
    let perspective = settings(Projection::Perspective { fov_y_deg: 50.0 });
    let wide = two_planes(&perspective);
    let mut small_settings = with_fill(perspective, 5);
    // The sphere seen from farther away covers the middle of the image only.
    small_settings.camera.position = ORIGIN + DVec3::new(0.0, -25.0, 0.0);
    let small = holey_sphere(&small_settings);
    let mut renderer = Renderer::new(crate::testing::gpu());
    let (wide_resident, small_resident) = (
        renderer.upload(&wide).expect("upload"),
        renderer.upload(&small).expect("upload"),
    );
    renderer
        .render(&wide_resident, &with_fill(perspective, 9))
        .expect("wide frame");
    let frame = renderer
        .render(&small_resident, &small_settings)
        .expect("small frame");
    let expected = reference::render(&small, &small_settings);
    let far_colors = colors_apart(&frame.image, &expected.image);
    compare_images("fill-after-wide", &frame.image, &expected.image);
    assert!(
        far_colors * 1000 <= (WIDTH * HEIGHT) as usize,
        "{far_colors} colors differ"
    );
}

#[test]
fn pintus_shading_matches_the_reference() {
    let mut settings = with_fill(settings(Projection::Perspective { fov_y_deg: 50.0 }), 5);
    settings.shading = Shading::PINTUS;
    assert_close_to_reference("pintus-sphere", &holey_sphere(&settings), &settings);
    settings.fill = None;
    settings.shading = Shading::Pintus {
        levels: 3,
        exponent: 0.0,
    };
    assert_close_to_reference("pintus-planes-unfilled", &two_planes(&settings), &settings);
}

#[test]
fn pintus_shading_darkens_slopes_and_keeps_flat_facing_surfaces() {
    let mut settings = with_fill(settings(Projection::Perspective { fov_y_deg: 50.0 }), 5);
    settings.shading = Shading::PINTUS;
    let frame = render_gpu(&holey_sphere(&settings), &settings);
    let unshaded = render_gpu(
        &holey_sphere(&settings),
        &FrameSettings {
            shading: Shading::None,
            ..settings
        },
    );
    let brightness = |image: &image::RgbaImage, x: u32, y: u32| {
        let mut sum = 0u32;
        for dy in 0..5 {
            for dx in 0..5 {
                let p = image.get_pixel(x + dx, y + dy).0;
                sum += p[0] as u32 + p[1] as u32 + p[2] as u32;
            }
        }
        sum
    };
    let ratio =
        |x, y| brightness(&frame.image, x, y) as f64 / brightness(&unshaded.image, x, y) as f64;
    // The centre of the sphere faces the camera; its rim is seen at a grazing angle.
    let (centre, rim) = (ratio(78, 58), ratio(78, 58 - 33));
    eprintln!("Pintus shading: centre keeps {centre:.2} of its color, the rim {rim:.2}");
    assert!(centre > 0.85, "{centre}");
    assert!(rim < centre - 0.1, "{rim} {centre}");
}

#[test]
fn fill_and_pintus_report_their_stages() {
    let mut settings = with_fill(settings(Projection::Perspective { fov_y_deg: 50.0 }), 3);
    settings.shading = Shading::PINTUS;
    let frame = render_gpu(&holey_sphere(&settings), &settings);
    let names: Vec<&str> = frame
        .timings
        .stages
        .iter()
        .map(|t| t.stage.name())
        .collect();
    assert_eq!(
        names,
        [
            "upload",
            "cull",
            "rasterize",
            "resolve",
            "visibility",
            "fill",
            "shade",
            "readback"
        ]
    );
}

#[test]
fn fill_settings_are_validated() {
    let mut renderer = Renderer::new(crate::testing::gpu());
    let base = settings(Projection::Perspective { fov_y_deg: 50.0 });
    for kernel in [0, 1, 2, 4, 8, 11] {
        let error = renderer
            .validate(&with_fill(base, kernel))
            .expect_err("bad kernel");
        assert!(matches!(error, RenderError::FillKernel(k) if k == kernel));
        assert!(error
            .to_string()
            .contains("odd number of pixels from 3 to 9"));
    }
    for kernel in [3, 5, 7, 9] {
        renderer
            .validate(&with_fill(base, kernel))
            .expect("good kernel");
    }
    for (levels, exponent) in [(0, 1.5), (33, 1.5), (8, -1.0), (8, f32::NAN)] {
        let settings = FrameSettings {
            shading: Shading::Pintus { levels, exponent },
            ..base
        };
        assert!(matches!(
            renderer.validate(&settings),
            Err(RenderError::Pintus { .. })
        ));
    }
    // Supersampling widens the kernel with the image.
    let mut big = with_fill(base, 7);
    big.supersample = 3;
    assert_eq!(
        big.scaled_for_supersampling().fill,
        Some(FillSettings { kernel: 19 })
    );
    renderer.validate(&big).expect("supersampled fill");
    let _ = &mut renderer;
}

#[test]
fn supersampled_filling_closes_the_same_holes() {
    let mut settings = with_fill(settings(Projection::Perspective { fov_y_deg: 50.0 }), 5);
    let cloud = holey_sphere(&settings);
    let single = render_gpu(&cloud, &settings);
    settings.supersample = 2;
    let double = render_gpu(&cloud, &settings);
    assert!(double.timings.get(Stage::Fill).is_some());
    assert!(double.timings.get(Stage::Downsample).is_some());
    let covered = |frame: &Frame| depth_of(frame).iter().filter(|d| d.is_finite()).count();
    let (a, b) = (covered(&single), covered(&double));
    // Points are twice as large at twice the size, so coverage is the same within the rim.
    assert!(a.abs_diff(b) * 50 < a, "{a} vs {b} covered pixels");
}

#[test]
fn eye_dome_lighting_matches_the_reference_and_outlines_silhouettes() {
    let mut settings = perspective_settings(160, 120);
    let cloud = pixel_centre_scene(&settings, 2, 12);
    let (mut renderer, resident) = uploaded(&cloud);
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

//! The rasterizer on the real scans in `../shared/data/` (skipped with a message when absent):
//! agreement with the CPU reference, and sub-pixel accuracy at survey coordinates.

use glam::DVec3;

use super::render_gpu;
use super::*;
use crate::camera::Camera;
use crate::cloud::pack_rgba8;
use crate::ingest::load_point_cloud;
use crate::reference;
use crate::testing::{compare_images, gpu, perspective_camera, shared_data};

fn load(file: &str) -> Option<PointCloud> {
    let path = shared_data(file)?;
    Some(load_point_cloud(&path).unwrap_or_else(|e| panic!("{e}")))
}

/// Runs `check` on each of `files` found in `../shared/data/`, loaded and uploaded by one
/// renderer.
/// One file of each real scan (the LAS and LAZ of Autzen hold the same points).
const DISTINCT_SCANS: &[&str] = &["autzen_trim.laz", "lone-star.laz"];

fn each_real_scan(
    files: &[&str],
    mut check: impl FnMut(&str, &PointCloud, &mut Renderer, &GpuPointCloud),
) {
    let mut renderer = Renderer::new(gpu());
    for file in files {
        let Some(cloud) = load(file) else { continue };
        let resident = renderer.upload(&cloud).expect("upload");
        check(file, &cloud, &mut renderer, &resident);
    }
}

/// The automatic camera turned 100° about its target and moved to `closeness` of its
/// distance, the near plane brought in tenfold: a close oblique view with many points per pixel.
fn close_oblique_camera(cloud: &PointCloud, aspect: f64, closeness: f64) -> Camera {
    let mut camera = Camera::auto(&cloud.bounds, aspect).orbit(100.0);
    camera.position = camera.target + (camera.position - camera.target) * closeness;
    camera.near *= 0.1;
    camera
}

/// Share of equal pixels overall and among pixels that the reference covers.
fn agreement(
    name: &str,
    cloud: &PointCloud,
    settings: &FrameSettings,
    frame: &Frame,
) -> (f64, f64) {
    let expected = reference::render_basic(cloud, settings);
    let diff = compare_images(name, &frame.image, &expected.image);
    let covered = expected.depth.iter().filter(|d| d.is_finite()).count();
    let covered_equal = covered - diff.differing.min(covered);
    let covered_fraction = covered_equal as f64 / covered.max(1) as f64;
    eprintln!(
        "{name}: {} of {} pixels differ ({:.4}% equal; {:.4}% of the {covered} covered pixels)",
        diff.differing,
        diff.pixels,
        diff.equal_fraction() * 100.0,
        covered_fraction * 100.0
    );
    (diff.equal_fraction(), covered_fraction)
}

#[test]
fn real_scans_agree_with_the_reference() {
    each_real_scan(
        &["autzen_trim.las", "autzen_trim.laz", "lone-star.laz"],
        |file, cloud, renderer, resident| {
            let (w, h) = (800, 600);
            let overview =
                FrameSettings::new(w, h, Camera::auto(&cloud.bounds, w as f64 / h as f64));
            // A closer oblique view with larger points, where many points compete per pixel.
            let near_view = FrameSettings {
                camera: close_oblique_camera(cloud, w as f64 / h as f64, 0.35),
                point_size: 3,
                ..overview
            };
            for (view, settings) in [("overview", overview), ("close", near_view)] {
                for atomics in [AtomicsMode::Auto, AtomicsMode::Force32] {
                    let settings = FrameSettings {
                        atomics,
                        ..settings
                    };
                    let frame = renderer.render(resident, &settings).expect("render");
                    let name = format!("{file}-{view}-{atomics:?}");
                    let (all, covered) = agreement(&name, cloud, &settings, &frame);
                    assert!(
                        all >= 0.995,
                        "{name}: only {:.3}% of pixels equal",
                        all * 100.0
                    );
                    assert!(
                        covered >= 0.99,
                        "{name}: only {:.3}% of covered pixels equal",
                        covered * 100.0
                    );
                }
            }
        },
    );
}

/// lone-star is in UTM at 0.25 mm resolution: in f32 world coordinates a position would be
/// off by up to 3 cm, several pixels in a close-up. Points are rendered one per 8x8-pixel
/// cell with unique colors; each one's pixel must contain its f64 projection computed from the
/// file's own coordinates (the las crate, not our ingest), i.e. an error of at most 0.5 px.
#[test]
fn survey_coordinates_render_with_sub_pixel_accuracy_in_a_close_up() {
    let Some(path) = shared_data("lone-star.laz") else {
        return;
    };
    let cloud = load_point_cloud(&path).expect("load");
    let mut reader = las::Reader::from_path(&path).expect("las reader");
    let file_points = reader.read_all().expect("read");
    let world = crate::testing::las_world_positions(&file_points);
    assert_eq!(world.len(), cloud.len());

    // A close-up: 3 m from a point in the middle of the scan.
    let focus = world[world.len() / 2];
    let (w, h) = (1024u32, 768u32);
    let camera = perspective_camera(
        focus + DVec3::new(1.8, -2.0, 1.2),
        focus,
        45.0,
        (0.05, 50.0),
    );
    // The independent projection: f64 throughout, from absolute file coordinates.
    let absolute = camera.transform(DVec3::ZERO, w, h);
    let mut cell_taken = vec![false; (w as usize / 8 + 1) * (h as usize / 8 + 1)];
    let mut chosen = Vec::new();
    let mut projected = Vec::new();
    for (i, p) in world.iter().enumerate() {
        let Some((px, py, _)) = absolute.project(*p) else {
            continue;
        };
        if !(0.0..w as f64).contains(&px) || !(0.0..h as f64).contains(&py) {
            continue;
        }
        let cell = (py as usize / 8) * (w as usize / 8 + 1) + px as usize / 8;
        if !std::mem::replace(&mut cell_taken[cell], true) {
            chosen.push(i);
            projected.push((px, py));
        }
    }
    assert!(chosen.len() > 2000, "only {} points in view", chosen.len());

    let mut subset = cloud.select(&chosen);
    for (k, c) in subset.colors.iter_mut().enumerate() {
        let id = k as u32 + 1;
        *c = pack_rgba8(id as u8, (id >> 8) as u8, (id >> 16) as u8);
    }
    let mut settings = FrameSettings::new(w, h, camera);
    settings.background = [0, 0, 0, 0];
    let frame = render_gpu(&subset, &settings);

    let mut found = 0;
    let mut max_error: f64 = 0.0;
    for (x, y, pixel) in frame.image.enumerate_pixels() {
        let [r, g, b, a] = pixel.0;
        if a == 0 {
            continue;
        }
        let id = r as usize | (g as usize) << 8 | (b as usize) << 16;
        let (px, py) = projected[id - 1];
        let error = (x as f64 + 0.5 - px).abs().max((y as f64 + 0.5 - py).abs());
        max_error = max_error.max(error);
        found += 1;
    }
    // Naive f32 world coordinates, for scale: how far the same points would land.
    let naive_max_error = chosen
        .iter()
        .zip(&projected)
        .map(|(&i, &(px, py))| {
            let rounded = world[i].as_vec3().as_dvec3();
            let (qx, qy, _) =
                absolute
                    .project(rounded)
                    .unwrap_or((f64::INFINITY, f64::INFINITY, 0.0));
            (qx - px).abs().max((qy - py).abs())
        })
        .fold(0.0, f64::max);
    eprintln!(
        "lone-star close-up: {found} of {} points found, max error {max_error:.4} px \
         (f32 world coordinates would be off by up to {naive_max_error:.1} px)",
        chosen.len()
    );
    assert!(
        found as f64 >= chosen.len() as f64 * 0.99,
        "points lost: {found} of {}",
        chosen.len()
    );
    assert!(max_error <= 0.5 + 1e-3, "max error {max_error} px");
    assert!(
        naive_max_error > 2.0,
        "the close-up must be sensitive to f32 rounding"
    );
}

/// High-quality mode on the real scans: each pixel's average within 1/255 per channel of the
/// reference's, on at least 99.5% of pixels (a point right at the band's edge may fall on
/// either side of it in f32).
#[test]
fn real_scans_high_quality_agrees_with_the_reference() {
    each_real_scan(DISTINCT_SCANS, |file, cloud, renderer, resident| {
        let (w, h) = (800, 600);
        let mut settings =
            FrameSettings::new(w, h, Camera::auto(&cloud.bounds, w as f64 / h as f64));
        settings.quality = Quality::HIGH;
        settings.point_size = 2;
        let frame = renderer.render(resident, &settings).expect("render");
        let expected = reference::render(cloud, &settings);
        let within = frame
            .image
            .pixels()
            .zip(expected.image.pixels())
            .filter(|(a, e)| a.0.iter().zip(e.0).all(|(x, y)| x.abs_diff(y) <= 1))
            .count();
        let fraction = within as f64 / (w * h) as f64;
        eprintln!(
            "{file} high quality: {:.4}% of pixels within 1/255",
            fraction * 100.0
        );
        assert!(fraction >= 0.995, "{file}: {:.3}%", fraction * 100.0);
    });
}

#[test]
fn filling_and_pintus_shading_of_real_scans_agree_with_the_reference() {
    each_real_scan(DISTINCT_SCANS, |file, cloud, renderer, resident| {
        let (w, h) = (320, 240);
        let camera = close_oblique_camera(cloud, w as f64 / h as f64, 0.5);
        let settings = FrameSettings {
            fill: Some(FillSettings::default()),
            shading: Shading::PINTUS,
            ..FrameSettings::new(w, h, camera)
        };
        let frame = renderer.render(resident, &settings).expect("render");
        let expected = reference::render(cloud, &settings);
        let name = format!("{file}-fill-pintus");
        let diff = crate::testing::compare_images_within(&name, &frame.image, &expected.image, 2);
        eprintln!(
            "{name}: {:.3}% of pixels within 2 levels of the reference",
            diff.equal_fraction() * 100.0
        );
        // The point pass itself agrees on at least 99.5% of pixels (f32 vs f64 projection
        // at pixel edges); the 3x3 filling spreads each difference to a few neighbours.
        assert!(diff.equal_fraction() >= 0.995, "{name}");
    });
}

/// The median luma of the surface (pixels with a depth) of a frame rendered with its depth.
fn surface_median_luma(frame: &Frame) -> usize {
    let depth = frame.depth.as_ref().expect("rendered with its depth");
    let mut lumas: Vec<usize> = frame
        .image
        .pixels()
        .zip(depth)
        .filter(|(_, depth)| depth.is_finite())
        .map(|(pixel, _)| crate::raster::exposure::luma_bin(pixel[0], pixel[1], pixel[2]))
        .collect();
    assert!(!lumas.is_empty(), "the scan is in view");
    let middle = lumas.len() / 2;
    *lumas.select_nth_unstable(middle).1
}

/// Eye-Dome Lighting darkens edges, not the picture: after the exposure the surface's median
/// luma stays within 15% of the unshaded render's, the colorless terrestrial scan included;
/// and the GPU's shaded frame is the reference's.
#[test]
fn eye_dome_lighting_keeps_the_median_brightness_of_real_scans() {
    each_real_scan(DISTINCT_SCANS, |file, cloud, renderer, resident| {
        let (w, h) = (640, 360);
        let unshaded = FrameSettings {
            read_depth: true,
            ..FrameSettings::new(w, h, Camera::auto(&cloud.bounds, w as f64 / h as f64))
        };
        let shaded = FrameSettings {
            shading: Shading::EDL,
            ..unshaded
        };
        let plain = renderer.render(resident, &unshaded).expect("render");
        let lit = renderer.render(resident, &shaded).expect("render");
        let (before, after) = (surface_median_luma(&plain), surface_median_luma(&lit));
        let ratio = (after as f64 + 0.5) / (before as f64 + 0.5);
        eprintln!("{file}: surface median luma {before} unshaded, {after} with EDL ({ratio:.2})");
        assert!((0.85..=1.15).contains(&ratio), "{file}: {ratio:.2}");

        let expected = reference::render(cloud, &shaded);
        let name = format!("{file}-edl");
        let diff = crate::testing::compare_images_within(&name, &lit.image, &expected.image, 2);
        assert!(diff.equal_fraction() >= 0.995, "{name}: {diff:?}");
    });
}

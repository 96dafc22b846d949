//! Culling on whole frames: batch frustum culling keeps every point in view, and occlusion
//! culling skips batches hidden behind a wall without changing the image.

use super::*;
use crate::testing::{perspective_camera, top_down_camera};

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
    let cam = perspective_camera(
        SURVEY_ORIGIN + DVec3::new(0.0, -120.0, 60.0),
        SURVEY_ORIGIN,
        30.0,
        (1.0, 400.0),
    );
    let mut settings = FrameSettings::new(200, 150, cam);
    settings.point_size = 2;
    let frame = assert_matches_reference("culling", &cloud, &settings);
    assert!(
        frame.image.pixels().any(|p| p.0 != settings.background),
        "something is in view"
    );
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
        top_down_camera(SURVEY_ORIGIN, 200.0, 15.0, (5.0, 300.0)),
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

    let (mut renderer, resident) = uploaded(&cloud);
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

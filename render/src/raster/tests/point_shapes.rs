//! Adaptive point sizes and round points against the CPU reference: each point's side from
//! its depth, and the disc inside its square, in the basic and high-quality modes.

use super::*;

/// The tests' sparse scene: pixel-centre points in two layers over the whole depth range,
/// thinned so that squares overlap partly and leave gaps.
fn sparse_scene(settings: &FrameSettings, seed: u64) -> PointCloud {
    let cloud = pixel_centre_scene(settings, 2, seed);
    let sparse: Vec<usize> = (0..cloud.len()).step_by(18).collect();
    cloud.select(&sparse)
}

/// Pixels that are not the background.
fn covered(frame: &Frame, settings: &FrameSettings) -> usize {
    let background = settings.background;
    frame.image.pixels().filter(|p| p.0 != background).count()
}

fn adaptive_settings() -> FrameSettings {
    let mut settings = perspective_settings(120, 90);
    settings.background = [0, 0, 0, 0];
    // The scene's depths run from about 22 to 133: sides from 6 (capped) down to 1.
    settings.point_size = 6;
    settings.adaptive_size = Some(150.0);
    settings
}

#[test]
fn adaptive_points_shrink_with_depth_like_the_reference() {
    let settings = adaptive_settings();
    let cloud = sparse_scene(&settings, 21);
    let sides: std::collections::BTreeSet<u32> = {
        let t = settings
            .camera
            .transform(cloud.origin, settings.width, settings.height);
        cloud
            .positions
            .iter()
            .filter_map(|p| t.project(p.as_dvec3()))
            .map(|(_, _, depth)| settings.point_side_at(depth as f32))
            .collect()
    };
    assert_eq!(sides, (1..=6).collect(), "the scene spans every side");
    let adaptive = assert_matches_reference("adaptive", &cloud, &settings);

    // Between one-pixel points and the largest side everywhere.
    let fixed = |point_size| FrameSettings {
        point_size,
        adaptive_size: None,
        ..settings
    };
    let small = render_gpu(&cloud, &fixed(1));
    let large = render_gpu(&cloud, &fixed(6));
    let (small, adaptive, large) = (
        covered(&small, &settings),
        covered(&adaptive, &settings),
        covered(&large, &settings),
    );
    assert!(
        small + 500 < adaptive && adaptive + 500 < large,
        "covered pixels: 1 px {small}, adaptive {adaptive}, 6 px {large}"
    );
}

#[test]
fn round_points_cover_discs_like_the_reference() {
    for point_size in [3, 4, 5, 8] {
        let mut settings = perspective_settings(96, 64);
        settings.background = [0, 0, 0, 0];
        settings.point_size = point_size;
        settings.round_points = true;
        let cloud = sparse_scene(&settings, 22);
        let round = assert_matches_reference(&format!("round-{point_size}"), &cloud, &settings);
        let square = render_gpu(
            &cloud,
            &FrameSettings {
                round_points: false,
                ..settings
            },
        );
        let (round, square) = (covered(&round, &settings), covered(&square, &settings));
        // A 3-pixel disc covers its whole square; from 4 pixels the corners are cut.
        if point_size == 3 {
            assert_eq!(round, square);
        } else {
            assert!(round < square, "{point_size} px: {round} vs {square}");
        }
    }
}

#[test]
fn one_round_point_is_a_disc() {
    let mut settings = perspective_settings(32, 32);
    settings.background = [0, 0, 0, 0];
    settings.point_size = 8;
    settings.round_points = true;
    let target = settings.camera.target;
    let cloud = PointCloud::from_world_points(&[target], vec![pack_rgba8(255, 255, 255)]);
    let frame = assert_matches_reference("round-one", &cloud, &settings);
    // An 8-pixel disc: rows of 4, 6, 8, 8, 8, 8, 6 and 4 pixels (pixel centres within 4 of
    // the centre), 52 in all.
    assert_eq!(covered(&frame, &settings), 52);
}

#[test]
fn adaptive_round_points_average_like_the_reference_in_high_quality() {
    let mut settings = adaptive_settings();
    settings.quality = Quality::HIGH;
    settings.round_points = true;
    let cloud = surface_with_depth_noise(&settings, 23);
    let sparse: Vec<usize> = (0..cloud.len()).step_by(5).collect();
    let cloud = cloud.select(&sparse);
    let frame = render_gpu(&cloud, &settings);
    let expected = reference::render(&cloud, &settings);
    let difference = max_channel_difference(&frame.image, &expected.image);
    let diff = compare_images("hq-adaptive-round", &frame.image, &expected.image);
    assert!(
        difference <= 1,
        "{} pixels differ, by at most {difference}/255",
        diff.differing
    );
}

#[test]
fn adaptive_sizes_scale_with_supersampling() {
    let settings = FrameSettings {
        supersample: 2,
        ..adaptive_settings()
    };
    let scaled = settings.scaled_for_supersampling();
    assert_eq!(scaled.point_size, 12);
    assert_eq!(scaled.adaptive_size, Some(300.0));
    assert_eq!(scaled.point_side_at(50.0), 2 * settings.point_side_at(50.0));
}

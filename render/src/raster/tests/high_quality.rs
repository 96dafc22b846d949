//! The high-quality mode: the average of the front surface's points within the depth band,
//! like the reference, with pixels deeper than the packed sums and a configurable band.

use super::*;

/// Pixels with more points in the depth band than the packed sums hold (256) spill into the
/// wide sums (`shaders/hq_sums_atomic64.wgsl`): their averages stay exact, the same as the
/// 32-bit path's to the bit and the reference's, frame after frame.
#[test]
fn high_quality_averages_pixels_deeper_than_the_packed_sums() {
    let mut renderer = Renderer::new(gpu());
    let mut settings = perspective_settings(24, 16);
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
    // Bright colors, so that a channel's sum over more than 257 points overflows 16 bits.
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
    let mut settings = perspective_settings(160, 120);
    settings.quality = Quality::HIGH;
    settings.read_depth = true;
    let cloud = surface_with_depth_noise(&settings, 10);
    let (mut renderer, resident) = uploaded(&cloud);
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

    // The average really is not the nearest point's color.
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
    let mut settings = perspective_settings(96, 64);
    let cloud = surface_with_depth_noise(&settings, 11);
    let (mut renderer, resident) = uploaded(&cloud);
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

/// Many thousands of points in one pixel's band, with the colors of vegetation, drawn from
/// many segments: the packed sums hold the first 256, the wide sums the rest, and the average is
/// the reference's whichever path adds them, frame after frame.
#[test]
fn high_quality_averages_thousands_of_points_a_pixel_over_many_segments() {
    let base = perspective_settings(8, 6);
    let (near, far) = (base.camera.near, base.camera.far);
    for (points, segment_points) in [(5_000, None), (20_000, Some(4 * BATCH_POINTS))] {
        let mut cloud = pixel_centre_scene_by_pixel(&base, 7, |rng, x, y| {
            if (x + y) % 3 != 0 {
                return Vec::new();
            }
            let front = near + (far - near) * rng.random_range(0.1..0.6);
            (0..points)
                .map(|_| front * rng.random_range(1.0..1.005))
                .collect()
        });
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        for color in &mut cloud.colors {
            *color = pack_rgba8(
                rng.random_range(45..=60),
                rng.random_range(190..=230),
                rng.random_range(60..=80),
            );
        }
        let mut renderer = Renderer::new(gpu());
        if let Some(segment_points) = segment_points {
            renderer.set_max_segment_points(segment_points);
        }
        let resident = renderer.upload(&cloud).expect("upload");
        let settings = FrameSettings {
            quality: Quality::HIGH,
            ..base
        };
        let expected = reference::render(&cloud, &settings);
        for atomics in [AtomicsMode::Auto, AtomicsMode::Force32, AtomicsMode::Auto] {
            let frame = render_with_atomics(&mut renderer, &resident, &settings, atomics);
            let name = format!("hq-thousands-{points}-{atomics:?}");
            let difference = max_channel_difference(&frame.image, &expected.image);
            assert!(difference <= 1, "{name}: differs by {difference}/255");
        }
    }
}

/// A generated terrain (`GeneratedSource::terrain`: brown ground, vegetation up to 20 m above
/// it in green, both shaded by height) seen obliquely, many points a pixel towards the
/// horizon. Where the depth band reaches from the canopy down to the ground, the average
/// mixes the two: brownish and darker than the basic mode's canopy, on the GPU as in the
/// reference. A band of 10% here spans what 1% does from 10 times as far, as in the full
/// view of the 100M-point terrain, 3.2 km across. Frames in different modes and views follow
/// one another on one renderer.
#[test]
fn high_quality_matches_the_reference_on_a_terrain_where_the_band_reaches_the_ground() {
    use crate::lod::{GeneratedSource, PointSource};
    let source = GeneratedSource::terrain(400_000, 5);
    let (mut points, mut colors) = (Vec::new(), Vec::new());
    source
        .for_each_batch(&mut |batch| {
            let rgb = batch.rgb.expect("the terrain has RGB");
            points.extend_from_slice(batch.positions);
            colors.extend(rgb.iter().map(|c| {
                let [r, g, b] = c.map(|channel| (channel >> 8) as u8);
                pack_rgba8(r, g, b)
            }));
            Ok(())
        })
        .expect("generate");
    let cloud = PointCloud::from_world_points(&points, colors);
    let bounds = source.bounds();
    let mut renderer = Renderer::new(gpu());
    renderer.set_max_segment_points(64 * BATCH_POINTS);
    let resident = renderer.upload(&cloud).expect("upload");
    // From above one corner, 40 m up, towards the far one: the far half at a grazing angle.
    let oblique = Camera {
        position: bounds.min + DVec3::new(-10.0, -10.0, 40.0),
        target: bounds.max - DVec3::new(0.0, 0.0, 40.0),
        up: DVec3::Z,
        projection: Projection::Perspective { fov_y_deg: 40.0 },
        near: 1.0,
        far: 1000.0,
    };
    let turned = oblique.orbit(40.0);
    let frames = [
        (oblique, Quality::Basic, AtomicsMode::Auto),
        (
            oblique,
            Quality::High { depth_band: 0.1 },
            AtomicsMode::Auto,
        ),
        (turned, Quality::HIGH, AtomicsMode::Auto),
        (
            oblique,
            Quality::High { depth_band: 0.1 },
            AtomicsMode::Force32,
        ),
        (turned, Quality::High { depth_band: 0.1 }, AtomicsMode::Auto),
    ];
    let mut images = Vec::new();
    for (index, (camera, quality, atomics)) in frames.into_iter().enumerate() {
        let settings = FrameSettings {
            quality,
            atomics,
            ..FrameSettings::new(96, 54, camera)
        };
        let frame = renderer.render(&resident, &settings).expect("render");
        let expected = reference::render(&cloud, &settings);
        // As on the real scans, a point right at a pixel's or the band's edge may fall on
        // either side of it in f32.
        let name = format!("hq-terrain-{index}");
        let diff = crate::testing::compare_images_within(&name, &frame.image, &expected.image, 1);
        assert!(
            diff.equal_fraction() >= 0.995,
            "{name}: {} pixels differ",
            diff.differing
        );
        images.push(frame.image);
    }
    // Integer sums: the 64-bit and the 32-bit accumulation give the same image.
    let diff = compare_images("hq-terrain-atomics", &images[1], &images[3]);
    assert_eq!(diff.differing, 0, "the atomics paths differ");
    // Where the basic mode shows the green canopy, the wide band's average takes in the
    // ground beneath it and turns brown.
    let browned = images[0]
        .pixels()
        .zip(images[1].pixels())
        .filter(|(basic, high)| basic.0[1] > basic.0[0] && high.0[0] > high.0[1])
        .count();
    assert!(browned > 96 * 54 / 50, "{browned} pixels turned brown");
}

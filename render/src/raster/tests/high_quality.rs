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

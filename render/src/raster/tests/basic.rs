//! The basic mode against the CPU reference, pixel for pixel: perspective and orthographic
//! views, large points, odd image sizes, consecutive frames, and settings refused before any
//! GPU work.

use super::*;

#[test]
fn basic_mode_equals_the_reference_pixel_for_pixel() {
    let settings = perspective_settings(160, 120);
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

/// The resolves take runs of consecutive pixels per invocation (`resolve_pass.rs`): at image
/// sizes whose pixel runs end in a partial one, both modes still equal the reference, and
/// the framebuffer is emptied for the next frame (a frame after a different view equals the
/// first).
#[test]
fn odd_image_sizes_resolve_their_last_pixels_and_empty_the_framebuffer() {
    let mut renderer = Renderer::new(gpu());
    for (width, height) in [(101, 77), (37, 29)] {
        let basic = perspective_settings(width, height);
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
    let centre = perspective_settings(160, 120);
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
fn invalid_settings_are_refused_before_any_gpu_work() {
    let renderer = Renderer::new(gpu());
    let good = perspective_settings(64, 48);
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
    // 2 GB of framebuffer: over most adapters' binding limit (lavapipe's is 128 MiB), drawn
    // in tiles (`tests/tiles.rs` has what cannot be).
    renderer
        .validate(&too_many_pixels)
        .expect("drawn in tiles where one pass does not fit");
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

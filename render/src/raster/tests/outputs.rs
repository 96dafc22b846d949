//! What a frame returns besides its color image: the depth image (and its 16-bit PNG),
//! supersampled images, and the stage timings on both clocks.

use super::*;

/// A 64x48 frame with its depth image, of `layers` points per pixel centre.
fn frame_with_depth(layers: usize, seed: u64) -> (FrameSettings, PointCloud, Frame) {
    let settings = FrameSettings {
        read_depth: true,
        ..perspective_settings(64, 48)
    };
    let cloud = pixel_centre_scene(&settings, layers, seed);
    let frame = render_gpu(&cloud, &settings);
    (settings, cloud, frame)
}

#[test]
fn depth_image_holds_linear_depth() {
    let (settings, cloud, frame) = frame_with_depth(2, 7);
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
fn depth_image_is_written_as_16_bit_png() {
    let (settings, _, frame) = frame_with_depth(1, 14);
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
fn supersampling_renders_larger_and_averages_blocks() {
    let mut settings = perspective_settings(80, 60);
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
            gain: None,
        },
        2,
    );
    assert_eq!(
        compare_images("ssaa", &frame.image, &expected.image).differing,
        0
    );
    // Edges are blended: some pixels hold colors no single point has.
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
fn every_frame_reports_its_stage_timings() {
    let settings = perspective_settings(64, 48);
    let (mut renderer, resident) = uploaded(&pixel_centre_scene(&settings, 1, 8));
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
    crate::encode::save_frame(
        &mut first,
        &dir.path().join("frame.png"),
        crate::encode::FrameFormat::Png,
    )
    .expect("png");
    assert!(first.timings.get(Stage::Encode).is_some());
    let line = first.timings.to_string();
    assert!(
        line.contains("rasterize") && line.contains("encode"),
        "{line}"
    );
}

#[test]
fn host_clocks_time_the_passes_without_timestamp_queries() {
    let settings = perspective_settings(64, 48);
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

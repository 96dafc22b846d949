//! Cuts at pixel error 0 draw what the resident cloud of the same file draws, in every mode and
//! filter, from cold and warm caches and in tiles.

use super::*;

#[test]
fn every_mode_at_lod_error_zero_renders_as_the_resident_cloud() {
    let fixture = fixture(60_000);
    let mut renderer = Renderer::new(gpu());
    let mut cut = cut_renderer(&renderer, &fixture, 0.0);
    let default = basic;
    let filled = |shading| RenderOptions {
        fill: Some(FillSettings::default()),
        shading,
        ..default()
    };
    let high_quality = RenderOptions {
        quality: Quality::HIGH,
        point_size: PointSize::Fixed(2),
        ..default()
    };
    let options_in_rgb = [
        ("basic", default()),
        ("high-quality", high_quality),
        ("fill-edl", filled(Shading::EDL)),
        ("pintus", filled(Shading::PINTUS)),
        (
            "supersampled",
            RenderOptions {
                supersample: 2,
                ..default()
            },
        ),
    ];
    let colors_by_default = [
        ("intensity", ColorMode::Intensity),
        ("classes", ColorMode::Classification),
        ("returns", ColorMode::ReturnNumber),
        ("fixed", ColorMode::Fixed([255, 128, 0])),
        ("elevation", ColorMode::Elevation),
    ];
    let modes = (options_in_rgb.map(|(name, options)| (name, options, ColorMode::Rgb)))
        .into_iter()
        .chain(colors_by_default.map(|(name, mode)| (name, default(), mode)));
    for (name, options, color_mode) in modes {
        let settings = settings(&fixture, &options);
        let (frame, report) = cut
            .render(
                &mut renderer,
                &fixture.dataset,
                &settings,
                color_mode,
                &PointFilter::default(),
            )
            .expect("cut");
        assert_eq!(
            report.counts.points_rendered, report.counts.points_total,
            "{name}: lod 0 draws all"
        );
        let expected = resident_image(&fixture, &settings, color_mode);
        let share = close_share(&format!("cut-{name}"), &frame.image, &expected);
        // Elevation takes its range from a sample of the store, the resident cloud from every
        // point: a few colors shift by a level or two.
        assert!(
            share >= 0.99,
            "{name}: only {share:.4} of pixels within 8/255"
        );
    }
}

#[test]
fn filtered_cuts_at_lod_error_zero_draw_the_filtered_resident_cloud() {
    use crate::filter::{ClipBox, CodeSet, IntensityRange};
    let fixture = fixture(60_000);
    let mut renderer = Renderer::new(gpu());
    let mut cut = cut_renderer(&renderer, &fixture, 0.0);
    let bounds = fixture.cloud.bounds;
    // The half of the scene with the lower x.
    let half = ClipBox {
        min: bounds.min.to_array(),
        max: [bounds.center().x, bounds.max.y, bounds.max.z],
    };
    let classes = fixture.cloud.classification.iter().copied();
    let common_class = classes.max_by_key(|&c| {
        fixture
            .cloud
            .classification
            .iter()
            .filter(|&&d| d == c)
            .count()
    });
    let mut intensities = fixture.cloud.intensity.clone();
    intensities.sort_unstable();
    let median_intensity = intensities[intensities.len() / 2];
    let filters = [
        (
            "classes",
            PointFilter {
                classes: Some(CodeSet::of(common_class)),
                ..Default::default()
            },
        ),
        (
            "intensity",
            PointFilter {
                intensity: Some(IntensityRange {
                    min: 0,
                    max: median_intensity - 1,
                }),
                ..Default::default()
            },
        ),
        (
            "clip",
            PointFilter {
                clip: Some(half),
                ..Default::default()
            },
        ),
    ];
    let (_, everything) = cut
        .render(
            &mut renderer,
            &fixture.dataset,
            &settings(&fixture, &basic()),
            ColorMode::Rgb,
            &PointFilter::default(),
        )
        .expect("unfiltered");
    for (name, filter) in filters {
        let mut kept = fixture.cloud.clone();
        let count = filter.apply(&mut kept).expect("inside");
        assert!(
            count > 0 && count < fixture.cloud.len(),
            "{name}: {count} kept"
        );
        // Both paths frame the same bounds: the clip box's part of the dataset.
        let framing = filter
            .framing_bounds(&fixture.dataset.bounds())
            .expect("inside");
        let camera = Camera::auto(&framing, 4.0 / 3.0);
        let settings = FrameSettings::new(200, 150, camera);
        let (frame, report) = cut
            .render(
                &mut renderer,
                &fixture.dataset,
                &settings,
                ColorMode::Rgb,
                &filter,
            )
            .expect("filtered cut");
        assert_eq!(
            report.counts.points_rendered, count as u64,
            "{name}: what the filter kept"
        );
        let mut resident = Renderer::new(gpu());
        let uploaded = resident.upload(&kept).expect("upload");
        let expected = resident.render(&uploaded, &settings).expect("render").image;
        let share = close_share(&format!("cut-filter-{name}"), &frame.image, &expected);
        assert!(
            share >= 0.99,
            "{name}: only {share:.4} of pixels within 8/255"
        );
        if name == "clip" {
            assert!(
                report.counts.nodes < everything.counts.nodes,
                "the box leaves nodes outside it uncut: {} of {}",
                report.counts.nodes,
                everything.counts.nodes
            );
        }
    }
}

#[test]
fn a_frame_is_the_same_from_a_cold_and_a_warm_cache() {
    let (fixture, mut renderer, first) = basic_frame(40_000);
    let mut other = first;
    other.camera = Camera::framing(
        &fixture.cloud.bounds,
        4.0 / 3.0,
        40.0,
        50.0,
        Projection::Perspective { fov_y_deg: 40.0 },
    );
    let mut cut = cut_renderer(&renderer, &fixture, DEFAULT_LOD_ERROR_PX);
    let (cold, cold_report) = cut
        .render_rgb(&mut renderer, &fixture.dataset, &first)
        .expect("cold");
    assert_eq!(cold_report.counts.gpu_hits, 0);
    assert!(cold_report.counts.nodes_read > 0 && cold_report.counts.bytes_read > 0);
    cut.render_rgb(&mut renderer, &fixture.dataset, &other)
        .expect("other");
    let (warm, warm_report) = cut
        .render_rgb(&mut renderer, &fixture.dataset, &first)
        .expect("warm");
    assert_eq!(warm_report.counts.nodes_read, 0, "{warm_report:?}");
    assert_eq!(warm_report.counts.gpu_hits, warm_report.counts.nodes);
    assert!(
        cold.image == warm.image,
        "the warm frame differs from the cold one"
    );
}

#[test]
fn a_cut_too_large_for_one_pass_is_drawn_in_tiles_as_in_one() {
    let (fixture, mut renderer, first) = basic_frame(40_000);
    let settings = FrameSettings {
        shading: Shading::EDL,
        ..first
    };
    let (whole, whole_report) = fresh_cut(&mut renderer, &fixture, DEFAULT_LOD_ERROR_PX, &settings);
    let mut tiled = Renderer::new(gpu());
    tiled.set_tile_limit_bytes(200 * 150 * 8 / 4);
    assert!(tiled.tile_grid(&settings).is_some(), "drawn in tiles");
    let (frame, report) = fresh_cut(&mut tiled, &fixture, DEFAULT_LOD_ERROR_PX, &settings);
    assert_eq!(
        report.counts.points_rendered,
        whole_report.counts.points_rendered
    );
    // As in `raster/tests/tiles.rs`: a point within rounding of a pixel's edge may move.
    let diff = compare_images_within("cut-tiles", &frame.image, &whole.image, 0);
    assert!(
        diff.differing <= 200 * 150 / 2000,
        "{} pixels differ",
        diff.differing
    );
}

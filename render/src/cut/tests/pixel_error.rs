//! What the pixel error trades: points drawn against fidelity; and the one spacing a store and
//! its cloud share.

use super::*;

#[test]
fn a_coarser_pixel_error_draws_fewer_points_and_the_default_keeps_the_image() {
    let fixture = fixture(120_000);
    let mut renderer = Renderer::new(gpu());
    for (quality, least) in [(Quality::Basic, 0.96), (Quality::HIGH, 0.99)] {
        let mut settings = settings(&fixture, &basic());
        settings.quality = quality;
        let (full_frame, full_report) = fresh_cut(&mut renderer, &fixture, 0.0, &settings);
        let (frame, report) = fresh_cut(&mut renderer, &fixture, DEFAULT_LOD_ERROR_PX, &settings);
        let share = fidelity("cut-default-error", &frame.image, &full_frame.image);
        assert!(
            share >= least,
            "{quality:?}: {share:.4} of covered pixels within 8/255"
        );
        assert!(report.counts.points_rendered <= full_report.counts.points_rendered);
    }
    // Far away, a coarser error draws fewer points.
    let mut settings = settings(&fixture, &basic());
    let target = fixture.cloud.bounds.center();
    settings.camera.position = target + (settings.camera.position - target) * 3.0;
    settings.camera.far *= 4.0;
    let points = |lod_error: f64, renderer: &mut Renderer| {
        let mut cut = cut_renderer(renderer, &fixture, lod_error);
        cut.render(
            renderer,
            &fixture.dataset,
            &settings,
            ColorMode::Rgb,
            &PointFilter::default(),
        )
        .expect("frame")
        .1
        .counts
        .points_rendered
    };
    let (full, default, coarse) = (
        points(0.0, &mut renderer),
        points(DEFAULT_LOD_ERROR_PX, &mut renderer),
        points(2.0, &mut renderer),
    );
    assert!(
        coarse < default && default < full,
        "{coarse} {default} {full}"
    );
}

/// A small image of many points: the pixel error alone would draw them all, the cut stops at
/// the points its pixels warrant; at 0 px every point is drawn all the same.
#[test]
fn a_cut_draws_at_most_its_pixels_worth_of_points_unless_asked_for_every_point() {
    let fixture = fixture(60_000);
    let mut renderer = Renderer::new(gpu());
    let mut settings = settings(&fixture, &basic());
    (settings.width, settings.height) = (20, 15);
    let cap = 20 * 15 * crate::cut::MAX_CUT_POINTS_PER_PIXEL;
    let (_, capped) = fresh_cut(&mut renderer, &fixture, 0.05, &settings);
    assert!(capped.counts.limited_by_budget, "{:?}", capped.counts);
    assert!(
        capped.counts.points_rendered <= cap && capped.counts.points_rendered > cap / 2,
        "{} points for a cap of {cap}",
        capped.counts.points_rendered
    );
    let (_, full) = fresh_cut(&mut renderer, &fixture, 0.0, &settings);
    assert!(!full.counts.limited_by_budget);
    assert!(full.counts.points_rendered > 4 * cap, "{:?}", full.counts);
}

/// The fidelity table of docs/perf/lod-fidelity.md: `cargo test -p pointfarm-render --lib
/// cut::tests::pixel_error::fidelity_by_pixel_error -- --ignored --nocapture`.
#[test]
#[ignore]
fn fidelity_by_pixel_error() {
    let fixture = fixture(400_000);
    let mut renderer = Renderer::new(gpu());
    let views = [
        (1.0, Quality::Basic),
        (3.0, Quality::Basic),
        (1.0, Quality::HIGH),
        (3.0, Quality::HIGH),
    ];
    for (distance, quality) in views {
        let mut settings = settings(&fixture, &basic());
        settings.quality = quality;
        let target = fixture.cloud.bounds.center();
        settings.camera.position = target + (settings.camera.position - target) * distance;
        settings.camera.far *= 4.0;
        let (full_frame, _) = fresh_cut(&mut renderer, &fixture, 0.0, &settings);
        for error in [0.1, 0.25, 0.5, 1.0, 2.0] {
            let (frame, report) = fresh_cut(&mut renderer, &fixture, error, &settings);
            let share = fidelity("fidelity", &frame.image, &full_frame.image);
            eprintln!(
                "distance {distance} {quality:?} error {error}: {} of {} points, {share:.4}",
                report.counts.points_rendered, report.counts.points_total
            );
        }
    }
}

/// Adaptive points are as large from a store as from the whole cloud: the leaves' spacing is
/// the points' spacing.
#[test]
fn a_store_and_its_cloud_have_one_spacing() {
    let fixture = fixture(60_000);
    let from_points = fixture.cloud.spacing().expect("the cloud's spacing");
    let from_leaves = fixture
        .dataset
        .hierarchy()
        .point_spacing()
        .expect("the store's spacing");
    let ratio = from_leaves / from_points;
    assert!(
        (0.7..1.5).contains(&ratio),
        "leaves {from_leaves}, points {from_points}"
    );
}

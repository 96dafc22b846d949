//! Filtered renders against the CPU reference of the points a filter keeps, chosen here
//! point by point: classes, returns, intensity and a clip box, alone and together.

use super::*;
use crate::filter::{ClipBox, CodeSet, IntensityRange, PointFilter};

/// A scene of three layers a pixel whose points carry attributes drawn at random.
fn attributed_scene(settings: &FrameSettings) -> PointCloud {
    let mut cloud = pixel_centre_scene(settings, 3, 11);
    let mut rng = ChaCha8Rng::seed_from_u64(12);
    for i in 0..cloud.len() {
        cloud.classification[i] = [1, 2, 5, 6, 7][rng.random_range(0..5)];
        cloud.return_number[i] = rng.random_range(1..=4);
        cloud.intensity[i] = rng.random_range(0..4000);
    }
    cloud
}

#[test]
fn filters_draw_what_the_reference_draws_of_the_kept_points() {
    let settings = perspective_settings(160, 120);
    let cloud = attributed_scene(&settings);
    let unfiltered = reference::render_basic(&cloud, &settings).image;
    // A box around the camera's target, 30 units each way.
    let clip = ClipBox {
        min: (SURVEY_ORIGIN - DVec3::splat(30.0)).to_array(),
        max: (SURVEY_ORIGIN + DVec3::splat(30.0)).to_array(),
    };
    type Keeps = fn(u8, u8, u16, DVec3) -> bool;
    let cases: [(&str, PointFilter, Keeps); 5] = [
        (
            "classes",
            PointFilter {
                classes: Some(CodeSet::of([2, 6])),
                ..Default::default()
            },
            |class, _, _, _| class == 2 || class == 6,
        ),
        (
            "returns",
            PointFilter {
                return_numbers: Some(CodeSet::of([1])),
                ..Default::default()
            },
            |_, number, _, _| number == 1,
        ),
        (
            "intensity",
            PointFilter {
                intensity: Some(IntensityRange {
                    min: 1000,
                    max: 2999,
                }),
                ..Default::default()
            },
            |_, _, intensity, _| (1000..3000).contains(&intensity),
        ),
        (
            "clip",
            PointFilter {
                clip: Some(clip),
                ..Default::default()
            },
            |_, _, _, p| (p - SURVEY_ORIGIN).abs().max_element() <= 30.0,
        ),
        (
            "together",
            PointFilter {
                classes: Some(CodeSet::of([1, 2, 5])),
                return_numbers: Some(CodeSet::of([1, 2])),
                intensity: Some(IntensityRange {
                    min: 500,
                    max: 4000,
                }),
                clip: Some(clip),
            },
            |class, number, intensity, p| {
                class != 6
                    && class != 7
                    && number <= 2
                    && intensity >= 500
                    && (p - SURVEY_ORIGIN).abs().max_element() <= 30.0
            },
        ),
    ];
    for (name, filter, keeps) in cases {
        let kept: Vec<usize> = (0..cloud.len())
            .filter(|&i| {
                let world = cloud.origin + cloud.positions[i].as_dvec3();
                keeps(
                    cloud.classification[i],
                    cloud.return_number[i],
                    cloud.intensity[i],
                    world,
                )
            })
            .collect();
        assert!(
            kept.len() > cloud.len() / 10 && kept.len() < cloud.len(),
            "{name}: the case keeps {} of {} points",
            kept.len(),
            cloud.len()
        );
        let expected = reference::render_basic(&cloud.select(&kept), &settings).image;
        let mut filtered = cloud.clone();
        assert_eq!(
            filter.apply(&mut filtered).expect("inside"),
            kept.len(),
            "{name}"
        );
        let frame = render_gpu(&filtered, &settings);
        let diff = compare_images(&format!("filter-{name}"), &frame.image, &expected);
        assert_eq!(
            diff.differing, 0,
            "{name}: {} pixels differ",
            diff.differing
        );
        // The filter shows through: points behind dropped ones, and background.
        let changed = frame
            .image
            .pixels()
            .zip(unfiltered.pixels())
            .filter(|(a, b)| a != b)
            .count();
        assert!(changed > 500, "{name}: only {changed} pixels changed");
    }
}

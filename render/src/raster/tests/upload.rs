//! Uploading clouds: the bytes a point takes on the GPU, streamed uploads, and clouds larger
//! than one storage binding rendered in segments.

use super::*;

/// Bytes per point on the GPU, from the sizes of the buffers that hold the cloud: quantised
/// positions, packed colors and the batch tables.
#[test]
fn points_take_at_most_12_bytes_each_on_the_gpu() {
    let mut renderer = Renderer::new(gpu());
    let cloud = crate::sample::sample_scene(50_000, 7);
    for segment_points in [usize::MAX, 3 * BATCH_POINTS] {
        renderer.set_max_segment_points(segment_points);
        let resident = renderer.upload(&cloud).expect("upload");
        let per_point = resident.gpu_bytes_per_point();
        assert!(
            (POINT_BYTES as f64..=12.0).contains(&per_point),
            "{per_point} bytes per point in {} segments",
            resident.segment_count()
        );
    }
}

/// A cloud uploaded segment by segment renders like the same points uploaded whole.
#[test]
fn a_streamed_upload_renders_like_a_whole_one() {
    let settings = perspective_settings(96, 64);
    let cloud = pixel_centre_scene(&settings, 2, 21);
    let (mut renderer, whole) = uploaded(&cloud);
    let mut next = 0;
    let streamed = renderer
        .upload_segments(cloud.origin, &mut |n| {
            let range = next..(next + n.min(5000)).min(cloud.len());
            next = range.end;
            (!range.is_empty()).then(|| {
                (
                    cloud.positions[range.clone()].to_vec(),
                    cloud.colors[range].to_vec(),
                )
            })
        })
        .expect("streamed upload");
    assert_eq!(streamed.len(), cloud.len());
    let a = renderer.render(&whole, &settings).expect("render");
    let b = renderer.render(&streamed, &settings).expect("render");
    let diff = compare_images("streamed-upload", &b.image, &a.image);
    assert_eq!(diff.differing, 0);
}

#[test]
fn a_cloud_larger_than_one_binding_renders_in_segments() {
    let settings = perspective_settings(160, 120);
    let cloud = pixel_centre_scene(&settings, 3, 5);
    let mut renderer = Renderer::new(gpu());
    // Lower the binding limit to two batches per segment.
    renderer.set_max_segment_points(2 * BATCH_POINTS);
    let resident = renderer.upload(&cloud).expect("upload");
    assert!(
        resident.segment_count() >= 4,
        "only {} segments",
        resident.segment_count()
    );
    for atomics in [AtomicsMode::Auto, AtomicsMode::Force32] {
        let frame = render_with_atomics(&mut renderer, &resident, &settings, atomics);
        let expected = reference::render_basic(&cloud, &settings);
        assert_eq!(
            compare_images("segmented", &frame.image, &expected.image).differing,
            0
        );
    }
}

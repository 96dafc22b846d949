//! The atomics paths and workgroup sizes: 64-bit and 32-bit atomics, and every point-pass
//! workgroup size, render the same images.

use super::*;

#[test]
fn fallback_32_bit_path_renders_the_same_image_as_the_64_bit_path() {
    let gpu = gpu();
    assert!(
        gpu.capabilities.int64_atomics,
        "this adapter lacks 64-bit atomics; the comparison needs both paths"
    );
    let mut settings = perspective_settings(160, 120);
    settings.read_depth = true;
    // Many points per pixel, including exact depth ties broken by color.
    let mut cloud = pixel_centre_scene(&settings, 4, 4);
    let duplicates: Vec<usize> = (0..cloud.len())
        .chain((0..cloud.len()).step_by(3))
        .collect();
    cloud = cloud.select(&duplicates);
    for (i, c) in cloud
        .colors
        .iter_mut()
        .enumerate()
        .skip(cloud.positions.len() * 3 / 4)
    {
        *c = pack_rgba8(i as u8, 0, 255 - i as u8);
    }
    let mut renderer = Renderer::new(gpu);
    let resident = renderer.upload(&cloud).expect("upload");
    let wide = renderer.render(&resident, &settings).expect("64-bit");
    settings.atomics = AtomicsMode::Force32;
    let narrow = renderer.render(&resident, &settings).expect("32-bit");
    assert_eq!(wide.atomics, AtomicsPath::Atomic64);
    assert_eq!(narrow.atomics, AtomicsPath::Atomic32);
    let diff = compare_images("fallback-vs-64", &narrow.image, &wide.image);
    assert_eq!(diff.differing, 0);
    assert_eq!(narrow.depth, wide.depth);
    // Against the reference, exactly, except at a few depth ties: a point and its copy in
    // another batch are quantised apart by a rounding error, and a real GPU's fused
    // multiply-adds can put either in front (seen at 1 of ~4,800 tied pixels on an H200).
    let expected = reference::render_basic(&cloud, &settings).image;
    let ties = reference::depth_ties(&cloud, &settings, 1e-5);
    let tied = ties.iter().filter(|&&t| t).count();
    let differing: Vec<usize> = narrow
        .image
        .pixels()
        .zip(expected.pixels())
        .enumerate()
        .filter(|(_, (a, e))| a != e)
        .map(|(pixel, _)| pixel)
        .collect();
    if !differing.is_empty() {
        compare_images("fallback-vs-reference", &narrow.image, &expected);
    }
    assert!(
        differing.iter().all(|&pixel| ties[pixel]),
        "pixels without a depth tie differ from the reference"
    );
    assert!(
        tied > 1000 && differing.len() <= tied / 500,
        "{} of {tied} tied pixels differ from the reference",
        differing.len()
    );
}

/// The point passes' workgroup size depends on the adapter (one subgroup on lavapipe, 128 on
/// GPUs: `point_workgroup.rs`). Every size renders the same image, in both modes and on both
/// atomics paths, with several segments and point sizes.
#[test]
fn every_point_workgroup_size_renders_the_same_image() {
    let gpu = gpu();
    let mut settings = perspective_settings(160, 120);
    settings.read_depth = true;
    let cloud = surface_with_depth_noise(&settings, 11);
    let sizes = [4, 8, 32, 128, 256];
    let mut renderers: Vec<_> = sizes
        .iter()
        .map(|&size| {
            let mut renderer = Renderer::with_point_workgroup_size(gpu.clone(), size);
            renderer.set_max_segment_points(2 * BATCH_POINTS);
            let resident = renderer.upload(&cloud).expect("upload");
            (renderer, resident)
        })
        .collect();
    assert!(renderers[0].1.segment_count() > 1);
    for quality in [Quality::Basic, Quality::HIGH] {
        for atomics in [AtomicsMode::Auto, AtomicsMode::Force32] {
            for point_size in [1, 2] {
                let settings = FrameSettings {
                    quality,
                    atomics,
                    point_size,
                    ..settings
                };
                let frames: Vec<Frame> = renderers
                    .iter_mut()
                    .map(|(renderer, resident)| {
                        renderer.render(resident, &settings).expect("render")
                    })
                    .collect();
                for (size, frame) in sizes.iter().zip(&frames).skip(1) {
                    let name = format!("workgroup-{size}-{quality:?}-{atomics:?}-{point_size}");
                    let diff = compare_images(&name, &frame.image, &frames[0].image);
                    assert_eq!(diff.differing, 0, "{name}");
                    assert_eq!(frame.depth, frames[0].depth, "{name}");
                }
            }
        }
    }
}

/// The high-quality accumulation adds its sums with 64-bit atomics where the device has them
/// (`hq_pass.rs`) and with 32-bit ones otherwise: both give the reference's image, the same to
/// the bit, with and without large points.
#[test]
fn high_quality_sums_are_the_same_with_64_and_32_bit_atomics() {
    let gpu = gpu();
    eprintln!(
        "64-bit atomicAdd on this adapter: {}",
        gpu.capabilities.int64_atomic_add
    );
    let mut renderer = Renderer::new(gpu);
    for point_size in [1, 3] {
        let mut settings = perspective_settings(96, 64);
        settings.quality = Quality::HIGH;
        settings.read_depth = true;
        settings.point_size = point_size;
        let cloud = surface_with_depth_noise(&settings, 11);
        let resident = renderer.upload(&cloud).expect("upload");
        let auto = renderer.render(&resident, &settings).expect("render");
        let forced = FrameSettings {
            atomics: AtomicsMode::Force32,
            ..settings
        };
        let with_32 = renderer.render(&resident, &forced).expect("render");
        let name = format!("hq-sums-size-{point_size}");
        let diff = compare_images(&name, &auto.image, &with_32.image);
        assert_eq!(diff.differing, 0, "{name}");
        assert_eq!(auto.depth, with_32.depth, "{name}");
        let expected = reference::render(&cloud, &settings);
        let difference = max_channel_difference(&auto.image, &expected.image);
        assert!(difference <= 1, "{name}: differs by {difference}/255");
    }
}

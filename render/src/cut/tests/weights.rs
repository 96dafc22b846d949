//! High quality on a cut weighs each point by the original points it stands for.

use super::*;
use crate::testing::max_channel_difference;

/// High quality on a cut's pages adds each point as many times as its weight where its
/// node's child below it is not drawn, once where it is: the frame matches the weighted
/// reference within a level, on the packed sums (light points, pixels under and over their
/// 256) and the wide ones (heavy points), and the 64-bit path matches the 32-bit one to the
/// bit. The root and a grandchild are drawn, the child between them left without points (its
/// parent took them all), so not listed: the root's points in that child's octant count once.
#[test]
fn weighted_high_quality_matches_the_weighted_reference() {
    use super::gpu_cache::GpuNodeCache;
    use crate::lod::weights::{decode_weight, encode_weight, WEIGHT_CODE_BITS};
    use crate::raster::AtomicsMode;

    let camera = side_view();
    let mut settings = FrameSettings::new(96, 64, camera);
    settings.quality = Quality::High { depth_band: 0.5 };
    settings.point_size = 1;
    let origin = glam::DVec3::ZERO;
    let columns = pixel_centre_points(&settings, origin, 0..96);
    let mut state = 0x9e37_79b9_7f4a_7c15u64;
    let mut next = |n: u64| {
        state = state
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        (state >> 33) % n
    };
    // Per pixel 1 to 60 points along its ray, 1.0 to 1.3 times the first's depth; weights
    // mostly light, some heavy, so that pixels fill the packed sums and spill past them.
    let mut world = Vec::new();
    let mut bits = Vec::new();
    for (p, first) in columns.iter().enumerate() {
        let ray = (*first - camera.position).normalize();
        let depth = (*first - camera.position).length();
        for k in 0..=next(60) {
            let along = if k == 0 {
                0.0
            } else {
                depth * (1 + next(300)) as f64 / 1000.0
            };
            world.push(*first + ray * along);
            let weight = match next(10) {
                0..=5 => 1 + next(16) as u32,
                6..=7 => 17 + next(300) as u32,
                8 => 1 + next(3) as u32,
                _ => 1000 + next(50_000) as u32,
            };
            let octant = (p as u16 + k as u16) % 8;
            bits.push(encode_weight(weight) | octant << WEIGHT_CODE_BITS);
        }
    }
    let colors: Vec<u32> = (0..world.len())
        .map(|_| crate::cloud::pack_rgba8(next(256) as u8, next(256) as u8, next(256) as u8))
        .collect();
    let cloud = PointCloud::from_world_points(&world, colors);
    // The root holds the first half of the points, a node below its child 0 the rest.
    let half = world.len() / 2;
    let parts = [
        (NodeKey::ROOT, 0..half),
        (NodeKey::ROOT.child(0).child(3), half..world.len()),
    ];
    let renderer = &mut Renderer::new(gpu());
    let mut cache = GpuNodeCache::new(cloud.origin, 64 << 20, 1 << 16);
    let keys: Vec<NodeKey> = parts.iter().map(|(k, _)| *k).collect();
    let keep: HashSet<NodeKey> = keys.iter().copied().collect();
    for (key, range) in &parts {
        let mut data = SegmentData::new(
            &cloud.positions[range.clone()],
            cloud.colors[range.clone()].iter().copied(),
        );
        data.weights = bits[range.clone()].to_vec();
        data.weights
            .resize(data.weights.len().next_multiple_of(2), 0);
        insert_whole(&mut cache, renderer, *key, &data, &keep);
    }
    // What each point counts for: the root's points in octant 0 once (drawn below child 0).
    let weights: Vec<u32> = bits
        .iter()
        .enumerate()
        .map(|(i, &b)| {
            let drawn_child = i < half && b >> WEIGHT_CODE_BITS == 0;
            if drawn_child {
                1
            } else {
                decode_weight(b)
            }
        })
        .collect();
    assert!(weights.iter().any(|&w| w > 256) && weights.iter().filter(|&&w| w == 1).count() > 100);
    let expected =
        crate::reference::render_high_quality_weighted(&cloud, &settings, 0.5, &weights).image;
    let unweighted = crate::reference::render_high_quality(&cloud, &settings, 0.5).image;
    let gpu_cloud = cache.frame_cloud(renderer.gpu(), &keys, 0.0, None);
    let auto = renderer.render(gpu_cloud, &settings).expect("render").image;
    let forced = FrameSettings {
        atomics: AtomicsMode::Force32,
        ..settings
    };
    let with_32 = renderer.render(gpu_cloud, &forced).expect("render").image;
    assert!(
        max_channel_difference(&expected, &unweighted) > 32,
        "the weights matter"
    );
    assert_eq!(
        max_channel_difference(&auto, &with_32),
        0,
        "64-bit against 32-bit sums"
    );
    let off = max_channel_difference(&auto, &expected);
    assert!(off <= 1, "differs from the weighted reference by {off}/255");
}

//! Adaptive point sizes on cuts: each batch drawn at the spacing of its nodes.

use super::*;

/// Batches drawn with a size factor are sized as the reference sizes their points at that
/// factor times the frame's adaptive size: two nodes side by side, the right one at twice the
/// left's size, match the references of each half.
#[test]
fn batches_take_their_own_point_size_factor() {
    use super::gpu_cache::GpuNodeCache;

    let mut settings = FrameSettings::new(96, 64, side_view());
    settings.background = [0, 0, 0, 0];
    settings.adaptive_size = Some(16.0);
    settings.point_size = crate::raster::MAX_ADAPTIVE_POINT_SIZE;
    let origin = glam::DVec3::ZERO;
    // Left and right halves, 12 pixels apart: no square of one reaches the other's pixels.
    let left = pixel_centre_points(&settings, origin, 0..42);
    let right = pixel_centre_points(&settings, origin, 54..96);
    let world: Vec<glam::DVec3> = left.iter().chain(&right).copied().collect();
    let colors = (0..world.len() as u32)
        .map(|i| crate::cloud::pack_rgba8((i * 37) as u8, (i * 91) as u8, 200))
        .collect();
    let cloud = PointCloud::from_world_points(&world, colors);
    let halves = [
        cloud.select(&(0..left.len()).collect::<Vec<_>>()),
        cloud.select(&(left.len()..world.len()).collect::<Vec<_>>()),
    ];
    assert!(halves
        .iter()
        .all(|h| h.len() <= crate::raster::BATCH_POINTS));

    let renderer = &mut Renderer::new(gpu());
    let mut cache = GpuNodeCache::new(cloud.origin, 64 << 20, 1 << 16);
    let keys = [NodeKey::ROOT.child(0), NodeKey::ROOT.child(7)];
    let keep: HashSet<NodeKey> = keys.into_iter().collect();
    for (key, half) in keys.iter().zip(&halves) {
        let data = SegmentData::new(&half.positions, half.colors.iter().copied());
        insert_whole(&mut cache, renderer, *key, &data, &keep);
    }
    let factor_of = |key: NodeKey| if key == keys[0] { 1.0 } else { 2.0 };
    let mut factor = |key: NodeKey, _: &GpuBatch| factor_of(key);
    let gpu_cloud = cache.frame_cloud(renderer.gpu(), &keys, 0.0, Some(&mut factor));
    let frame = renderer.render(gpu_cloud, &settings).expect("render");

    let mut expected = image::RgbaImage::new(settings.width, settings.height);
    let mut sides = std::collections::BTreeSet::new();
    for (key, half) in keys.iter().zip(&halves) {
        let sized = FrameSettings {
            adaptive_size: Some(16.0 * factor_of(*key)),
            ..settings
        };
        let t = sized
            .camera
            .transform(half.origin, sized.width, sized.height);
        sides.extend(
            half.positions
                .iter()
                .filter_map(|p| t.project(p.as_dvec3()))
                .map(|(_, _, depth)| sized.point_side_at(depth as f32)),
        );
        let reference = crate::reference::render_basic(half, &sized).image;
        for (out, drawn) in expected.pixels_mut().zip(reference.pixels()) {
            if drawn.0 != settings.background {
                *out = *drawn;
            }
        }
    }
    assert_eq!(sides, (1..=8).collect(), "the halves span every side");
    let diff = crate::testing::compare_images("batch-size-factors", &frame.image, &expected);
    assert_eq!(diff.differing, 0, "{} pixels differ", diff.differing);
}

/// Where a cut stops at coarse nodes, adaptive points take those nodes' spacing: a coarse
/// pixel error covers the surface about as full detail does, not with the holes that points
/// sized for the finest nodes leave (at 6 px those cover 53% of full detail's pixels; with
/// each node's spacing 94%, the rest being gaps where a cell's point lies off its centre).
#[test]
fn adaptive_points_of_a_coarse_cut_close_the_surface() {
    let fixture = fixture(120_000);
    let mut renderer = Renderer::new(gpu());
    let spacing = fixture.dataset.point_spacing();
    let camera = Camera::auto(&fixture.cloud.bounds, 4.0 / 3.0);
    let settings = FrameSettings::new(200, 150, camera).with_point_size(
        PointSize::Adaptive,
        &fixture.cloud.bounds,
        spacing,
    );
    let (full, full_report) = fresh_cut(&mut renderer, &fixture, 0.0, &settings);
    let (coarse, coarse_report) = fresh_cut(&mut renderer, &fixture, 6.0, &settings);
    assert!(
        coarse_report.counts.points_rendered * 4 < full_report.counts.points_rendered,
        "the coarse cut draws far fewer points: {:?}",
        coarse_report.counts
    );
    let (full, coarse) = (covered(&full.image), covered(&coarse.image));

    assert!(
        coarse as f64 >= 0.9 * full as f64,
        "covered pixels: full detail {full}, coarse cut {coarse}"
    );
}

/// A batch of the root takes the root's own spacing where the cut stops at it, and the
/// spacing of the deepest nodes below it where the cut reaches them.
#[test]
fn a_batch_takes_the_spacing_of_the_deepest_nodes_drawn_where_it_lies() {
    let fixture = fixture(60_000);
    let hierarchy = fixture.dataset.hierarchy();
    let reference = fixture.dataset.point_spacing().expect("spacing");
    let settings = settings(&fixture, &basic());
    let transform =
        settings
            .camera
            .transform(fixture.dataset.origin(), settings.width, settings.height);
    let bounds = &fixture.cloud.bounds;
    let whole = GpuBatch {
        min: (bounds.min - fixture.dataset.origin()).as_vec3().to_array(),
        first: 0,
        max: (bounds.max - fixture.dataset.origin()).as_vec3().to_array(),
        count: 1,
    };
    let root_factor = |lod_error: f64| {
        let view = CutView {
            camera: &settings.camera,
            origin: fixture.dataset.origin(),
            width: settings.width,
            height: settings.height,
            point_size: 1,
            lod_error,
            max_batches: usize::MAX,
            max_points: None,
            clip: None,
        };
        let cut = select_cut(hierarchy, &view);
        let mut sizes = CutPointSizes::new(
            hierarchy,
            &cut,
            NodesInView::new(hierarchy, &view, &transform),
            &transform,
            fixture.dataset.origin(),
            reference,
            1.0,
        );
        (cut.nodes.len(), sizes.factor(NodeKey::ROOT, &whole) as f64)
    };
    let root_cell = hierarchy.spacing(NodeKey::ROOT).expect("an inner root");
    let (nodes, coarse) = root_factor(1e9);
    assert_eq!(nodes, 1, "only the root");
    assert!((coarse - root_cell / reference).abs() < 1e-5, "{coarse}");

    let (nodes, full) = root_factor(0.0);
    assert_eq!(nodes, hierarchy.stored_nodes().count());
    let coarsest_leaf = hierarchy
        .nodes()
        .iter()
        .filter(|n| n.is_leaf())
        .filter_map(|n| hierarchy.points_spacing(n.key))
        .fold(0.0, f64::max);
    assert!(
        full < coarse && (full - coarsest_leaf / reference).abs() < 1e-5,
        "every node drawn: {full}, the coarsest leaf {}",
        coarsest_leaf / reference
    );
}

//! The node caches within their budgets, the read-ahead, and a damaged node.

use super::*;

#[test]
fn the_caches_stay_within_their_budgets_and_evict() {
    let fixture = fixture(120_000);
    let mut renderer = Renderer::new(gpu());
    let budgets = CacheBudgets {
        host_bytes: 600 << 10,
        gpu_bytes: 30 * SLOT_BYTES,
    };
    let mut cut =
        CutRenderer::with_budgets(&renderer, &fixture.dataset, CutOptions::default(), budgets);
    let mut evicted = 0;
    for step in 0..6 {
        let mut settings = settings(&fixture, &basic());
        settings.camera = Camera::framing(
            &fixture.cloud.bounds,
            4.0 / 3.0,
            f64::from(step) * 60.0,
            35.0,
            Projection::Perspective { fov_y_deg: 30.0 },
        );
        let again = settings;
        let (frame, report) = cut
            .render_rgb(&mut renderer, &fixture.dataset, &settings)
            .expect("frame");
        assert!(report.gpu_cache_bytes <= budgets.gpu_bytes, "{report:?}");
        assert!(report.host_cache_bytes <= budgets.host_bytes, "{report:?}");
        assert!(
            report.counts.points_rendered <= 30 * BATCH_POINTS_U64,
            "{report:?}"
        );
        evicted += report.counts.gpu_evicted;
        // The same view again, after whatever the budget evicted: the same image.
        let (repeat, _) = cut
            .render_rgb(&mut renderer, &fixture.dataset, &again)
            .expect("repeat");
        assert!(
            repeat.image == frame.image,
            "step {step}: a repeated frame differs"
        );
    }
    assert!(evicted > 0, "a small GPU budget evicts as the camera turns");
}

#[test]
fn a_read_ahead_fills_the_host_cache_and_changes_no_pixel() {
    let (fixture, mut renderer, first) = basic_frame(40_000);
    let mut next = first;
    next.camera.position =
        first.camera.target + (first.camera.position - first.camera.target) * 0.5;
    let (expected, _) = fresh_cut(&mut renderer, &fixture, 0.0, &next);

    let mut cut = CutRenderer::with_budgets(
        &renderer,
        &fixture.dataset,
        CutOptions {
            lod_error: 0.0,
            ..CutOptions::default()
        },
        CacheBudgets {
            host_bytes: 64 << 20,
            gpu_bytes: 64 << 20,
        },
    );
    cut.render(
        &mut renderer,
        &fixture.dataset,
        &first,
        ColorMode::Intensity,
        &PointFilter::default(),
    )
    .expect("first");
    // Another color mode empties the GPU cache, so the next frame needs every node.
    cut.read_ahead(&fixture.dataset, &next, &PointFilter::default());
    let (frame, report) = cut
        .render_rgb(&mut renderer, &fixture.dataset, &next)
        .expect("next");
    assert_eq!(report.counts.gpu_hits, 0);
    assert_eq!(
        report.counts.nodes_read, 0,
        "every node came from the host cache: {report:?}"
    );
    assert!(report.counts.host_hits > 0);
    assert!(frame.image == expected.image);
}

#[test]
fn a_damaged_node_is_reported_not_drawn() {
    let fixture = fixture(20_000);
    let hierarchy = fixture.dataset.hierarchy();
    let node = hierarchy
        .nodes()
        .iter()
        .find(|n| n.point_count > 100)
        .copied()
        .expect("a node");
    let store = &fixture.store;
    let mut bytes = store
        .node_bytes(hierarchy, node.key)
        .expect("read")
        .expect("bytes");
    let middle = bytes.len() / 2;
    bytes[middle] ^= 0x55;
    // The same length: damaged in place, where the dataset's hierarchy points.
    store
        .overwrite_node_bytes(&mut hierarchy.clone(), node.key, &bytes)
        .expect("damage");
    let mut renderer = Renderer::new(gpu());
    let mut cut = cut_renderer(&renderer, &fixture, 0.0);
    let settings = settings(&fixture, &basic());
    let Err(error) = cut.render_rgb(&mut renderer, &fixture.dataset, &settings) else {
        panic!("a damaged node fails the frame");
    };
    assert!(
        matches!(error, CutError::Store(LodError::CorruptNode { .. })),
        "{error}"
    );
    assert!(error.to_string().contains(&node.key.to_string()), "{error}");
}

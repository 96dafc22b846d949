//! What a COPC export carries for readers. Its points' weights: a file pointfarm wrote gives
//! its points the weights of the store it was written from, so high quality on its cuts
//! averages what full detail would, as on the store; a foreign file's points count once. Its
//! spacing: one that no node is sparser than.

use std::path::{Path, PathBuf};

use super::tests::copc_file;
use super::*;
use crate::camera::Camera;
use crate::color::ColorMode;
use crate::cut::{CutOptions, CutRenderer};
use crate::filter::PointFilter;
use crate::lod::copc_export::{export_copc, ExportSettings};
use crate::lod::{build_lod, GeneratedSource, LodBuildOptions, LodHierarchy, LodStore};
use crate::raster::{FrameSettings, Quality, Renderer, Shading};
use crate::request::PointSize;
use crate::testing::{compare_images_within, gpu};

pub(super) struct Exported {
    _db: sled::Db,
    store: LodStore,
    hierarchy: LodHierarchy,
    pub path: PathBuf,
}

/// A generated terrain of `points` built with leaves of at most `max_leaf_points` and
/// exported as a COPC file.
pub(super) fn exported_terrain(dir: &Path, points: u64, max_leaf_points: usize) -> Exported {
    let source = GeneratedSource::terrain(points, 7);
    let db = sled::open(dir.join("db")).expect("sled");
    let store =
        LodStore::open(db.open_tree("lod").expect("tree"), dir.join("lod.bin")).expect("store");
    let mut options = LodBuildOptions::new(dir.join("spill"));
    options.max_leaf_points = max_leaf_points;
    let hierarchy = build_lod(&source, &store, &options)
        .expect("build")
        .hierarchy;
    let path = dir.join("terrain.copc.laz");
    let settings = ExportSettings::fixed(&hierarchy.cube);
    export_copc(&hierarchy, &store, &settings, &path, &mut |_| {}).expect("export");
    Exported {
        _db: db,
        store,
        hierarchy,
        path,
    }
}

#[test]
fn an_exported_files_nodes_carry_the_weights_of_its_store() {
    let dir = tempfile::tempdir().expect("tempdir");
    let exported = exported_terrain(dir.path(), 60_000, 1_000);
    let opened = open_copc_whole(&exported.path).expect("opens");
    assert_eq!(
        opened.decoder.weight_at(),
        Some(opened.decoder.record_len() - 4),
        "the weight is the record's last 4 bytes"
    );
    let hierarchy = opened.dataset.hierarchy();
    let records = opened.dataset.records();
    let mut heavier = 0;
    for info in exported
        .hierarchy
        .nodes()
        .iter()
        .filter(|n| n.point_count > 0)
    {
        let stored = exported
            .store
            .read_node(&exported.hierarchy, info.key)
            .expect("stored node");
        let copc_info = hierarchy
            .nodes()
            .iter()
            .find(|n| n.key == info.key)
            .expect("the same node in the file");
        let bytes = records.read_records(&[*copc_info]).expect("read");
        let decoded = records
            .decode(&hierarchy.cube, copc_info, &bytes[0])
            .expect("decodes");
        assert_eq!(decoded.weights, stored.weights, "node {}", info.key);
        heavier += stored.weights.iter().filter(|&&w| w > 1).count();
    }
    assert!(heavier > 1_000, "inner nodes' points stand for others");

    // A file another writer made keeps no weights: its points count once.
    let foreign = open_copc(&copc_file("simple.copc.laz")).expect("opens");
    assert_eq!(foreign.decoder.weight_at(), None);
}

/// A camera over the terrain's corner, looking across it, so that a pixel's 20% depth band
/// reaches from the canopy to the ground behind it.
fn across(bounds: &crate::cloud::WorldBounds) -> FrameSettings {
    let mut camera = Camera::auto(bounds, 4.0 / 3.0);
    let centre = bounds.center();
    let size = bounds.size();
    camera.position = glam::DVec3::new(
        bounds.min.x - 0.2 * size.x,
        bounds.min.y - 0.2 * size.y,
        bounds.max.z + 0.15 * size.x,
    );
    camera.target = centre;
    let mut settings =
        FrameSettings::new(120, 90, camera).with_point_size(PointSize::Adaptive, bounds, None);
    settings.shading = Shading::None;
    settings.quality = Quality::High { depth_band: 0.2 };
    settings
}

/// 300k points, 120x90, a 20% depth band: at 1 px the cut draws 60% of the points in view,
/// and 99.5% of covered pixels stay within 8/255 of full detail with the weights, 92.0%
/// with every point counting once.
#[test]
fn high_quality_on_a_cut_of_an_exported_file_keeps_the_fidelity_rule() {
    let dir = tempfile::tempdir().expect("tempdir");
    let exported = exported_terrain(dir.path(), 300_000, 3_000);
    let opened = open_copc(&exported.path).expect("opens");
    let settings = across(&opened.dataset.bounds());
    let mut renderer = Renderer::new(gpu());
    let mut frame = |lod_error: f64, weighted: bool| {
        let options = CutOptions {
            lod_error,
            ..CutOptions::default()
        };
        let mut cut = CutRenderer::new(&renderer, &opened.dataset, options).expect("cut");
        cut.set_weighted_high_quality(weighted);
        let (frame, report) = cut
            .render(
                &mut renderer,
                &opened.dataset,
                &settings,
                ColorMode::Rgb,
                &PointFilter::default(),
            )
            .expect("frame");
        (frame.image, report.counts.points_rendered)
    };
    let (full, all) = frame(0.0, true);
    let covered = full
        .pixels()
        .filter(|p| p.0 != crate::raster::DEFAULT_BACKGROUND)
        .count();
    for lod_error in [0.5, 1.0] {
        let (weighted, drawn) = frame(lod_error, true);
        let (once, _) = frame(lod_error, false);
        let share = |name: &str, image: &image::RgbaImage| {
            1.0 - compare_images_within(name, image, &full, 8).differing as f64
                / covered.max(1) as f64
        };
        let (weighted, once) = (share("copc-weighted", &weighted), share("copc-once", &once));
        eprintln!("{lod_error} px: {drawn} points, weighted {weighted:.4}, once {once:.4}");
        assert!(
            drawn < all,
            "{lod_error} px: a cut, not every point in view"
        );
        assert!(
            weighted >= 0.97,
            "{lod_error} px: {weighted:.4} of covered pixels within 8/255"
        );
        if lod_error == 1.0 {
            // Where the cut stops at coarse nodes the weights are what keeps the rule.
            assert!(
                weighted - once >= 0.03,
                "weighted {weighted:.4}, every point once {once:.4}"
            );
        }
    }
}

/// A store samples each node on a grid of its own, halved where the node would hold more
/// than its bound, and COPC has one spacing, halved per level. With leaves of 1,000 points
/// this terrain's root keeps a grid of 128 and the nodes below grids of 8: the export
/// declares the coarsest grid's spacing, so no node is sparser than the file says and a
/// reader's cut refines where it must (declaring the root's, a cut at 0.5 px drew 2% of the
/// points and kept 27% of the covered pixels within 8/255 of full detail).
#[test]
fn an_export_declares_a_spacing_no_node_is_sparser_than() {
    let dir = tempfile::tempdir().expect("tempdir");
    let exported = exported_terrain(dir.path(), 300_000, 1_000);
    let opened = open_copc(&exported.path).expect("opens");
    let grids: std::collections::BTreeSet<u32> = exported
        .hierarchy
        .nodes()
        .iter()
        .map(|n| n.sample_grid)
        .filter(|&g| g > 0)
        .collect();
    assert!(
        grids.len() > 1,
        "nodes sampled on grids of several sizes: {grids:?}"
    );
    for node in exported.hierarchy.nodes() {
        if let Some(spacing) = exported.hierarchy.spacing(node.key) {
            let declared = opened.info.spacing / f64::from(1u32 << node.key.level);
            assert!(
                spacing <= declared * (1.0 + 1e-9),
                "node {}: spacing {spacing} in the store, {declared} declared",
                node.key
            );
        }
    }

    let mut settings = across(&opened.dataset.bounds());
    settings.quality = Quality::Basic;
    let mut renderer = Renderer::new(gpu());
    let mut frame = |lod_error: f64| {
        let options = CutOptions {
            lod_error,
            ..CutOptions::default()
        };
        let mut cut = CutRenderer::new(&renderer, &opened.dataset, options).expect("cut");
        cut.render(
            &mut renderer,
            &opened.dataset,
            &settings,
            ColorMode::Rgb,
            &PointFilter::default(),
        )
        .expect("frame")
    };
    let (full, _) = frame(0.0);
    let (cut, report) = frame(0.5);
    let covered = full
        .image
        .pixels()
        .filter(|p| p.0 != crate::raster::DEFAULT_BACKGROUND)
        .count();
    let close = 1.0
        - compare_images_within("copc-grids", &cut.image, &full.image, 8).differing as f64
            / covered.max(1) as f64;
    eprintln!(
        "grids {grids:?}; 0.5 px: {} of {} points, {close:.4} of covered pixels within 8/255",
        report.counts.points_rendered,
        opened.dataset.point_count()
    );
    assert!(close >= 0.97, "{close:.4} of covered pixels within 8/255");
}

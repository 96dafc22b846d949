//! What a COPC export carries for readers. Its points' weights: a file pointfarm wrote gives
//! its points the weights of the store it was written from, so high quality on its cuts
//! averages what full detail would, as on the store; a foreign file's points count once. Its
//! spacing: one that no node is sparser than, and each node's own grid for pointfarm's cuts.

use std::path::{Path, PathBuf};

use super::tests::{copc_file, cut_at, small_view};
use super::*;
use crate::camera::Camera;
use crate::cut::{select_cut, Cut};
use crate::lod::NodeKey;
use crate::raster::{FrameSettings, Quality, Renderer, Shading};
use crate::request::PointSize;
use crate::testing::{compare_images_within, exported_terrain, gpu};

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
    for info in exported.hierarchy.stored_nodes() {
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
        let mut cut = cut_at(&renderer, &opened.dataset, lod_error);
        cut.set_weighted_high_quality(weighted);
        let (frame, report) = cut
            .render_rgb(&mut renderer, &opened.dataset, &settings)
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
/// points and kept 27% of the covered pixels within 8/255 of full detail). The cut is drawn
/// as a reader that knows only the declared spacing draws it.
#[test]
fn an_export_declares_a_spacing_no_node_is_sparser_than() {
    let dir = tempfile::tempdir().expect("tempdir");
    let exported = exported_terrain(dir.path(), 300_000, 1_000);
    let opened = open_copc(&without_node_grids(&exported.path)).expect("opens");
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
        let mut cut = cut_at(&renderer, &opened.dataset, lod_error);
        cut.render_rgb(&mut renderer, &opened.dataset, &settings)
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

/// An export records each inner node's grid (the node grids EVLR), so pointfarm's cuts of the
/// file are the store's: the same nodes at every pixel error, from two sides. Without the
/// record a reader refines by the declared spacing, the coarsest grid's, and draws more.
#[test]
fn cuts_of_an_exported_file_are_the_stores() {
    let dir = tempfile::tempdir().expect("tempdir");
    let exported = exported_terrain(dir.path(), 300_000, 1_000);
    let opened = open_copc(&exported.path).expect("opens");
    let without = open_copc(&without_node_grids(&exported.path)).expect("opens");

    let bounds = opened.dataset.bounds();
    let origin = opened.dataset.origin();
    let cameras = [Camera::auto(&bounds, 4.0 / 3.0), across(&bounds).camera];
    let mut fewer = 0;
    for camera in &cameras {
        for lod_error in [8.0, 2.0, 1.0, 0.5, 0.25] {
            let view = small_view(camera, origin, lod_error);
            let nodes = |cut: Cut| -> Vec<(NodeKey, u32)> {
                cut.nodes.iter().map(|n| (n.key, n.points)).collect()
            };
            let store = nodes(select_cut(&exported.hierarchy, &view));
            let file = nodes(opened.dataset.select_cut(&view).expect("cut"));
            assert_eq!(file, store, "{lod_error} px");
            let declared = without.dataset.select_cut(&view).expect("cut").points();
            let points: u64 = store.iter().map(|&(_, p)| u64::from(p)).sum();
            assert!(
                declared >= points,
                "{lod_error} px: {declared} against {points}"
            );
            fewer += usize::from(declared > points);
        }
    }
    assert!(
        fewer > 0,
        "the nodes' own grids are finer than the declared one somewhere"
    );
}

/// A copy of the exported file `path` whose node grids EVLR is another writer's (its user id
/// changed), as a reader that does not know the record sees the file.
pub(super) fn without_node_grids(path: &Path) -> PathBuf {
    let mut bytes = std::fs::read(path).expect("read");
    // The user id lies at 2 of the EVLR's header.
    let header = node_grids_header(&bytes);
    bytes[header + 2] = b'q';
    let copy = path.with_file_name("without-grids.copc.laz");
    std::fs::write(&copy, &bytes).expect("write");
    copy
}

/// A damaged node grids record is an error naming the file and the record, whatever is wrong
/// in it: a length that is not whole entries, a key that is no cell, a grid of no cells, a
/// node listed twice.
#[test]
fn a_damaged_node_grids_record_is_an_error_naming_the_file() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (bytes, header) = exported_grids(dir.path());
    let data = header + 60;
    assert!(data + 40 <= bytes.len(), "two entries at least");
    let damaged = |name: &str, damage: &dyn Fn(&mut Vec<u8>)| -> String {
        let mut copy = bytes.clone();
        damage(&mut copy);
        let path = dir.path().join(name);
        std::fs::write(&path, &copy).expect("write");
        let Err(error) = open_copc(&path) else {
            panic!("{name} opened");
        };
        let message = error.to_string();
        assert!(message.contains(name), "{message}");
        assert!(message.contains("its node grids"), "{message}");
        message
    };
    let length = damaged("length.copc.laz", &|b| {
        let len = u64::from_le_bytes(b[header + 20..header + 28].try_into().expect("8"));
        b[header + 20..header + 28].copy_from_slice(&(len - 1).to_le_bytes());
    });
    assert!(
        length.contains("not a whole number of 20-byte entries"),
        "{length}"
    );
    let key = damaged("key.copc.laz", &|b| {
        b[data..data + 4].copy_from_slice(&30i32.to_le_bytes());
    });
    assert!(key.contains("is not a cell of its level"), "{key}");
    let grid = damaged("grid.copc.laz", &|b| {
        b[data + 16..data + 20].copy_from_slice(&0u32.to_le_bytes());
    });
    assert!(grid.contains("grid of 0 cells"), "{grid}");
    let twice = damaged("twice.copc.laz", &|b| {
        b.copy_within(data..data + 20, data + 20);
    });
    assert!(twice.contains("is listed twice"), "{twice}");
}

/// Any byte of the node grids record flipped, its header's included, opens (the record is
/// then another writer's, or says other grids, which a cut refines by) or is an error naming
/// the file: never a panic.
#[test]
fn any_byte_of_the_node_grids_flipped_opens_or_is_an_error_never_a_panic() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (original, header) = exported_grids(dir.path());
    let path = dir.path().join("flipped.copc.laz");
    let end = original.len();
    for at in (header..header + 60 + 60).chain(end - 20..end) {
        let mut bytes = original.clone();
        bytes[at] ^= 0x80;
        std::fs::write(&path, &bytes).expect("write");
        match open_copc(&path) {
            Ok(opened) => {
                let bounds = opened.dataset.bounds();
                let camera = Camera::auto(&bounds, 4.0 / 3.0);
                let view = small_view(&camera, opened.dataset.origin(), 1.0);
                let cut = opened.dataset.select_cut(&view).expect("cut");
                assert!(cut.points() > 0, "byte {at}: a cut of the file");
            }
            Err(error) => assert!(
                error.to_string().contains("flipped.copc.laz"),
                "byte {at}: {error}"
            ),
        }
    }
}

/// The bytes of a small terrain exported in `dir`, and where its node grids EVLR's header
/// starts: what the damage tests change.
fn exported_grids(dir: &Path) -> (Vec<u8>, usize) {
    let exported = exported_terrain(dir, 60_000, 1_000);
    let bytes = std::fs::read(&exported.path).expect("read");
    let header = node_grids_header(&bytes);
    (bytes, header)
}

/// Where the node grids EVLR's header starts in an exported file's `bytes` (its description
/// lies at 28 of the header).
fn node_grids_header(bytes: &[u8]) -> usize {
    let description = b"pointfarm node grids";
    bytes
        .windows(description.len())
        .rposition(|w| w == description)
        .expect("the node grids EVLR")
        - 28
}

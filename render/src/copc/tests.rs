//! COPC files read node by node against the same files read whole, drawn on the GPU against
//! the resident cloud, and damaged hierarchies refused naming the file.

use std::path::Path;

use super::*;
use crate::camera::Camera;
use crate::color::ColorMode;
use crate::cut::{CutOptions, CutRenderer, CutView};
use crate::filter::PointFilter;
use crate::ingest::load_point_cloud;
use crate::lod::{read_nodes, NodeKey};
use crate::raster::{FrameSettings, Renderer, Shading};
use crate::request::PointSize;
pub(super) use crate::testing::copc_file;
use crate::testing::{compare_images_within, gpu};

const FILES: [&str; 3] = [
    "autzen.copc.laz",
    "simple.copc.laz",
    "simple_with_page.copc.laz",
];

/// Every point of a file as integers on its scale grid, with its attributes, sorted.
type PointRow = ([i64; 3], u16, u8, u8, Option<[u16; 3]>);

fn whole_file_points(path: &Path) -> Vec<PointRow> {
    let mut reader = las::Reader::from_path(path).expect("las reads it");
    let t = *reader.header().transforms();
    let mut data = las::PointDataBuilder::new()
        .for_header(reader.header())
        .build();
    let count = reader.header().number_of_points();
    reader.fill_points(count, &mut data).expect("points");
    let raw = |v: f64, t: las::Transform| ((v - t.offset) / t.scale).round() as i64;
    let mut rgb = data.rgb().map(|rgb| rgb.collect::<Vec<_>>().into_iter());
    let mut rows: Vec<PointRow> = data
        .x()
        .zip(data.y())
        .zip(data.z())
        .zip(data.intensity())
        .zip(data.classification())
        .zip(data.return_number())
        .map(|(((((x, y), z), i), c), r)| {
            let color = rgb
                .as_mut()
                .and_then(|rgb| rgb.next())
                .map(|(r, g, b)| [r, g, b]);
            ([raw(x, t.x), raw(y, t.y), raw(z, t.z)], i, c, r, color)
        })
        .collect();
    rows.sort_unstable();
    rows
}

fn node_points(path: &Path) -> Vec<PointRow> {
    let reader = las::Reader::from_path(path).expect("las reads it");
    let t = *reader.header().transforms();
    let opened = open_copc(path).expect("opens");
    let hierarchy = opened.dataset.hierarchy();
    let keys: Vec<NodeKey> = hierarchy.nodes().iter().map(|n| n.key).collect();
    let nodes =
        read_nodes(opened.dataset.records().as_ref(), hierarchy, &keys).expect("every node");
    let mut rows = Vec::new();
    for node in &nodes {
        for (i, p) in node.world_positions().into_iter().enumerate() {
            rows.push((
                [
                    ((p.x - t.x.offset) / t.x.scale).round() as i64,
                    ((p.y - t.y.offset) / t.y.scale).round() as i64,
                    ((p.z - t.z.offset) / t.z.scale).round() as i64,
                ],
                node.intensity[i],
                node.classification[i],
                node.return_number[i],
                node.rgb.as_ref().map(|rgb| rgb[i]),
            ));
        }
    }
    rows.sort_unstable();
    rows
}

#[test]
fn real_copc_files_are_detected_by_their_info_vlr() {
    for name in FILES {
        assert!(is_copc(&copc_file(name)).expect("readable"), "{name}");
    }
    let dir = tempfile::tempdir().expect("tempdir");
    let plain = dir.path().join("plain.laz");
    crate::ingest::write_las(
        &plain,
        &crate::sample::sample_scene(100, 1),
        &crate::ingest::LasWriteOptions::default(),
    )
    .expect("write");
    assert!(!is_copc(&plain).expect("readable"));
    let short = dir.path().join("short.laz");
    std::fs::write(&short, b"LASF").expect("write");
    assert!(!is_copc(&short).expect("readable"));
}

#[test]
fn every_point_of_the_file_is_in_exactly_one_node() {
    for name in FILES {
        let path = copc_file(name);
        let whole = whole_file_points(&path);
        let nodes = node_points(&path);
        assert_eq!(nodes.len(), whole.len(), "{name}: points");
        assert!(nodes == whole, "{name}: the nodes hold the file's points");
    }
}

#[test]
fn a_hierarchy_in_two_pages_is_the_hierarchy_in_one() {
    let flat = open_copc(&copc_file("simple.copc.laz")).expect("opens");
    let paged = open_copc(&copc_file("simple_with_page.copc.laz")).expect("opens");
    assert_eq!((flat.pages, paged.pages), (1, 2));
    let counts = |d: &CopcDataset| -> Vec<(NodeKey, u32, u8)> {
        let nodes = d.dataset.hierarchy().nodes();
        nodes
            .iter()
            .map(|n| (n.key, n.point_count, n.child_mask))
            .collect()
    };
    assert_eq!(counts(&flat), counts(&paged));
    assert_eq!(flat.nodes, 65);
}

#[test]
fn inner_nodes_take_the_measured_root_spacing_halved_per_level() {
    let opened = open_copc(&copc_file("simple.copc.laz")).expect("opens");
    let hierarchy = opened.dataset.hierarchy();
    let spacing = opened.root_spacing;
    // This writer declares a spacing far finer than its root's points lie apart: adaptive
    // points sized by it would be single pixels.
    assert!(spacing > 10.0 * opened.info.spacing, "{spacing}");
    assert_eq!(hierarchy.spacing(NodeKey::ROOT), Some(spacing));
    let inner = hierarchy
        .nodes()
        .iter()
        .find(|n| n.key.level == 2 && !n.is_leaf())
        .expect("an inner node at level 2");
    assert_eq!(hierarchy.spacing(inner.key), Some(spacing / 4.0));
    let leaf = hierarchy
        .nodes()
        .iter()
        .find(|n| n.is_leaf())
        .expect("a leaf");
    assert_eq!(hierarchy.spacing(leaf.key), None);
    assert_eq!(hierarchy.cube, opened.info.cube());
}

// Damaged files.

/// Where the info VLR's data starts: after the 375-byte header and the VLR's 54-byte header.
pub(super) const INFO_AT: usize = 375 + 54;

/// What a daemon sends of a COPC file's header decodes its chunks as the file does, and
/// parts that cannot be a COPC file's are refused naming the file.
#[test]
fn a_decoder_sent_apart_from_the_file_decodes_its_chunks_as_the_file_does() {
    let opened = open_copc(&copc_file("simple_with_page.copc.laz")).expect("opens");
    let d = &opened.decoder;
    let name = Path::new("sent.copc.laz");
    let rebuild = |format: u8, record_len: u16, scale: [f64; 3], vlr: &[u8]| {
        CopcDecoder::from_parts(name, format, record_len, scale, d.offset(), vlr, None)
    };
    let weighed_at = |at: u16| {
        let (format, len) = (d.point_format(), d.record_len());
        CopcDecoder::from_parts(
            name,
            format,
            len,
            d.scale(),
            d.offset(),
            d.laszip_vlr(),
            Some(at),
        )
    };
    let sent = rebuild(d.point_format(), d.record_len(), d.scale(), d.laszip_vlr())
        .expect("the file's own parts");
    let hierarchy = opened.dataset.hierarchy();
    let records = opened.dataset.records();
    let stored: Vec<_> = hierarchy.stored_nodes().copied().collect();
    let chunks = records.read_records(&stored).expect("read");
    for (info, bytes) in stored.iter().zip(&chunks) {
        let here = records
            .decode(&hierarchy.cube, info, bytes)
            .expect("decodes");
        let there = sent
            .decode_chunk(&hierarchy.cube, info, bytes)
            .expect("decodes");
        assert_eq!(here, there, "node {}", info.key);
    }
    // A chunk of another node is an error naming the file, not other points.
    let error = sent
        .decode_chunk(&hierarchy.cube, &stored[1], &chunks[0])
        .expect_err("another node's chunk");
    assert!(error.to_string().contains("sent.copc.laz"), "{error}");

    let vlr = d.laszip_vlr();
    let refused = [
        rebuild(3, d.record_len(), d.scale(), vlr),
        rebuild(d.point_format(), 10, d.scale(), vlr),
        rebuild(d.point_format(), d.record_len() + 4, d.scale(), vlr),
        rebuild(d.point_format(), d.record_len(), [0.0, 0.01, 0.01], vlr),
        rebuild(
            d.point_format(),
            d.record_len(),
            [f64::NAN, 0.01, 0.01],
            vlr,
        ),
        rebuild(
            d.point_format(),
            d.record_len(),
            d.scale(),
            &vlr[..vlr.len() / 2],
        ),
        rebuild(d.point_format(), d.record_len(), d.scale(), &[]),
        // A weight must lie in the records' extra bytes, which this file's have none of.
        weighed_at(d.record_len() - 4),
        weighed_at(d.record_len()),
    ];
    for (case, result) in refused.into_iter().enumerate() {
        let error = result
            .err()
            .unwrap_or_else(|| panic!("case {case} accepted"));
        assert!(error.to_string().contains("sent.copc.laz"), "{error}");
    }
}

pub(super) fn u64_at(bytes: &[u8], at: usize) -> u64 {
    u64::from_le_bytes(bytes[at..at + 8].try_into().expect("8 bytes"))
}

/// The root page's offset and size.
pub(super) fn root_page(bytes: &[u8]) -> (usize, usize) {
    (
        u64_at(bytes, INFO_AT + 40) as usize,
        u64_at(bytes, INFO_AT + 48) as usize,
    )
}

/// Offsets of the entries of the page at `page` of `size` bytes.
pub(super) fn entries(page: usize, size: usize) -> impl Iterator<Item = usize> {
    (page..page + size).step_by(32)
}

pub(super) fn set_entry(bytes: &mut [u8], at: usize, offset: u64, byte_size: i32, count: i32) {
    bytes[at + 16..at + 24].copy_from_slice(&offset.to_le_bytes());
    bytes[at + 24..at + 28].copy_from_slice(&byte_size.to_le_bytes());
    bytes[at + 28..at + 32].copy_from_slice(&count.to_le_bytes());
}

pub(super) fn count_of(bytes: &[u8], at: usize) -> i32 {
    i32::from_le_bytes(bytes[at + 28..at + 32].try_into().expect("4 bytes"))
}

/// The byte size of the chunk or page the entry at `at` points to.
fn byte_size_of(bytes: &[u8], at: usize) -> i32 {
    i32::from_le_bytes(bytes[at + 24..at + 28].try_into().expect("4 bytes"))
}

/// The error opening `simple.copc.laz` with the point count of its root page's second entry
/// moved by `by`, so that the nodes no longer add up to the header's count.
fn miscounted(dir: &Path, by: i32) -> String {
    damaged(dir, "simple.copc.laz", |bytes| {
        let (page, _) = root_page(bytes);
        let at = page + 32;
        let (offset, size) = (u64_at(bytes, at + 16), byte_size_of(bytes, at));
        let count = count_of(bytes, at) + by;
        set_entry(bytes, at, offset, size, count);
    })
}

/// `name` changed by `damage`, written to `dir`, and the error opening it, which must name it.
fn damaged(dir: &Path, name: &str, damage: impl FnOnce(&mut Vec<u8>)) -> String {
    let mut bytes = std::fs::read(copc_file(name)).expect("read");
    damage(&mut bytes);
    let path = dir.join(format!("damaged-{name}"));
    std::fs::write(&path, &bytes).expect("write");
    let error = match open_copc(&path) {
        Ok(_) => panic!("{name}: the damage went unnoticed"),
        Err(error) => error.to_string(),
    };
    assert!(
        error.contains(&path.display().to_string()),
        "the error names the file: {error}"
    );
    error
}

#[test]
fn damaged_hierarchies_are_errors_naming_the_file() {
    let dir = tempfile::tempdir().expect("tempdir");
    let dir = dir.path();

    let beyond = damaged(dir, "simple.copc.laz", |bytes| {
        let (page, _) = root_page(bytes);
        let len = bytes.len() as u64;
        let count = count_of(bytes, page + 32);
        set_entry(bytes, page + 32, len + 100, 500, count);
    });
    assert!(beyond.contains("lies beyond the point data"), "{beyond}");

    let huge = damaged(dir, "simple.copc.laz", |bytes| {
        let (page, _) = root_page(bytes);
        let count = count_of(bytes, page + 32);
        set_entry(bytes, page + 32, 1000, i32::MAX, count);
    });
    assert!(huge.contains("lies beyond the point data"), "{huge}");

    let self_loop = damaged(dir, "simple.copc.laz", |bytes| {
        let (page, size) = root_page(bytes);
        set_entry(bytes, page + 64, page as u64, size as i32, -1);
    });
    assert!(self_loop.contains("the pages form a loop"), "{self_loop}");

    // The child page of the paged file pointing at itself.
    let child_loop = damaged(dir, "simple_with_page.copc.laz", |bytes| {
        let (page, size) = root_page(bytes);
        let link = entries(page, size)
            .find(|&at| count_of(bytes, at) == -1)
            .expect("a child page");
        let child = u64_at(bytes, link + 16);
        let child_size = byte_size_of(bytes, link);
        set_entry(bytes, child as usize, child, child_size, -1);
    });
    assert!(child_loop.contains("the pages form a loop"), "{child_loop}");

    let more = miscounted(dir, 1);
    assert!(
        more.contains("hold more points than the header's 1065"),
        "{more}"
    );

    let fewer = miscounted(dir, -1);
    assert!(fewer.contains("the header says 1065"), "{fewer}");

    // Two nodes' counts swapped: the sum holds, the chunks do not.
    let swapped = damaged(dir, "simple.copc.laz", |bytes| {
        let (page, size) = root_page(bytes);
        let mut with_points = entries(page, size).filter(|&at| count_of(bytes, at) > 0);
        let a = with_points.next().expect("a node");
        let b = with_points
            .find(|&at| count_of(bytes, at) != count_of(bytes, a))
            .expect("a node of another count");
        let (ca, cb) = (count_of(bytes, a), count_of(bytes, b));
        bytes[a + 28..a + 32].copy_from_slice(&cb.to_le_bytes());
        bytes[b + 28..b + 32].copy_from_slice(&ca.to_le_bytes());
    });
    assert!(swapped.contains("its chunk holds"), "{swapped}");

    let truncated = damaged(dir, "simple.copc.laz", |bytes| {
        bytes.truncate(bytes.len() / 2);
    });
    assert!(!truncated.is_empty());

    let bad_info = damaged(dir, "simple.copc.laz", |bytes| {
        bytes[INFO_AT + 24..INFO_AT + 32].copy_from_slice(&f64::NAN.to_le_bytes());
    });
    assert!(
        bad_info.contains("COPC info VLR: half size NaN"),
        "{bad_info}"
    );
}

#[test]
fn any_byte_of_the_hierarchy_flipped_opens_or_is_an_error_never_a_panic() {
    let dir = tempfile::tempdir().expect("tempdir");
    let original = std::fs::read(copc_file("simple_with_page.copc.laz")).expect("read");
    let (page, size) = root_page(&original);
    let path = dir.path().join("flipped.copc.laz");
    for at in (page..page + size).chain(INFO_AT..INFO_AT + 64) {
        let mut bytes = original.clone();
        bytes[at] ^= 0x80;
        std::fs::write(&path, &bytes).expect("write");
        match open_copc(&path) {
            Ok(opened) => assert_eq!(opened.dataset.point_count(), 1065),
            Err(error) => assert!(
                error.to_string().contains("flipped.copc.laz"),
                "byte {at}: {error}"
            ),
        }
    }
}

// On the GPU.

pub(super) fn frame_settings(bounds: &crate::cloud::WorldBounds) -> FrameSettings {
    let camera = Camera::auto(bounds, 4.0 / 3.0);
    let mut settings =
        FrameSettings::new(200, 150, camera).with_point_size(PointSize::Fixed(3), bounds, None);
    settings.shading = Shading::None;
    settings
}

/// A 200 by 150 view from `camera` with 2-pixel points at `lod_error` pixels and no budget:
/// the view the cut selection tests compare files by.
pub(super) fn small_view(camera: &Camera, origin: glam::DVec3, lod_error: f64) -> CutView<'_> {
    CutView {
        camera,
        origin,
        width: 200,
        height: 150,
        point_size: 2,
        lod_error,
        max_batches: usize::MAX,
        max_points: None,
        clip: None,
    }
}

/// A cut renderer of `dataset` refining to `lod_error` pixels, the one option these tests vary.
pub(super) fn cut_at(renderer: &Renderer, dataset: &LodDataset, lod_error: f64) -> CutRenderer {
    let options = CutOptions {
        lod_error,
        ..CutOptions::default()
    };
    CutRenderer::new(renderer, dataset, options).expect("cut renderer")
}

#[test]
fn every_node_drawn_is_the_file_read_whole() {
    let path = copc_file("simple.copc.laz");
    let opened = open_copc(&path).expect("opens");
    let cloud = load_point_cloud(&path).expect("the file read whole");
    assert_eq!(opened.dataset.origin(), cloud.origin, "one origin");
    let settings = frame_settings(&cloud.bounds);
    let mut renderer = Renderer::new(gpu());
    let mut cut = cut_at(&renderer, &opened.dataset, 0.0);
    for mode in [
        ColorMode::Rgb,
        ColorMode::Classification,
        ColorMode::Intensity,
        ColorMode::Elevation,
        ColorMode::ReturnNumber,
    ] {
        let (frame, report) = cut
            .render(
                &mut renderer,
                &opened.dataset,
                &settings,
                mode,
                &PointFilter::default(),
            )
            .expect("cut frame");
        assert_eq!(report.counts.points_rendered, 1065, "{mode:?}: every point");
        let mut whole = cloud.clone();
        whole.colors = crate::color::point_colors(&whole, mode.into());
        let mut resident_renderer = Renderer::new(gpu());
        let resident = resident_renderer.upload(&whole).expect("upload");
        let expected = resident_renderer
            .render(&resident, &settings)
            .expect("resident frame")
            .image;
        let name = format!("copc-{mode:?}").to_lowercase();
        let share = compare_images_within(&name, &frame.image, &expected, 8).equal_fraction();
        assert!(
            share >= 0.999,
            "{mode:?}: only {share:.4} of pixels within 8/255"
        );
    }
}

#[test]
fn a_coarse_cut_reads_only_the_nodes_it_draws() {
    let path = copc_file("simple.copc.laz");
    let opened = open_copc(&path).expect("opens");
    let file_len = std::fs::metadata(&path).expect("size").len();
    let chunk_bytes = opened.dataset.hierarchy().payload_bytes();
    let settings = frame_settings(&opened.dataset.bounds());
    let mut renderer = Renderer::new(gpu());
    let mut read = |lod_error: f64| {
        let mut cut = cut_at(&renderer, &opened.dataset, lod_error);
        let (_, report) = cut
            .render_rgb(&mut renderer, &opened.dataset, &settings)
            .expect("frame");
        report.counts
    };
    let every = read(0.0);
    assert_eq!((every.nodes_read, every.bytes_read), (65, chunk_bytes));
    // Its 1,065 points lie far apart: on a small frame they need a coarse error to be thinned.
    let coarse = read(32.0);
    assert!(coarse.nodes_read < every.nodes_read, "{coarse:?}");
    assert!(coarse.bytes_read < chunk_bytes / 2, "{coarse:?}");
    assert!(coarse.bytes_read < file_len);
    assert!(coarse.points_rendered < 1065);
}

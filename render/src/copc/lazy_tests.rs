//! Hierarchy pages read lazily: a frame's cut is the cut of the whole hierarchy, read a few
//! pages at a time, and a damaged child page fails the frame that reaches it, naming the file.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use super::tests::{
    copc_file, count_of, cut_at, entries, frame_settings, root_page, small_view, u64_at, INFO_AT,
};
use super::*;
use crate::camera::{Camera, Projection};
use crate::cut::{select_cut, CutRenderer, CutView};
use crate::raster::Renderer;
use crate::testing::{compare_images_within, gpu};

/// The file `path` opened reading the pages `reads` says, its color ranges from its coarsest
/// `sample_points` points.
fn open_at(path: &Path, reads: PageReads, sample_points: u64) -> Result<CopcDataset, CopcError> {
    open(CopcBytes::file(path)?, reads, sample_points)
}

/// A file opened for frames with only its root page read (its color ranges from the root
/// alone, so no child page is read for them), and the same file with every page read.
fn lazy_and_whole(path: &Path) -> (CopcDataset, CopcDataset) {
    let lazy = open_at(path, PageReads::AsNeeded, 1).expect("opens lazily");
    let whole = open_at(path, PageReads::All, 1).expect("opens whole");
    assert!(
        lazy.unread_pages > 0,
        "{}: pages left unread",
        path.display()
    );
    assert_eq!(lazy.pages, 1, "the root page alone");
    assert_eq!(whole.unread_pages, 0);
    (lazy, whole)
}

type RawEntry = [u8; 32];

fn entry_key(entry: &RawEntry) -> [i32; 4] {
    let at = |i: usize| i32::from_le_bytes(entry[i * 4..i * 4 + 4].try_into().expect("4"));
    [at(0), at(1), at(2), at(3)]
}

fn parent_of([level, x, y, z]: [i32; 4]) -> [i32; 4] {
    [level - 1, x / 2, y / 2, z / 2]
}

/// The COPC file `source`, whose hierarchy is one page, with every inner node below the root
/// given a page of its own (its entry, its leaf children's and links to its inner
/// children's pages), appended to the file: pages nested as deep as the tree.
fn repaged(source: &Path, dir: &Path) -> PathBuf {
    let mut bytes = std::fs::read(source).expect("read");
    let (page, size) = root_page(&bytes);
    let raw: Vec<RawEntry> = entries(page, size)
        .map(|at| bytes[at..at + 32].try_into().expect("32"))
        .collect();
    assert!(raw.iter().all(|e| count_of(e, 0) >= 0), "one page to start");
    let mut children: HashMap<[i32; 4], Vec<RawEntry>> = HashMap::new();
    let mut root = None;
    for entry in &raw {
        let key = entry_key(entry);
        if key[0] == 0 {
            root = Some(*entry);
        } else {
            children.entry(parent_of(key)).or_default().push(*entry);
        }
    }
    for list in children.values_mut() {
        list.sort_by_key(entry_key);
    }
    /// Appends the page of `node` to `out`, its inner children's pages first; returns where.
    fn write(
        node: &RawEntry,
        children: &HashMap<[i32; 4], Vec<RawEntry>>,
        out: &mut Vec<u8>,
    ) -> (u64, u64) {
        let mut page = vec![*node];
        for child in children.get(&entry_key(node)).into_iter().flatten() {
            if children.contains_key(&entry_key(child)) {
                let (offset, size) = write(child, children, out);
                let mut link = *child;
                link[16..24].copy_from_slice(&offset.to_le_bytes());
                link[24..28].copy_from_slice(&(size as i32).to_le_bytes());
                link[28..32].copy_from_slice(&(-1i32).to_le_bytes());
                page.push(link);
            } else {
                page.push(*child);
            }
        }
        let offset = out.len() as u64;
        out.extend(page.iter().flatten());
        (offset, page.len() as u64 * 32)
    }
    let (offset, size) = write(&root.expect("a root entry"), &children, &mut bytes);
    bytes[INFO_AT + 40..INFO_AT + 48].copy_from_slice(&offset.to_le_bytes());
    bytes[INFO_AT + 48..INFO_AT + 56].copy_from_slice(&size.to_le_bytes());
    let name = source.file_name().expect("a file").to_string_lossy();
    let path = dir.join(format!("repaged-{name}"));
    std::fs::write(&path, &bytes).expect("write");
    path
}

/// Cameras around and inside the file's bounds, each looking at another part of it.
fn cameras(bounds: &crate::cloud::WorldBounds) -> Vec<Camera> {
    let perspective = Projection::Perspective { fov_y_deg: 50.0 };
    let mut cameras = vec![Camera::auto(bounds, 4.0 / 3.0)];
    for (azimuth, elevation) in [(0.0, 10.0), (90.0, 45.0), (200.0, 80.0), (300.0, 20.0)] {
        cameras.push(Camera::framing(
            bounds,
            4.0 / 3.0,
            azimuth,
            elevation,
            perspective,
        ));
    }
    // Close to a corner, looking along the diagonal: near nodes fine, far ones coarse.
    let mut near = Camera::auto(bounds, 4.0 / 3.0);
    let size = bounds.max - bounds.min;
    near.position = bounds.min + size * 0.1;
    near.target = bounds.max;
    cameras.push(near);
    // Looking away from the cloud: nothing in view.
    let mut away = near;
    away.target = near.position - (bounds.max - near.position);
    cameras.push(away);
    cameras
}

/// For every view, coarse to fine, the cut of the file read lazily is the cut of every page.
fn check_cuts(path: &Path) {
    let (lazy, whole) = lazy_and_whole(path);
    let origin = lazy.dataset.origin();
    assert_eq!(origin, whole.dataset.origin());
    let bounds = lazy.dataset.bounds();
    let cameras = cameras(&bounds);
    let mut views = Vec::new();
    for lod_error in [1e9, 8.0, 2.0, 0.5, 0.0] {
        for camera in &cameras {
            for (max_batches, max_points) in [(usize::MAX, None), (2, None), (64, Some(300))] {
                views.push(CutView {
                    max_batches,
                    max_points,
                    ..small_view(camera, origin, lod_error)
                });
            }
        }
    }
    let name = path.display();
    let mut pages_read = Vec::new();
    for (i, view) in views.iter().enumerate() {
        let cut = lazy.dataset.select_cut(view).expect("lazy cut");
        let expected = select_cut(whole.dataset.hierarchy(), view);
        assert_eq!(cut, expected, "{name}: view {i}");
        pages_read.push(lazy.dataset.pages_read().pages);
    }
    // The root alone needs no child page; coarse views some; the finest views the rest.
    assert_eq!(pages_read[0], 0, "{name}: a cut of the root alone");
    let all = (whole.pages - lazy.pages) as u64;
    if all > 1 {
        assert!(
            pages_read.iter().any(|&read| read > 0 && read < all),
            "{name}: a coarse view reads part of the pages: {pages_read:?}"
        );
    }
    let unread = lazy.dataset.current_hierarchy().unread_pages().len();
    assert_eq!(
        lazy.pages + pages_read.last().copied().unwrap_or(0) as usize + unread,
        whole.pages,
        "{name}: each page read once"
    );
    assert!(pages_read.last() > Some(&0), "{name}: pages read by frames");
    if unread == 0 {
        assert_eq!(
            lazy.dataset.current_hierarchy().nodes(),
            whole.dataset.hierarchy().nodes(),
            "{name}: every page read is the whole hierarchy"
        );
    }
}

/// A generated terrain built into a store with small leaves and exported as a COPC file (in
/// one page, as the export writes it).
fn exported_terrain(dir: &Path) -> PathBuf {
    crate::testing::exported_terrain(dir, 60_000, 1_000).path
}

#[test]
fn a_cut_read_lazily_is_the_cut_of_every_page() {
    check_cuts(&copc_file("simple_with_page.copc.laz"));
    let dir = tempfile::tempdir().expect("tempdir");
    let sources = [copc_file("simple.copc.laz"), exported_terrain(dir.path())];
    for source in sources {
        let path = repaged(&source, dir.path());
        let whole = describe(&path).expect("a consistent file");
        let name = path.display();
        assert!(whole.pages > 2, "{name}: {} pages", whole.pages);
        assert_eq!(whole.nodes, describe(&source).expect("the source").nodes);
        check_cuts(&path);
    }
}

/// Adaptive points are made for one spacing whichever pages are read: the coarse sample's,
/// close to what the whole hierarchy's leaves say (the leaves known with the root page alone
/// are its page links' coarse nodes).
#[test]
fn a_file_read_lazily_has_the_spacing_of_the_whole_file() {
    let dir = tempfile::tempdir().expect("tempdir");
    let path = repaged(&exported_terrain(dir.path()), dir.path());
    let lazy = open_at(&path, PageReads::AsNeeded, 4_000).expect("opens lazily");
    let whole = open_at(&path, PageReads::All, 4_000).expect("opens whole");
    assert!(lazy.unread_pages > 0, "pages left unread");
    let spacing = lazy.dataset.point_spacing().expect("a spacing");
    assert_eq!(whole.dataset.point_spacing(), Some(spacing));
    let leaves = whole.dataset.hierarchy().point_spacing().expect("leaves");
    assert!(
        (0.7..1.5).contains(&(spacing / leaves)),
        "sample {spacing}, leaves {leaves}"
    );
}

#[test]
fn frames_read_the_pages_they_reach_once_and_draw_what_the_whole_file_draws() {
    let dir = tempfile::tempdir().expect("tempdir");
    let path = repaged(&copc_file("simple.copc.laz"), dir.path());
    let (lazy, whole) = lazy_and_whole(&path);
    let settings = frame_settings(&lazy.dataset.bounds());
    let mut renderer = Renderer::new(gpu());
    let mut frame = |opened: &CopcDataset| {
        let mut cut = cut_at(&renderer, &opened.dataset, 0.0);
        let render = |cut: &mut CutRenderer, renderer: &mut Renderer| {
            cut.render_rgb(renderer, &opened.dataset, &settings)
                .expect("frame")
        };
        let first = render(&mut cut, &mut renderer);
        let again = render(&mut cut, &mut renderer);
        (first, again)
    };
    let ((lazy_frame, first), (_, again)) = frame(&lazy);
    let ((whole_frame, whole_report), _) = frame(&whole);
    assert_eq!(first.counts, whole_report.counts, "one cut");
    assert_eq!(first.counts.points_total, 1065, "the header's count");
    assert_eq!(
        first.hierarchy_pages_read as usize,
        whole.pages - lazy.pages,
        "every page is in view"
    );
    assert!(first.hierarchy_page_bytes > 0);
    assert_eq!(again.hierarchy_pages_read, 0, "read once");
    assert_eq!(whole_report.hierarchy_pages_read, 0);
    let share = compare_images_within("copc-lazy", &lazy_frame.image, &whole_frame.image, 0)
        .equal_fraction();
    assert_eq!(share, 1.0, "the same image");
}

/// The paged file with its child page changed by `damage` (given the file's bytes, the child
/// page's offset and the offset of the root page's entry linking to it), written to `dir`.
fn damaged_child_page(dir: &Path, damage: impl FnOnce(&mut Vec<u8>, usize, usize)) -> PathBuf {
    let mut bytes = std::fs::read(copc_file("simple_with_page.copc.laz")).expect("read");
    let (page, size) = root_page(&bytes);
    let link = entries(page, size)
        .find(|&at| count_of(&bytes, at) == -1)
        .expect("a child page");
    let child = u64_at(&bytes, link + 16) as usize;
    damage(&mut bytes, child, link);
    let path = dir.join("damaged-child-page.copc.laz");
    std::fs::write(&path, &bytes).expect("write");
    path
}

/// The first entry with points of the page at `page`.
fn first_with_points(bytes: &[u8], page: usize) -> usize {
    (page..bytes.len() - 32)
        .step_by(32)
        .find(|&at| count_of(bytes, at) > 0)
        .expect("an entry with points")
}

#[test]
fn a_damaged_child_page_read_lazily_fails_the_frame_naming_the_file() {
    let dir = tempfile::tempdir().expect("tempdir");
    let dir = dir.path();
    let more_points = |bytes: &mut Vec<u8>, child: usize, _| {
        let at = first_with_points(bytes, child);
        let count = count_of(bytes, at) + 1;
        bytes[at + 28..at + 32].copy_from_slice(&count.to_le_bytes());
    };
    let beyond = |bytes: &mut Vec<u8>, child: usize, _| {
        let at = first_with_points(bytes, child);
        let len = bytes.len() as u64;
        bytes[at + 16..at + 24].copy_from_slice(&(len + 100).to_le_bytes());
    };
    let outside = |bytes: &mut Vec<u8>, child: usize, link: usize| {
        // The page's first entry moved to its node's neighbour along x, outside its subtree.
        let mut key: RawEntry = bytes[link..link + 32].try_into().expect("32");
        let [level, x, y, z] = entry_key(&key);
        for (i, v) in [level, x ^ 1, y, z].into_iter().enumerate() {
            key[4 * i..4 * i + 4].copy_from_slice(&v.to_le_bytes());
        }
        bytes[child..child + 16].copy_from_slice(&key[..16]);
    };
    let looped = |bytes: &mut Vec<u8>, child: usize, _| {
        // An entry with points turned into a link back to the root page.
        let (root, size) = root_page(bytes);
        let at = first_with_points(bytes, child);
        bytes[at + 16..at + 24].copy_from_slice(&(root as u64).to_le_bytes());
        bytes[at + 24..at + 28].copy_from_slice(&(size as i32).to_le_bytes());
        bytes[at + 28..at + 32].copy_from_slice(&(-1i32).to_le_bytes());
    };
    // Each damage, what the error says, and the pages merged before it (the child page
    // whose link is damaged is whole).
    for (case, damage, reason, merged) in [
        (
            "more points",
            &more_points as &dyn Fn(&mut Vec<u8>, usize, usize),
            "hold more points than the header's 1065",
            0,
        ),
        (
            "a chunk beyond the file",
            &beyond,
            "lies beyond the point data",
            0,
        ),
        (
            "an entry outside its subtree",
            &outside,
            "outside the subtree",
            0,
        ),
        (
            "a page linking to the root",
            &looped,
            "the pages form a loop",
            1,
        ),
    ] {
        let path = damaged_child_page(dir, damage);
        let name = path.display().to_string();
        let lazy = open_at(&path, PageReads::AsNeeded, 1).expect("the root page is whole");
        let eager = describe(&path).expect_err("every page read").to_string();
        assert!(
            eager.contains(&name) && eager.contains(reason),
            "{case}: {eager}"
        );
        let settings = frame_settings(&lazy.dataset.bounds());
        let mut renderer = Renderer::new(gpu());
        let mut cut = cut_at(&renderer, &lazy.dataset, 0.0);
        for attempt in 0..2 {
            let error = cut
                .render_rgb(&mut renderer, &lazy.dataset, &settings)
                .err()
                .unwrap_or_else(|| panic!("{case}: the damaged page went unnoticed"))
                .to_string();
            assert!(
                error.contains(&name) && error.contains(reason),
                "{case}, attempt {attempt}: {error}"
            );
        }
        assert_eq!(
            lazy.dataset.pages_read().pages,
            merged,
            "{case}: pages merged"
        );
    }
}

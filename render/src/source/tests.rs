//! A frame source renders the same frames however its points come, says what it drew, and
//! builds a damaged store of this machine again without losing the frame.

use std::cell::RefCell;
use std::sync::Arc;

use super::*;
use crate::ingest::{write_las, LasWriteOptions};
use crate::request::{CameraPath, Lens, Turntable};
use crate::testing::gpu;

const FRAMES: u32 = 3;

/// The events a source tells, each as its debug line.
#[derive(Default)]
pub(in crate::source) struct Told(RefCell<Vec<String>>);

impl Told {
    pub(in crate::source) fn tell(&self, event: SourceEvent<'_>) {
        self.0.borrow_mut().push(format!("{event:?}"));
    }

    /// How many lines start with `kind` (an event's name).
    pub(in crate::source) fn count(&self, kind: &str) -> usize {
        self.0
            .borrow()
            .iter()
            .filter(|l| l.starts_with(kind))
            .count()
    }

    pub(in crate::source) fn lines(&self) -> String {
        self.0.borrow().join("\n")
    }
}

/// A turntable of `FRAMES` small frames with `options`.
fn request(options: RenderOptions) -> RenderRequest {
    RenderRequest {
        width: 96,
        height: 72,
        camera_path: CameraPath::Turntable(Turntable::around_the_cloud(FRAMES)),
        lens: Lens::default(),
        render: options,
    }
}

/// A dataset of `points` in a LAS file of `dir`.
fn dataset(dir: &Path, points: usize) -> Vec<PathBuf> {
    let file = dir.join("scene.las");
    let scene = crate::sample::sample_scene(points, 7);
    write_las(&file, &scene, &LasWriteOptions::default()).expect("write");
    vec![file]
}

fn images(frames: &[SourceFrame]) -> Vec<image::RgbaImage> {
    frames.iter().map(|f| f.frame.image.clone()).collect()
}

fn cut_options(lod_error: f64) -> CutOptions {
    CutOptions {
        lod_error,
        ..CutOptions::default()
    }
}

/// Flips bits of every 61st byte of the payload of the store in `folder`: its checks fail.
pub(in crate::source) fn damage_payload(folder: &Path) {
    let payload = folder.join("nodes.bin");
    let mut bytes = std::fs::read(&payload).expect("payload");
    for byte in bytes.iter_mut().step_by(61) {
        *byte ^= 0x33;
    }
    std::fs::write(&payload, bytes).expect("damage");
}

/// A scratch folder holding a dataset of a generated scene, the turntable that renders it
/// with the default options, and the folder of its store.
struct Scene {
    files: Vec<PathBuf>,
    request: RenderRequest,
    store: PathBuf,
    _dir: tempfile::TempDir,
}

impl Scene {
    /// A scene of `points` in one LAS file.
    fn new(points: usize) -> Self {
        let dir = tempfile::tempdir().expect("tempdir");
        Self {
            files: dataset(dir.path(), points),
            request: request(RenderOptions::default()),
            store: dir.path().join("store"),
            _dir: dir,
        }
    }

    /// The scene's store, built when missing, cut at `lod_error` for its turntable.
    fn open_store(&self, renderer: Renderer, lod_error: f64) -> FrameSource {
        FrameSource::local_store(
            renderer,
            &self.files,
            &self.store,
            None,
            cut_options(lod_error),
            &self.request.render,
            &quiet,
        )
        .expect("the store")
    }

    /// Every frame of the scene's turntable from `source`.
    fn frames(&self, source: &mut FrameSource) -> Vec<SourceFrame> {
        let request = &self.request;
        (0..request.frames())
            .map(|index| {
                let settings = source.frame_settings(request, index);
                let frame = source.render(&settings, &quiet).expect("a frame");
                if index + 1 < request.frames() {
                    source.read_ahead(&source.frame_settings(request, index + 1));
                }
                frame
            })
            .collect()
    }
}

#[test]
fn a_store_and_its_records_served_from_elsewhere_give_the_same_frames() {
    let scene = Scene::new(40_000);
    let mut local = scene.open_store(Renderer::new(gpu()), 1.0);
    assert_eq!(local.frame_points(), FramePoints::StoreCut);
    let here = scene.frames(&mut local);
    assert!(here[0].opened.and_then(|o| o.build_ms).is_some(), "built");
    assert!(here[1].opened.is_none(), "told once");

    // The same records through the `NodeRecords` a daemon's store is read through.
    let Points::Cut { levels, .. } = &local.points else {
        panic!("a cut")
    };
    let stored = levels.dataset();
    let dataset = LodDataset::with_records(
        Arc::clone(stored.records()),
        stored.hierarchy().clone(),
        stored.bounds(),
    )
    .expect("served");
    let served = Levels::Served {
        dataset: Box::new(dataset),
        build_ms: Some(12.0),
    };
    let mut served = FrameSource::levels(
        Renderer::new(gpu()),
        served,
        cut_options(1.0),
        &scene.request.render,
        &quiet,
    )
    .expect("served");
    let there = scene.frames(&mut served);
    assert_eq!(there[0].opened.and_then(|o| o.build_ms), Some(12.0));
    assert_eq!(images(&here), images(&there), "pixel for pixel");
    for (a, b) in here.iter().zip(&there) {
        assert_eq!(a.points_rendered, b.points_rendered);
        assert_eq!(a.points_total, 40_000);
        assert!(a.cut.is_some() && a.preview.is_none());
    }
}

#[test]
fn coarse_cuts_are_previews_that_say_how_complete_they_are() {
    let scene = Scene::new(400_000);
    let mut source = scene.open_store(Renderer::new(gpu()), 0.5);
    let finals = images(&scene.frames(&mut source));
    assert!(source.preview_cuts(true).expect("coarse"));
    assert!(source.is_preview());
    let previews = scene.frames(&mut source);
    for frame in &previews {
        let completeness = frame.preview.expect("a preview");
        assert!(completeness > 0.0 && completeness < 1.0, "{completeness}");
        assert!(frame.points_rendered < frame.points_total);
    }
    assert!(!source.preview_cuts(false).expect("final"));
    assert_eq!(images(&scene.frames(&mut source)), finals);

    // A final error coarser than a preview's leaves nothing to preview.
    let mut coarse = scene.open_store(source.into_renderer(), PREVIEW_LOD_ERROR_PX * 2.0);
    assert!(!coarse.preview_cuts(true).expect("no coarser cut"));
}

#[test]
fn a_preview_frames_the_files_and_counts_the_dataset() {
    let scene = Scene::new(120_000);
    let chunk_starts = ChunkStarts::read(&scene.files).expect("chunk starts");
    let told = Told::default();
    let events = |event: SourceEvent<'_>| told.tell(event);
    let mut preview = FrameSource::preview(
        Renderer::new(gpu()),
        chunk_starts.with_nodes(&[]),
        &scene.request.render,
        &events,
    )
    .expect("a preview");
    assert!(preview.is_preview());
    // Framed as the frames of the files' store are, though only a few of their points are
    // drawn.
    let store = scene.open_store(Renderer::new(gpu()), 1.0);
    assert_eq!(preview.bounds().all, store.bounds().all);
    for frame in scene.frames(&mut preview) {
        assert_eq!(frame.points_total, 120_000);
        let completeness = frame.preview.expect("a preview");
        assert!(completeness > 0.0 && completeness < 0.1, "{completeness}");
    }
    assert!(told.lines().starts_with("Preview"), "{}", told.lines());
}

#[test]
fn a_resident_source_is_reused_only_for_its_own_colors_and_filter() {
    let dir = tempfile::tempdir().expect("tempdir");
    let files = dataset(dir.path(), 5_000);
    let options = RenderOptions::default();
    let told = Told::default();
    let events = |event: SourceEvent<'_>| told.tell(event);
    let mut source =
        FrameSource::resident(Renderer::new(gpu()), &files, None, &options, &events).expect("read");
    assert_eq!(source.frame_points(), FramePoints::Resident);
    assert!(told.lines().starts_with("Reading"), "{}", told.lines());
    assert_eq!(told.count("Read "), 1, "{}", told.lines());
    assert!(source.reuse_for(&options, None));
    let mut other = options;
    other.color_mode = crate::color::ColorMode::Elevation;
    assert!(!source.reuse_for(&other, None));
    let frame = source
        .render(&source.frame_settings(&request(options), 0), &quiet)
        .expect("a frame");
    let opened = frame.opened.expect("told with the first frame");
    assert!(opened.load_ms.is_some() && opened.cache.is_none());
    assert_eq!(frame.points_total, 5_000);
}

#[test]
fn a_store_damaged_between_frames_is_built_again_and_the_frame_drawn() {
    let scene = Scene::new(40_000);
    let mut source = scene.open_store(Renderer::new(gpu()), 1.0);
    let before = images(&scene.frames(&mut source));
    let mut source = scene.open_store(source.into_renderer(), 1.0);
    damage_payload(&scene.store);
    let told = Told::default();
    let events = |event: SourceEvent<'_>| told.tell(event);
    let settings = source.frame_settings(&scene.request, 0);
    let frame = source.render(&settings, &events).expect("built again");
    assert_eq!(frame.frame.image, before[0]);
    assert_eq!(told.count("Rebuilding"), 1, "{}", told.lines());
}

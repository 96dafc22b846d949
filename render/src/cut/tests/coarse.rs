//! Nodes a frame draws at most 1,024 pixels wide are read coarse (positions to 20 bits a side,
//! colors, weights): two thirds of their bytes, and the same image whether the caches held
//! them whole.

use super::*;

/// The fixture, renderer and settings that every frame of these tests shares.
struct Scene {
    fixture: Fixture,
    renderer: Renderer,
    settings: FrameSettings,
}

impl Scene {
    fn new(points: usize) -> Self {
        let (fixture, renderer, settings) = basic_frame(points);
        Self {
            fixture,
            renderer,
            settings,
        }
    }

    /// A new cut renderer at `lod_error`, its caches cold.
    fn cut(&self, lod_error: f64) -> CutRenderer {
        cut_renderer(&self.renderer, &self.fixture, lod_error)
    }

    /// A frame by `cut` in `mode`, every point kept.
    fn frame(&mut self, cut: &mut CutRenderer, mode: ColorMode) -> (Frame, CutReport) {
        let filter = PointFilter::default();
        let dataset = &self.fixture.dataset;
        cut.render(&mut self.renderer, dataset, &self.settings, mode, &filter)
            .expect("frame")
    }
}

/// A cold RGB frame at the default pixel error reads the coarse sections of the nodes it draws
/// small, far fewer bytes than the intensity frame of the same cut, which reads every record
/// whole. Drawn again after that intensity frame, from the whole records it left in the host
/// cache, the RGB frame reads nothing and is the same image. At pixel error 0 every record is
/// read whole.
#[test]
fn nodes_drawn_small_are_read_coarse_and_drawn_alike_from_whole_records() {
    let mut scene = Scene::new(120_000);
    let mut cold = scene.cut(DEFAULT_LOD_ERROR_PX);
    let (cold_frame, coarse) = scene.frame(&mut cold, ColorMode::Rgb);

    let mut cut = scene.cut(DEFAULT_LOD_ERROR_PX);
    let (_, whole) = scene.frame(&mut cut, ColorMode::Intensity);
    assert_eq!(
        coarse.counts.nodes_read, whole.counts.nodes_read,
        "the same cut"
    );
    let share = coarse.counts.bytes_read as f64 / whole.counts.bytes_read as f64;
    eprintln!(
        "{} nodes: {} bytes read coarse, {} whole ({share:.3})",
        coarse.counts.nodes_read, coarse.counts.bytes_read, whole.counts.bytes_read
    );
    assert!(share < 0.7, "{share:.3} of the whole records' bytes");

    let (warm_frame, warm) = scene.frame(&mut cut, ColorMode::Rgb);
    assert_eq!(warm.counts.nodes_read, 0, "{warm:?}");
    assert_eq!(
        compare_images_within("coarse-from-whole", &warm_frame.image, &cold_frame.image, 0)
            .differing,
        0,
        "drawn from whole records, the frame differs from the cold one"
    );

    let (_, rgb) = scene.frame(&mut scene.cut(0.0), ColorMode::Rgb);
    let (_, intensity) = scene.frame(&mut scene.cut(0.0), ColorMode::Intensity);
    assert_eq!(
        rgb.counts.bytes_read, intensity.counts.bytes_read,
        "every record whole at 0"
    );
}

//! The automatic camera frames the points, not their header's box: real scans, the COPC files
//! of other writers, every file of laspy's tests and a generated cloud with a few far stray
//! points, rendered with the default options at 320x180 through the frame source as
//! `pointfarm render` and the workers render them. From the image alone: the drawn pixels' box
//! fills at least 80% of the frame along the side that limits it and is centred within 6%;
//! enough of the frame is lit for adaptive points to close the surface (for laspy's files of a
//! few points, to show them); over a turntable of 8 frames the widest fills 80%, every frame
//! is centred within the same 6% as a still, and none touches the image's border.

use std::path::{Path, PathBuf};

use image::RgbaImage;
use pointfarm_render::cut::CutOptions;
use pointfarm_render::raster::Renderer;
use pointfarm_render::request::{
    CameraPath, Lens, RenderOptions, RenderRequest, StillCamera, Turntable,
};
use pointfarm_render::source::{quiet, FrameSource};
use pointfarm_tests::service::gpu;
use pointfarm_tests::{copc_file, shared_data};

const WIDTH: u32 = 320;
const HEIGHT: u32 = 180;
const TURNTABLE_FRAMES: u32 = 8;
/// The share of the frame the drawn box spans along its fuller side, at least.
const MIN_FILL: f64 = 0.8;
/// How far the drawn box's centre may lie from the frame's, as a share of each side.
const MAX_OFF_CENTRE: f64 = 0.06;
/// The share of the frame the still of a file of a few points lights, at least: enough for its
/// points to show (laspy's file of 4 points lights 0.7%).
const MIN_LIT_OF_FEW_POINTS: f64 = 0.005;

/// Where a frame's drawn pixels lie.
#[derive(Debug, Clone, Copy)]
struct Figures {
    /// Inclusive pixel box of the pixels that are not the background.
    x0: u32,
    y0: u32,
    x1: u32,
    y1: u32,
    drawn: u64,
}

impl Figures {
    fn of(image: &RgbaImage, background: [u8; 4]) -> Option<Figures> {
        let mut found: Option<Figures> = None;
        for (x, y, pixel) in image.enumerate_pixels() {
            if pixel.0 == background {
                continue;
            }
            let f = found.get_or_insert(Figures {
                x0: x,
                y0: y,
                x1: x,
                y1: y,
                drawn: 0,
            });
            f.x0 = f.x0.min(x);
            f.x1 = f.x1.max(x);
            f.y0 = f.y0.min(y);
            f.y1 = f.y1.max(y);
            f.drawn += 1;
        }
        found
    }

    /// The box's span as shares of the frame's width and height.
    fn span(&self) -> (f64, f64) {
        (
            f64::from(self.x1 - self.x0 + 1) / f64::from(WIDTH),
            f64::from(self.y1 - self.y0 + 1) / f64::from(HEIGHT),
        )
    }

    /// The span along the side the subject fills most.
    fn fill(&self) -> f64 {
        let (x, y) = self.span();
        x.max(y)
    }

    /// The box's centre as shares of the width and height, from the top left.
    fn centre(&self) -> (f64, f64) {
        (
            f64::from(self.x0 + self.x1 + 1) / 2.0 / f64::from(WIDTH),
            f64::from(self.y0 + self.y1 + 1) / 2.0 / f64::from(HEIGHT),
        )
    }

    /// Drawn pixels over the frame's.
    fn lit(&self) -> f64 {
        self.drawn as f64 / f64::from(WIDTH * HEIGHT)
    }

    fn touches_border(&self) -> bool {
        self.room() == 0
    }

    /// Background pixels between the box and the nearest side of the frame.
    fn room(&self) -> u32 {
        self.x0
            .min(self.y0)
            .min(WIDTH - 1 - self.x1)
            .min(HEIGHT - 1 - self.y1)
    }
}

fn request(camera_path: CameraPath) -> RenderRequest {
    RenderRequest {
        width: WIDTH,
        height: HEIGHT,
        camera_path,
        lens: Lens::default(),
        render: RenderOptions::default(),
    }
}

/// The frame source `pointfarm render` opens for `file` with default options: a COPC file cut
/// from its own hierarchy, anything else resident.
fn open(renderer: Renderer, file: &Path, options: &RenderOptions) -> FrameSource {
    open_as(
        renderer,
        file,
        options,
        file.to_string_lossy().ends_with(".copc.laz"),
    )
}

/// The frame source of `file`, cut from its COPC hierarchy when `copc` says so, else resident.
fn open_as(renderer: Renderer, file: &Path, options: &RenderOptions, copc: bool) -> FrameSource {
    let source = if copc {
        FrameSource::copc(renderer, file, CutOptions::default(), options, &quiet)
    } else {
        FrameSource::resident(renderer, &[file.to_path_buf()], None, options, &quiet)
    };
    source.unwrap_or_else(|e| panic!("{}: {e}", file.display()))
}

/// The figures of every frame of `request` from `file`.
fn figures(renderer: Renderer, file: &Path, request: &RenderRequest) -> (Vec<Figures>, Renderer) {
    let mut source = open(renderer, file, &request.render);
    let figures = (0..request.frames())
        .map(|index| {
            let settings = source.frame_settings(request, index);
            let frame = source.render(&settings, &quiet).expect("a frame");
            Figures::of(&frame.frame.image, request.render.background)
                .unwrap_or_else(|| panic!("{}: frame {index} is empty", file.display()))
        })
        .collect();
    (figures, source.into_renderer())
}

/// Adds `what` to `failures` unless `ok`.
fn expect(failures: &mut Vec<String>, ok: bool, what: String) {
    if !ok {
        failures.push(what);
    }
}

/// Checks the still of `file`, which must light at least `min_lit` of the frame; adds what
/// fails to `failures`.
fn check_still(
    renderer: Renderer,
    file: &Path,
    min_lit: f64,
    failures: &mut Vec<String>,
) -> Renderer {
    let name = file.file_name().expect("a name").to_string_lossy();
    let mut expect = |ok: bool, what: String| expect(failures, ok, what);
    let still = request(CameraPath::Still(StillCamera::default()));
    let (figures_of_still, renderer) = figures(renderer, file, &still);
    let f = figures_of_still[0];
    let ((w, h), (cx, cy)) = (f.span(), f.centre());
    eprintln!(
        "{name}: still box {:.0}% x {:.0}%, centre {:.0}%, {:.0}%, lit {:.1}%",
        w * 100.0,
        h * 100.0,
        cx * 100.0,
        cy * 100.0,
        f.lit() * 100.0
    );
    expect(
        f.fill() >= MIN_FILL,
        format!("{name}: the still fills {:.3}", f.fill()),
    );
    expect(
        (cx - 0.5).abs() <= MAX_OFF_CENTRE && (cy - 0.5).abs() <= MAX_OFF_CENTRE,
        format!("{name}: the still's subject is centred at ({cx:.3}, {cy:.3})"),
    );
    expect(
        f.lit() >= min_lit,
        format!("{name}: the still lights {:.4}", f.lit()),
    );
    renderer
}

/// Checks the still and the turntable of `file`, whose still must light at least `min_lit` of
/// the frame; adds what fails to `failures`.
fn check(renderer: Renderer, file: &Path, min_lit: f64, failures: &mut Vec<String>) -> Renderer {
    let renderer = check_still(renderer, file, min_lit, failures);
    let name = file.file_name().expect("a name").to_string_lossy();
    let mut expect = |ok: bool, what: String| expect(failures, ok, what);
    let turntable = request(CameraPath::Turntable(Turntable::around_the_cloud(
        TURNTABLE_FRAMES,
    )));
    let (frames, renderer) = figures(renderer, file, &turntable);
    let widest = frames.iter().map(Figures::fill).fold(0.0, f64::max);
    let off_centre = |f: &Figures| {
        let (cx, cy) = f.centre();
        (cx - 0.5).abs().max((cy - 0.5).abs())
    };
    let farthest = frames.iter().map(off_centre).fold(0.0, f64::max);
    let nearest = frames.iter().map(Figures::room).min().unwrap_or(0);
    eprintln!(
        "{name}: turntable widest {:.0}%, centres at most {:.1}% off, {nearest} px from the border",
        widest * 100.0,
        farthest * 100.0
    );
    expect(
        widest >= MIN_FILL,
        format!("{name}: the turntable's widest frame fills {widest:.3}"),
    );
    for (index, f) in frames.iter().enumerate() {
        expect(
            !f.touches_border(),
            format!("{name}: turntable frame {index} is cut: {f:?}"),
        );
        expect(
            off_centre(f) <= MAX_OFF_CENTRE,
            format!(
                "{name}: turntable frame {index} is centred at {:?}",
                f.centre()
            ),
        );
    }
    renderer
}

#[test]
fn real_scans_are_framed_by_their_points() {
    let mut renderer = Renderer::new(gpu());
    let mut failures = Vec::new();
    for (file, min_lit) in [("autzen_trim.laz", 0.15), ("lone-star.laz", 0.1)] {
        let Some(path) = shared_data(file) else {
            continue;
        };
        renderer = check(renderer, &path, min_lit, &mut failures);
    }
    assert!(failures.is_empty(), "{failures:#?}");
}

#[test]
fn copc_files_of_other_writers_are_framed_and_sized_as_their_points() {
    let mut renderer = Renderer::new(gpu());
    let mut failures = Vec::new();
    let still = request(CameraPath::Still(StillCamera::default()));
    for file in [
        "autzen.copc.laz",
        "simple.copc.laz",
        "simple_with_page.copc.laz",
    ] {
        let path = copc_file(file);
        // The same points read whole, as a plain LAZ file: the cut's points, sized by the
        // spacing measured as the resident cloud's is, must light about as much of the frame.
        let mut lit = [0.0; 2];
        for (copc, lit) in [false, true].into_iter().zip(&mut lit) {
            let mut source = open_as(renderer, &path, &still.render, copc);
            let settings = source.frame_settings(&still, 0);
            let frame = source.render(&settings, &quiet).expect("a frame");
            *lit = Figures::of(&frame.frame.image, still.render.background)
                .expect("drawn")
                .lit();
            renderer = source.into_renderer();
        }
        let [whole, cut] = lit;
        eprintln!("{file}: read whole lights {whole:.4}, cut {cut:.4}");
        if cut < 0.85 * whole {
            failures.push(format!(
                "{file}: its cut lights {cut:.4}, read whole {whole:.4}"
            ));
        }
        renderer = check(renderer, &path, 0.08, &mut failures);
    }
    assert!(failures.is_empty(), "{failures:#?}");
}

/// The LAS and LAZ files of `folder`, by name.
fn point_files(folder: &Path) -> Vec<PathBuf> {
    let entries =
        std::fs::read_dir(folder).unwrap_or_else(|e| panic!("reading {}: {e}", folder.display()));
    let mut files: Vec<PathBuf> = entries
        .map(|entry| entry.expect("a folder entry").path())
        .filter(|path| {
            path.extension().is_some_and(|ext| {
                ext.eq_ignore_ascii_case("las") || ext.eq_ignore_ascii_case("laz")
            })
        })
        .collect();
    files.sort();
    files
}

/// Every file of laspy's tests, as `deploy/test.sh` fetches them into `$POINTFARM_LASPY_DATA`
/// from laspy's source distribution: files of a few points, old versions and point formats,
/// COPC, extra bytes, a file with stray points far from two clusters. Their stills and
/// turntables are held to what the gallery measures of its default renders (docs/gallery.md).
#[test]
fn laspy_test_files_are_framed_by_their_points() {
    let Some(folder) = std::env::var_os("POINTFARM_LASPY_DATA") else {
        eprintln!(
            "skipping: POINTFARM_LASPY_DATA names no folder of laspy's test files \
             (bash deploy/test.sh fetches them)"
        );
        return;
    };
    let files = point_files(Path::new(&folder));
    assert!(
        !files.is_empty(),
        "{}: no .las or .laz file",
        Path::new(&folder).display()
    );
    let mut renderer = Renderer::new(gpu());
    let mut failures = Vec::new();
    for file in &files {
        renderer = check(renderer, file, MIN_LIT_OF_FEW_POINTS, &mut failures);
    }
    assert!(failures.is_empty(), "{failures:#?}");
}

#[test]
fn a_few_far_stray_points_do_not_move_the_camera() {
    let dir = tempfile::tempdir().expect("tempdir");
    let file = dir.path().join("strays.las");
    // A 200 x 100 m hillside, points 0.5 m apart, and five points hundreds of metres off it.
    let origin = [512_000.0, 5_430_000.0, 300.0];
    let mut points: Vec<[f64; 3]> = (0..400 * 200)
        .map(|i| {
            let (x, y) = (f64::from(i % 400) * 0.5, f64::from(i / 400) * 0.5);
            [x, y, 8.0 * (x / 30.0).sin() + 0.05 * y]
        })
        .collect();
    points.extend([
        [4_000.0, 50.0, 0.0],
        [-2_500.0, -3_000.0, 40.0],
        [100.0, 50.0, 1_500.0],
        [100.0, 900.0, -600.0],
        [-700.0, 60.0, 10.0],
    ]);
    let mut builder = las::Builder::from((1, 2));
    builder.point_format = las::point::Format::new(2).expect("format 2");
    let axis = |offset: f64| las::Transform {
        scale: 0.01,
        offset,
    };
    builder.transforms = las::Vector {
        x: axis(origin[0]),
        y: axis(origin[1]),
        z: axis(origin[2]),
    };
    let header = builder.into_header().expect("header");
    let mut writer = las::Writer::from_path(&file, header).expect("writer");
    for [x, y, z] in points {
        let shade = ((z + 10.0).clamp(0.0, 20.0) * 3000.0) as u16;
        writer
            .write_point(las::Point {
                x: origin[0] + x,
                y: origin[1] + y,
                z: origin[2] + z,
                color: Some(las::Color::new(shade, 30_000, u16::MAX - shade)),
                ..las::Point::default()
            })
            .expect("a point");
    }
    writer.close().expect("written");
    drop(writer);
    let mut failures = Vec::new();
    check(Renderer::new(gpu()), &file, 0.2, &mut failures);
    assert!(failures.is_empty(), "{failures:#?}");
}

//! Color that holds across tiles and frames: two crops of a real scan rendered apart with
//! one `--range` give the same color to the same height (here and from levels of detail),
//! and different colors without it; the range and ramp refused where they do not apply, on
//! the command line and through a daemon; the legend written as a PNG.

use std::path::{Path, PathBuf};
use std::process::Output;

use image::RgbaImage;
use pointfarm_proto::v1 as pb;
use pointfarm_render::cloud::PointCloud;
use pointfarm_render::ingest::{load_point_cloud, write_las, LasWriteOptions};
use pointfarm_render::legend::RAMP_LEGEND_SIZE;
use pointfarm_tests::service::{daemon_with_sample, scan, scratch_sample, turntable_job};
use pointfarm_tests::{assert_fails_saying, assert_ok, path_arg, pointfarm, stdout};

/// A scan cut into a west and an east crop that share a band in the middle.
struct Crops {
    cloud: PointCloud,
    west: PathBuf,
    east: PathBuf,
    /// World X of the shared band.
    band: (f64, f64),
}

fn crops(dir: &Path) -> Crops {
    let cloud = load_point_cloud(&scan(dir)).expect("the scan");
    let (min, max) = (cloud.bounds.min, cloud.bounds.max);
    let band = (min.x + 0.4 * (max.x - min.x), min.x + 0.6 * (max.x - min.x));
    let world_x = |i: usize| cloud.origin.x + f64::from(cloud.positions[i].x);
    let select = |keep: &dyn Fn(f64) -> bool| -> Vec<usize> {
        (0..cloud.len()).filter(|&i| keep(world_x(i))).collect()
    };
    let west = dir.join("west.las");
    let east = dir.join("east.laz");
    let options = LasWriteOptions::default();
    write_las(&west, &cloud.select(&select(&|x| x <= band.1)), &options).expect("west");
    write_las(&east, &cloud.select(&select(&|x| x >= band.0)), &options).expect("east");
    Crops {
        cloud,
        west,
        east,
        band,
    }
}

const SIZE: (u32, u32) = (200, 150);

/// The flags of one top-down orthographic camera over the whole scan, the same for each
/// crop, so a pixel is the same place in both images.
fn camera(cloud: &PointCloud) -> Vec<String> {
    let (min, max) = (cloud.bounds.min, cloud.bounds.max);
    let centre = cloud.bounds.center();
    let above = max.z + 50.0;
    let height = (max.y - min.y).max((max.x - min.x) * f64::from(SIZE.1) / f64::from(SIZE.0));
    vec![
        format!("--camera-pos={},{},{above}", centre.x, centre.y),
        format!("--camera-target={},{},{}", centre.x, centre.y, min.z),
        "--camera-up=0,1,0".into(),
        "--ortho".into(),
        format!("--ortho-height={}", height * 1.02),
        "--near=1".into(),
        format!("--far={}", above - min.z + 50.0),
        format!("--size={}x{}", SIZE.0, SIZE.1),
    ]
}

fn render(input: &Path, out: &Path, more: &[String]) -> RgbaImage {
    let mut args = vec![
        "render".to_string(),
        path_arg(input).into(),
        "--out".into(),
        path_arg(out).into(),
    ];
    args.extend(more.iter().cloned());
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    let output = pointfarm(&args);
    assert_ok(&output);
    image::open(out).expect("the frame").to_rgba8()
}

/// Of the pixels inside the shared band where both images drew a point: how many, and the
/// share within one level a channel.
fn agreement(crops: &Crops, a: &RgbaImage, b: &RgbaImage, background: [u8; 4]) -> (usize, f64) {
    let (min_x, max_x) = (crops.cloud.bounds.min.x, crops.cloud.bounds.max.x);
    let centre = crops.cloud.bounds.center().x;
    let ortho_width = {
        let (min, max) = (crops.cloud.bounds.min, crops.cloud.bounds.max);
        let height =
            (max.y - min.y).max((max.x - min.x) * f64::from(SIZE.1) / f64::from(SIZE.0)) * 1.02;
        height * f64::from(SIZE.0) / f64::from(SIZE.1)
    };
    let column = |x: f64| ((x - centre) / ortho_width + 0.5) * f64::from(SIZE.0);
    // A few pixels inside the band: its edges hold points of one crop only.
    let margin = 0.1 * (crops.band.1 - crops.band.0);
    let (first, last) = (
        column(crops.band.0 + margin).ceil() as u32,
        column(crops.band.1 - margin).floor() as u32,
    );
    assert!(
        first < last && min_x < crops.band.0 && crops.band.1 < max_x,
        "band in columns {first}..{last}"
    );
    let (mut both, mut close) = (0, 0);
    for y in 0..SIZE.1 {
        for x in first..=last {
            let (p, q) = (a.get_pixel(x, y).0, b.get_pixel(x, y).0);
            if p == background || q == background {
                continue;
            }
            both += 1;
            close += usize::from((0..3).all(|c| p[c].abs_diff(q[c]) <= 1));
        }
    }
    (both, close as f64 / both.max(1) as f64)
}

const BACKGROUND: [u8; 4] = [0, 0, 0, 255];

/// One elevation range over the whole scan: its 10% to 90% of height.
fn fixed_range(cloud: &PointCloud) -> String {
    let (low, high) = (cloud.bounds.min.z, cloud.bounds.max.z);
    let span = high - low;
    format!("--range={:.3}..{:.3}", low + 0.1 * span, low + 0.9 * span)
}

fn crops_agree_with_a_range_only(lod: bool) {
    let dir = tempfile::tempdir().expect("tempdir");
    let crops = crops(dir.path());
    let mut common = camera(&crops.cloud);
    // Unshaded: EDL's exposure takes each frame's own gain, and the colors are compared here.
    common.extend([
        "--color=elevation".into(),
        "--background=#000000".into(),
        "--shading=none".into(),
    ]);
    if lod {
        let cache = dir.path().join("cache");
        common.extend([
            "--lod-error=0".into(),
            format!("--cache-dir={}", path_arg(&cache)),
        ]);
    }
    let frames = |name: &str, more: &[String]| {
        let mut args = common.clone();
        args.extend(more.iter().cloned());
        let west = render(
            &crops.west,
            &dir.path().join(format!("{name}-w.png")),
            &args,
        );
        let east = render(
            &crops.east,
            &dir.path().join(format!("{name}-e.png")),
            &args,
        );
        (west, east)
    };
    let range = [fixed_range(&crops.cloud), "--ramp=turbo".into()];
    let (west, east) = frames("range", &range);
    let (both, close) = agreement(&crops, &west, &east, BACKGROUND);
    eprintln!("with --range: {both} shared pixels, {close:.4} agree");
    assert!(both > 500, "only {both} pixels drawn by both crops");
    assert!(
        close >= 0.99,
        "with one --range, {:.2}% of the shared pixels agree",
        close * 100.0
    );
    let (west, east) = frames("robust", &[]);
    let (both, close) = agreement(&crops, &west, &east, BACKGROUND);
    eprintln!("without --range: {both} shared pixels, {close:.4} agree");
    assert!(both > 500);
    assert!(
        close < 0.8,
        "without --range, each crop's own range should color the band differently: {:.2}% agree",
        close * 100.0
    );
}

#[test]
fn two_crops_with_one_range_color_the_same_height_alike() {
    crops_agree_with_a_range_only(false);
}

#[test]
fn two_crops_with_one_range_color_the_same_height_alike_from_levels_of_detail() {
    crops_agree_with_a_range_only(true);
}

#[test]
fn ranges_and_ramps_are_checked_on_the_command_line() {
    let (dir, input) = scratch_sample("sample.las", 2_000, 4);
    let out = dir.path().join("out.png");
    let run = |more: &[&str]| {
        let mut args = vec![
            "render",
            path_arg(&input),
            "--out",
            path_arg(&out),
            "--size",
            "32x24",
        ];
        args.extend_from_slice(more);
        pointfarm(&args)
    };
    for (more, needle) in [
        (
            &["--color", "elevation", "--range", "NaN..5"][..],
            "render.color_range",
        ),
        (&["--color", "elevation", "--range", "0..inf"], "finite"),
        (
            &["--color", "intensity", "--range", "5..5"],
            "min must be below max",
        ),
        (
            &["--color", "elevation", "--range", "-12.5..-20"],
            "render.color_range",
        ),
        (&["--range", "0..10"], "not rgb"),
        (&["--color", "#ff8000", "--range", "0..10"], "not fixed"),
        (
            &["--color", "classification", "--ramp", "turbo"],
            "render.color_ramp",
        ),
        (
            &["--color", "return", "--range", "0..10"],
            "applies only to the elevation",
        ),
        (&["--color", "elevation", "--range", "1-5"], "not a range"),
        (&["--color", "elevation", "--ramp", "jet"], "not a ramp"),
        (&["--legend", "legend.png"], "--color rgb has none"),
        (&["--color", "elevation", "--legend", "legend.jpg"], ".png"),
    ] {
        assert_fails_saying(&run(more), needle);
    }
    // Through a server, the workers choose the robust range: a ramp's legend needs --range.
    let server = ["--server", "http://127.0.0.1:9", "--color", "elevation"];
    let legend = dir.path().join("legend.png");
    assert_fails_saying(
        &run(&[&server[..], &["--legend", path_arg(&legend)]].concat()),
        "needs --range",
    );
    assert!(!out.exists() && !legend.exists(), "nothing written");
    assert_ok(&run(&[
        "--color",
        "elevation",
        "--range",
        "-12.5..340",
        "--ramp",
        "inferno",
    ]));
    assert_ok(&run(&[
        "--color",
        "intensity",
        "--range=0..4000",
        "--ramp",
        "grey",
    ]));
}

/// The legend `args` write, decoded, and the size the render said it has.
fn legend(args: &[&str]) -> (RgbaImage, String) {
    let output: Output = pointfarm(args);
    assert_ok(&output);
    let said = stdout(&output);
    let line = said
        .lines()
        .find(|l| l.contains("legend: "))
        .unwrap_or_else(|| panic!("no legend line in:\n{said}"));
    let size = line
        .rsplit_once('(')
        .and_then(|(_, s)| s.strip_suffix(')'))
        .expect("the legend's size")
        .to_string();
    let path = args[args
        .iter()
        .position(|a| *a == "--legend")
        .expect("--legend")
        + 1];
    let bytes = std::fs::read(path).expect("the legend");
    let format = image::guess_format(&bytes).expect("an image");
    assert_eq!(format, image::ImageFormat::Png);
    (
        image::load_from_memory(&bytes).expect("decodes").to_rgba8(),
        size,
    )
}

fn drawn_pixels(image: &RgbaImage) -> usize {
    image
        .pixels()
        .filter(|p| p.0 != [255, 255, 255, 255])
        .count()
}

#[test]
fn the_legend_is_a_png_of_the_ramp_or_the_swatches() {
    let dir = tempfile::tempdir().expect("tempdir");
    let input = scan(dir.path());
    let out = dir.path().join("frame.png");
    let ramp = dir.path().join("ramp.png");
    let common = [
        "render",
        path_arg(&input),
        "--out",
        path_arg(&out),
        "--size",
        "64x48",
    ];
    let (image, size) = legend(
        &[
            &common[..],
            &["--color", "elevation", "--legend", path_arg(&ramp)],
        ]
        .concat(),
    );
    assert_eq!(image.dimensions(), RAMP_LEGEND_SIZE);
    assert_eq!(
        size,
        format!("{}x{}", RAMP_LEGEND_SIZE.0, RAMP_LEGEND_SIZE.1)
    );
    assert!(drawn_pixels(&image) > 5_000, "the ramp and its numbers");
    let classes = dir.path().join("classes.png");
    let (image, size) = legend(
        &[
            &common[..],
            &["--color", "classification", "--legend", path_arg(&classes)],
        ]
        .concat(),
    );
    assert_eq!(size, format!("{}x{}", image.width(), image.height()));
    assert!(image.height() > image.width(), "a row a class");
    assert!(drawn_pixels(&image) > 2_000, "swatches and names");
    // The ground's swatch is there.
    assert!(image.pixels().any(|p| p.0 == [166, 118, 61, 255]));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_service_refuses_bad_ranges_and_ramps_naming_the_field() {
    let (daemon, dataset) = daemon_with_sample(2_000, 5).await;
    let mut jobs = daemon.jobs().await;
    let job = |name: &str, mode: pb::ColorMode, range: Option<(f64, f64)>, ramp: i32| {
        let mut request = turntable_job(name, &dataset.id, 1, 32, 24);
        request.render = Some(pb::RenderOptions {
            color_mode: mode as i32,
            color_range: range.map(|(min, max)| pb::ColorRange { min, max }),
            color_ramp: ramp,
            ..Default::default()
        });
        request
    };
    let turbo = pb::ColorRamp::Turbo as i32;
    for (request, field, needle) in [
        (
            job("nan", pb::ColorMode::Elevation, Some((f64::NAN, 1.0)), 0),
            "render.color_range",
            "finite",
        ),
        (
            job("empty", pb::ColorMode::Intensity, Some((3.0, 3.0)), 0),
            "render.color_range",
            "below",
        ),
        (
            job("rgb", pb::ColorMode::Rgb, Some((0.0, 1.0)), 0),
            "render.color_range",
            "not rgb",
        ),
        (
            job("classes", pb::ColorMode::Classification, None, turbo),
            "render.color_ramp",
            "not classification",
        ),
        (
            job("unknown", pb::ColorMode::Elevation, None, 99),
            "render.color_ramp",
            "",
        ),
    ] {
        let status = jobs.submit_job(request).await.expect_err("refused");
        assert_eq!(status.code(), tonic::Code::InvalidArgument, "{status:?}");
        let message = status.message();
        assert!(
            message.contains(field) && message.contains(needle),
            "{message}"
        );
    }
    let fine = job(
        "fine",
        pb::ColorMode::Elevation,
        Some((-12.5, 340.0)),
        turbo,
    );
    jobs.submit_job(fine).await.expect("a valid range and ramp");
    daemon.stop().await;
}

//! What `pointfarm render` writes: images in the format their extension names, turntables
//! into folders or patterns, depth images with what turns them back into distances, and
//! videos of exactly the frames of the render (with ffmpeg, checked before rendering).

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use pointfarm_tests::{
    assert_fails_saying, assert_ok, installed_or_skip, path_arg, pointfarm, pointfarm_bin,
    printed_camera,
};

/// A temporary folder holding one small generated cloud.
struct Scene {
    dir: tempfile::TempDir,
    cloud: String,
}

impl Scene {
    fn new() -> Self {
        let dir = tempfile::tempdir().expect("tempdir");
        let cloud = path_arg(&dir.path().join("sample.laz")).to_owned();
        assert_ok(&pointfarm(&["sample", &cloud, "--points", "20000"]));
        Self { dir, cloud }
    }

    fn path(&self, name: &str) -> PathBuf {
        self.dir.path().join(name)
    }

    /// `render` of the scene at 96x64 with `options`.
    fn render(&self, options: &[&str]) -> Output {
        let mut args = vec!["render", &self.cloud, "--local", "--size", "96x64"];
        args.extend(options);
        pointfarm(&args)
    }
}

/// The image format the file's bytes are in, whatever its name says.
fn format_of(path: &Path) -> image::ImageFormat {
    image::ImageReader::open(path)
        .and_then(|r| r.with_guessed_format())
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
        .format()
        .unwrap_or_else(|| panic!("{}: no known format", path.display()))
}

fn ffmpeg_installed() -> bool {
    installed_or_skip("ffmpeg", "-version", "deploy/test.sh installs it")
}

/// The frames of a video, counted by ffprobe.
fn video_frames(video: &Path) -> u64 {
    let output = Command::new("ffprobe")
        .args(["-v", "error", "-count_frames", "-select_streams", "v:0"])
        .args(["-show_entries", "stream=nb_read_frames", "-of", "csv=p=0"])
        .arg(video)
        .output()
        .expect("ffprobe runs");
    let text = String::from_utf8_lossy(&output.stdout);
    text.trim()
        .parse()
        .unwrap_or_else(|_| panic!("ffprobe said {text:?} of {}", video.display()))
}

#[test]
fn a_still_is_written_in_the_format_its_extension_names() {
    let scene = Scene::new();
    for (name, format) in [
        ("still.png", image::ImageFormat::Png),
        ("still.JPG", image::ImageFormat::Jpeg),
        ("still.webp", image::ImageFormat::WebP),
        ("still.tiff", image::ImageFormat::Tiff),
    ] {
        let path = scene.path(name);
        assert_ok(&scene.render(&["--out", path_arg(&path)]));
        assert_eq!(format_of(&path), format, "{name}");
        let image = image::open(&path).expect("readable");
        assert_eq!((image.width(), image.height()), (96, 64), "{name}");
        if format == image::ImageFormat::Tiff {
            // The frame's 8-bit colors as they are, alpha kept.
            assert!(image.as_rgba8().is_some(), "8 bits a channel");
        }
    }
    let bmp = scene.path("still.bmp");
    assert_fails_saying(&scene.render(&["--out", path_arg(&bmp)]), ".jpg/.jpeg");
    assert_fails_saying(
        &scene.render(&[
            "--out",
            path_arg(&scene.path("t.jpg")),
            "--background",
            "transparent",
        ]),
        "JPEG has no alpha channel",
    );
}

#[test]
fn a_turntable_goes_to_a_folder_or_a_pattern_never_over_one_file() {
    let scene = Scene::new();
    let pattern = scene.path("shots/orbit_{:03}.jpg");
    assert_ok(&scene.render(&["--turntable", "2", "--out", path_arg(&pattern)]));
    for i in 0..2 {
        let frame = scene.path(&format!("shots/orbit_{i:03}.jpg"));
        assert_eq!(format_of(&frame), image::ImageFormat::Jpeg);
    }
    let file = scene.path("foo.png");
    assert_fails_saying(
        &scene.render(&["--turntable", "2", "--out", path_arg(&file)]),
        "writes many frames",
    );
    assert!(!file.exists(), "nothing is made of a refused --out");
}

#[test]
fn a_depth_image_comes_with_its_near_far_and_camera() {
    let scene = Scene::new();
    let out = scene.path("view.webp");
    // Unshaded: EDL darkens background pixels beside the points, which have no depth.
    assert_ok(&scene.render(&[
        "--out",
        path_arg(&out),
        "--depth",
        "--shading",
        "none",
        "--near",
        "10",
        "--far",
        "5000",
    ]));
    let depth_path = scene.path("view.depth.png");
    let sidecar: serde_json::Value =
        serde_json::from_slice(&std::fs::read(scene.path("view.depth.json")).expect("sidecar"))
            .expect("JSON");
    assert_eq!(sidecar["near"], 10.0, "{sidecar}");
    assert_eq!(sidecar["far"], 5000.0, "{sidecar}");
    assert_eq!(sidecar["image"], "view.depth.png");
    assert_eq!(
        (sidecar["width"].as_u64(), sidecar["height"].as_u64()),
        (Some(96), Some(64))
    );
    for key in ["position", "target", "up"] {
        let vector = sidecar["camera"][key].as_array().expect(key);
        assert_eq!(vector.len(), 3, "{sidecar}");
    }
    assert!(sidecar["camera"]["projection"]["perspective"]["fovYDeg"].is_number());

    // Where the color image shows a point the depth decodes to a distance, nearer at the
    // bottom of this view from above than at the top.
    let depth = image::open(&depth_path).expect("depth PNG");
    let depth = depth.as_luma16().expect("16-bit grey");
    let color = image::open(&out).expect("color").to_rgba8();
    let background = *color.get_pixel(0, 0);
    let mut halves = [(0.0, 0u32); 2];
    for (x, y, c) in color.enumerate_pixels() {
        if *c == background {
            continue;
        }
        let v = depth.get_pixel(x, y).0[0];
        assert!(v > 0, "the point at ({x}, {y}) has a depth");
        let distance = 10.0 + f64::from(v - 1) / 65534.0 * (5000.0 - 10.0);
        let half = &mut halves[usize::from(y >= 32)];
        half.0 += distance;
        half.1 += 1;
    }
    let [(top, top_n), (bottom, bottom_n)] = halves;
    assert!(
        top_n > 50 && bottom_n > 50,
        "{top_n} and {bottom_n} pixels lit"
    );
    let (top, bottom) = (top / f64::from(top_n), bottom / f64::from(bottom_n));
    assert!(bottom < top, "bottom {bottom} nearer than top {top}");
}

#[test]
fn a_video_holds_exactly_the_frames_of_its_render() {
    if !ffmpeg_installed() {
        return;
    }
    let scene = Scene::new();
    let frames = scene.path("frames");
    // Frames of an earlier, longer render in the same folder.
    assert_ok(&scene.render(&["--turntable", "6", "--out", path_arg(&frames)]));
    let video = scene.path("turn.mp4");
    assert_ok(&scene.render(&[
        "--turntable",
        "3",
        "--out",
        path_arg(&frames),
        "--video",
        path_arg(&video),
        "--fps",
        "10",
        "--video-quality",
        "28",
    ]));
    assert_eq!(video_frames(&video), 3);
    let gif = scene.path("turn.gif");
    assert_ok(&scene.render(&[
        "--turntable",
        "4",
        "--out",
        path_arg(&scene.path("jpegs/f_{}.jpg")),
        "--video",
        path_arg(&gif),
    ]));
    assert_eq!(format_of(&gif), image::ImageFormat::Gif);
    assert_eq!(video_frames(&gif), 4);
}

#[test]
fn a_video_that_cannot_be_made_is_refused_before_any_frame_is_rendered() {
    let scene = Scene::new();
    let frames = scene.path("frames");
    let video = scene.path("turn.mp4");
    // No ffmpeg on the PATH.
    let output = Command::new(pointfarm_bin())
        .args(["render", &scene.cloud, "--local", "--size", "96x64"])
        .args([
            "--turntable",
            "2",
            "--out",
            path_arg(&frames),
            "--video",
            path_arg(&video),
        ])
        .env("PATH", scene.path("empty"))
        .output()
        .expect("run pointfarm");
    assert_fails_saying(&output, "ffmpeg is not installed");
    assert!(!frames.exists(), "no frame rendered");
    let turntable_to = |out: &Path, video: &Path| {
        scene.render(&[
            "--turntable",
            "2",
            "--out",
            path_arg(out),
            "--video",
            path_arg(video),
        ])
    };
    let output = turntable_to(&frames, &scene.path("absent/turn.mp4"));
    assert_fails_saying(&output, "does not exist");
    assert!(!frames.exists(), "no frame rendered");
    let output = turntable_to(&scene.path("tiffs/f_{}.tif"), &video);
    assert_fails_saying(&output, "TIFF frames cannot be piped");
    assert!(!scene.path("tiffs").exists(), "no frame rendered");
}

#[test]
fn the_camera_a_render_prints_gives_the_same_picture_again() {
    let scene = Scene::new();
    let (first, again) = (scene.path("top.png"), scene.path("again.png"));
    let output = scene.render(&["--out", path_arg(&first), "--view", "top", "--ortho"]);
    assert_ok(&output);
    let text = String::from_utf8_lossy(&output.stdout);
    assert!(text.contains("bounds: x "), "{text}");
    let flags = printed_camera(&output);
    assert!(
        flags.join(" ").contains("--ortho --ortho-height="),
        "{flags:?}"
    );
    let mut options = vec!["--out", again.to_str().expect("UTF-8")];
    options.extend(flags.iter().map(String::as_str));
    assert_ok(&scene.render(&options));
    let (a, b) = (
        image::open(&first).expect("first").to_rgba8(),
        image::open(&again).expect("again").to_rgba8(),
    );
    // The printed decimals move a point across a pixel edge at most here and there.
    let differing = a.pixels().zip(b.pixels()).filter(|(x, y)| x != y).count();
    assert!(differing * 200 < a.len() / 4, "{differing} pixels differ");
}

#[test]
fn a_camera_path_file_renders_its_frames() {
    let scene = Scene::new();
    // The cloud's bounds, as a render reports them.
    let still = scene.path("still.png");
    let output = scene.render(&["--out", path_arg(&still), "--json"]);
    assert_ok(&output);
    let frame: serde_json::Value = serde_json::from_slice(&output.stdout).expect("one JSON object");
    let corner = |key: &str| -> Vec<f64> {
        let values = frame["bounds"][key].as_array().expect(key);
        values.iter().map(|v| v.as_f64().expect("number")).collect()
    };
    let (min, max) = (corner("min"), corner("max"));
    let center: Vec<f64> = min.iter().zip(&max).map(|(a, b)| (a + b) / 2.0).collect();
    let span = (max[0] - min[0]).max(max[1] - min[1]);
    let path = scene.path("orbit.toml");
    // A view from above and beside the cloud, towards its centre: position and target.
    let view = |dx: f64, dy: f64| {
        let position = [center[0] + dx * span, center[1] + dy * span, max[2] + span];
        (format!("{position:?}"), format!("{center:?}"))
    };
    let keyframe = |dx: f64, dy: f64| {
        let (position, target) = view(dx, dy);
        format!("[[keyframes]]\nposition = {position}\ntarget = {target}\nfov_y_deg = 55\n")
    };
    let text = format!(
        "frames = 3\ninterpolation = \"linear\"\n{}{}",
        keyframe(1.0, 0.0),
        keyframe(0.0, 1.0)
    );
    std::fs::write(&path, text).expect("path file");
    let frames = scene.path("path-frames");
    assert_ok(&scene.render(&["--camera-path", path_arg(&path), "--out", path_arg(&frames)]));
    let images: Vec<image::RgbaImage> = (0..3)
        .map(|i| {
            image::open(frames.join(format!("frame_{i:05}.png")))
                .expect("frame")
                .to_rgba8()
        })
        .collect();
    assert_ne!(images[0], images[2], "the camera moved along the path");
    assert!(!frames.join("frame_00003.png").exists());

    // The same two views as a Potree project's camera animation (JSON5, as Potree saves it):
    // half a second at 6 frames a second is 3 frames, from the first view to the second.
    let control_point = |dx: f64, dy: f64| {
        let (position, target) = view(dx, dy);
        format!("{{position: {position}, target: {target}}}")
    };
    let project = scene.path("potree.json5");
    std::fs::write(
        &project,
        format!(
            "{{type: 'Potree', version: 1.7, settings: {{fov: 55}},\n cameraAnimations: [{{name: 'orbit', duration: 0.5, curveType: 'centripetal', controlPoints: [{}, {}]}}]}}",
            control_point(1.0, 0.0),
            control_point(0.0, 1.0)
        ),
    )
    .expect("project file");
    let potree_frames = scene.path("potree-frames");
    let output = scene.render(&[
        "--camera-path",
        path_arg(&project),
        "--fps",
        "6",
        "--out",
        path_arg(&potree_frames),
    ]);
    assert_ok(&output);
    let said = String::from_utf8_lossy(&output.stderr);
    assert!(
        said.contains("Potree animation 'orbit': 2 control points"),
        "{said}"
    );
    for i in [0, 2] {
        let frame = image::open(potree_frames.join(format!("frame_{i:05}.png")))
            .expect("frame")
            .to_rgba8();
        assert!(frame == images[i], "frame {i} is the keyframe's view");
    }
    assert!(!potree_frames.join("frame_00003.png").exists());

    let broken = scene.path("broken.json");
    std::fs::write(&broken, "{\"frames\": 3, \"keyframes\": [], \"speed\": 1}").expect("file");
    assert_fails_saying(
        &scene.render(&[
            "--camera-path",
            path_arg(&broken),
            "--out",
            path_arg(&frames),
        ]),
        "broken.json is not a camera path",
    );
    assert_fails_saying(
        &scene.render(&[
            "--out",
            path_arg(&still),
            "--video",
            path_arg(&scene.path("v.mp4")),
        ]),
        "--video needs frames",
    );
}

#[test]
fn adaptive_points_close_a_sparse_cloud_and_say_their_size() {
    let scene = Scene::new();
    // 20,000 points at 320x240: sparse enough for gaps between one-pixel points. Unshaded,
    // so that only points cover pixels.
    let render = |options: &[&str]| {
        let mut args = vec!["render", &scene.cloud, "--local", "--size", "320x240"];
        args.extend(["--shading", "none"]);
        args.extend(options);
        pointfarm(&args)
    };
    let covered = |path: &Path| {
        let image = image::open(path).expect("frame").to_rgba8();
        let background = *image.get_pixel(0, 0);
        image.pixels().filter(|p| **p != background).count()
    };
    let (auto, one) = (scene.path("auto.png"), scene.path("one.png"));
    let output = render(&["--out", path_arg(&auto)]);
    assert_ok(&output);
    let text = String::from_utf8_lossy(&output.stdout);
    let line = text
        .lines()
        .find_map(|line| line.strip_prefix("point size: 1 to "))
        .unwrap_or_else(|| panic!("no adaptive point size line in {text}"));
    assert!(line.contains("pixels by depth (points about "), "{line}");
    assert_ok(&render(&["--out", path_arg(&one), "--point-size", "1"]));
    let (auto_px, one_px) = (covered(&auto), covered(&one));
    assert!(
        auto_px > one_px * 3 / 2,
        "adaptive points cover {auto_px} pixels, one-pixel points {one_px}"
    );

    let output = render(&["--out", path_arg(&auto), "--json"]);
    assert_ok(&output);
    let frame: serde_json::Value = serde_json::from_slice(&output.stdout).expect("one JSON object");
    assert_eq!(frame["adaptivePointSize"], true, "{frame}");
    assert!(
        frame["pointSize"].as_u64().expect("pointSize") > 1,
        "{frame}"
    );

    let round = scene.path("round.png");
    let options = [
        "--out",
        path_arg(&round),
        "--point-size",
        "6",
        "--round-points",
    ];
    let output = render(&options);
    assert_ok(&output);
    let text = String::from_utf8_lossy(&output.stdout);
    assert!(text.contains("point size: 6 pixels"), "{text}");
}

#[test]
fn an_image_wider_than_one_pass_allows_is_drawn_in_tiles() {
    // 16384 x 1100 in basic quality needs a 137 MiB framebuffer, more than lavapipe binds at
    // once (128 MiB): the frame is drawn in tiles and stitched.
    let scene = Scene::new();
    let path = scene.path("wide.png");
    assert_ok(&pointfarm(&[
        "render",
        &scene.cloud,
        "--local",
        "--size",
        "16384x1100",
        "--out",
        path_arg(&path),
    ]));
    let image = image::open(&path).expect("read").into_rgba8();
    assert_eq!(image.dimensions(), (16384, 1100));
    let background = pointfarm_render::raster::DEFAULT_BACKGROUND;
    let drawn_in = |columns: std::ops::Range<u32>| {
        columns
            .flat_map(|x| (0..1100).map(move |y| (x, y)))
            .filter(|&(x, y)| image.get_pixel(x, y).0 != background)
            .count()
    };
    // The scene sits in the middle, across the seam of two halves.
    assert!(drawn_in(7900..8192) > 1000 && drawn_in(8192..8484) > 1000);
    assert_eq!(drawn_in(0..2000) + drawn_in(14384..16384), 0);
}

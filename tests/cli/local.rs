//! `render`, `sample` and their output on this machine: images, timings, JSON, bad input.

use super::*;

#[test]
fn renders_a_sample_cloud_to_a_png_and_prints_the_stage_timings() {
    let scene = Scene::sampled("sample.laz", 50_000);
    let png = scene.path("frame.png");
    let options = ["--size", "320x200", "--point-size", "2"];
    let output = render_into(&scene.cloud, &png, None, &options);
    assert_rendered(&png, 320, 200);
    for stage in [
        "upload",
        "cull",
        "rasterize",
        "resolve",
        "readback",
        "encode",
    ] {
        assert_says(&output, stage);
    }
}

/// `sample` holds one block of the scene at a time: 2M points took about 380 MiB when the scene
/// was generated and encoded whole (190 B a point); a block at a time, about 60 MiB at any size.
#[test]
fn sample_writes_a_scene_within_a_block_s_memory() {
    let dir = tempfile::tempdir().expect("tempdir");
    let out = path_arg(&dir.path().join("big.laz"));
    let mut child = std::process::Command::new(pointfarm_bin())
        .args(["sample", &out, "--points", "2000000"])
        .stdout(std::process::Stdio::null())
        .spawn()
        .expect("pointfarm sample starts");
    // The kernel's peak resident set of the child, read until it exits (a zombie has none).
    let status = format!("/proc/{}/status", child.id());
    let mut peak_kib = 0u64;
    let exit = loop {
        if let Ok(text) = std::fs::read_to_string(&status) {
            let running = text
                .lines()
                .any(|l| l.starts_with("Name:") && l.contains("pointfarm"));
            let hwm = text
                .lines()
                .find_map(|l| l.strip_prefix("VmHWM:"))
                .and_then(|v| v.split_whitespace().next()?.parse::<u64>().ok());
            if let (true, Some(hwm)) = (running, hwm) {
                peak_kib = peak_kib.max(hwm);
            }
        }
        if let Some(exit) = child.try_wait().expect("wait for pointfarm sample") {
            break exit;
        }
        std::thread::sleep(Duration::from_millis(5));
    };
    assert!(exit.success(), "pointfarm sample failed: {exit}");
    assert!(peak_kib > 0, "no peak read");
    assert!(peak_kib < 160 << 10, "peak {} MiB", peak_kib >> 10);
    let info = pointfarm(&["info", &out]);
    assert_says(&info, "points      2000000");
}

#[test]
fn renders_a_turntable_into_a_directory() {
    let scene = Scene::sampled("sample.las", 20_000);
    let frames = scene.path("frames");
    let options = ["--turntable", "3", "--size", "160x120", "--atomics", "32"];
    let output = render_into(&scene.cloud, &frames, None, &options);
    assert_frames(&frames, 3, (160, 120));
    let first = std::fs::read(frames.join("frame_00000.png")).expect("frame 0");
    let second = std::fs::read(frames.join("frame_00001.png")).expect("frame 1");
    assert_ne!(
        first, second,
        "the camera must move between turntable frames"
    );
    assert_says(&output, "median per stage");
}

/// The summary at the end of a turntable lists every stage its frames report, those of high
/// quality, filling and shading too, and their total.
#[test]
fn a_turntable_s_summary_lists_every_stage_and_a_total() {
    let scene = Scene::sampled("sample.las", 20_000);
    let frames = scene.path("frames");
    let options = [
        "--turntable",
        "2",
        "--size",
        "96x64",
        "--quality",
        "high",
        "--fill",
        "--shading",
        "pintus",
    ];
    let output = render_into(&scene.cloud, &frames, None, &options);
    let text = stdout(&output);
    let (_, summary) = text
        .split_once("median per stage:")
        .unwrap_or_else(|| panic!("no summary in:\n{text}"));
    let listed: Vec<&str> = summary
        .lines()
        .filter_map(|line| line.split_whitespace().next())
        .collect();
    for stage in [
        "upload",
        "cull",
        "rasterize",
        "accumulate",
        "resolve",
        "visibility",
        "fill",
        "shade",
        "readback",
        "encode",
    ] {
        assert!(
            listed.contains(&stage),
            "no {stage} in the summary:\n{text}"
        );
    }
    assert_eq!(listed.last(), Some(&"total"), "{text}");
    assert!(
        summary
            .lines()
            .filter(|l| !l.trim().is_empty())
            .all(|l| l.ends_with(" ms")),
        "{text}"
    );
}

/// An exported POINTFARM_SERVER makes `render` remote; `--local` renders here all the same.
#[test]
fn local_renders_here_whatever_the_environment_names() {
    let scene = Scene::sampled("sample.las", 20_000);
    let png = scene.path("frame.png");
    let run = |local: bool| {
        let mut command = std::process::Command::new(pointfarm_tests::pointfarm_bin());
        command
            .args(["render", &scene.cloud, "--out", &path_arg(&png)])
            .args(["--size", "160x120"])
            .env("POINTFARM_SERVER", "http://127.0.0.1:9");
        if local {
            command.arg("--local");
        }
        command.output().expect("run pointfarm")
    };
    assert!(!run(false).status.success(), "no server listens there");
    assert_ok(&run(true));
    assert_rendered(&png, 160, 120);
}

/// `pointfarm render … | head -1`: the reader goes away, the turntable is still rendered and
/// the command ends without a panic.
#[test]
fn a_closed_output_pipe_does_not_stop_a_render() {
    let scene = Scene::sampled("sample.las", 20_000);
    let frames = scene.path("frames");
    let frames_arg = path_arg(&frames);
    run_into_a_closed_pipe(&[
        "render",
        &scene.cloud,
        "--out",
        &frames_arg,
        "--turntable",
        "3",
        "--size",
        "160x120",
        "--json",
    ]);
    assert_frames(&frames, 3, (160, 120));
}

#[test]
fn renders_a_real_scan_from_a_given_camera() {
    let Some(laz) = shared_data("autzen_trim.laz") else {
        return;
    };
    let dir = tempfile::tempdir().expect("tempdir");
    let png = dir.path().join("autzen.png");
    let output = pointfarm(&[
        "render",
        &path_arg(&laz),
        "--out",
        &path_arg(&png),
        "--size",
        "400x300",
        "--camera-pos",
        "636590,848300,1400",
        "--camera-target",
        "636590,849216,430",
        "--fov",
        "60",
    ]);
    assert_ok(&output);
    assert_rendered(&png, 400, 300);
}

#[test]
fn bad_input_fails_with_one_line_that_names_the_problem() {
    let dir = tempfile::tempdir().expect("tempdir");
    let not_las = dir.path().join("notes.las");
    std::fs::write(&not_las, "these are not points").expect("write");
    let not_las = path_arg(&not_las);
    let out = path_arg(&dir.path().join("x.png"));
    let sample = sample(dir.path(), "s.laz", 1000);
    let render = |extra: &[&str]| {
        let mut args = vec!["render", sample.as_str(), "--out", out.as_str()];
        args.extend_from_slice(extra);
        pointfarm(&args)
    };

    // A header whose largest x (LAS 1.2: byte 179) is a metre past its smallest (byte 187).
    let understated = super::sample(dir.path(), "understated.las", 1000);
    let mut bytes = std::fs::read(&understated).expect("read");
    let min_x = f64::from_le_bytes(bytes[187..195].try_into().expect("8 bytes"));
    bytes[179..187].copy_from_slice(&(min_x + 1.0).to_le_bytes());
    std::fs::write(&understated, bytes).expect("patch");
    let cache = path_arg(&dir.path().join("cache"));
    let lod = ["--lod-error", "1", "--cache-dir", cache.as_str()];

    let cases: Vec<(Output, &str)> = vec![
        (pointfarm(&["render", &not_las, "--out", &out]), "notes.las"),
        (
            pointfarm(&[&["render", &understated, "--out", &out][..], &lod].concat()),
            "understated.las: its point at",
        ),
        (
            pointfarm(&["render", "/nonexistent/scan.laz", "--out", &out]),
            "scan.laz",
        ),
        (render(&["--size", "100000x100000"]), "100000x100000"),
        (render(&["--point-size", "0"]), "point size"),
        (
            render(&["--camera-pos", "1,2,3", "--camera-target", "1,2,3"]),
            "same point",
        ),
        (render(&["--turntable", "0"]), "turntable"),
        (render(&["--fill-kernel", "4"]), "fill kernel 4"),
        (
            render(&["--shading", "pintus", "--pintus-levels", "0"]),
            "Pintus shading",
        ),
        (
            render(&["--shading", "edl", "--edl-strength", "500"]),
            "render.edl_strength",
        ),
        // What the service cannot do is refused before anything is sent, never dropped.
        (
            render(&["--server", "http://127.0.0.1:9", "--depth"]),
            "--depth is not available through a server",
        ),
        (
            render(&["--server", "http://127.0.0.1:9", "--atomics", "32"]),
            "--atomics",
        ),
    ];
    for (output, needle) in cases {
        assert!(
            !output.status.success(),
            "expected a failure mentioning {needle}"
        );
        let lines = own_stderr_lines(&output);
        let errors: Vec<&String> = lines.iter().filter(|l| l.starts_with("error:")).collect();
        assert_eq!(
            errors.len(),
            1,
            "{needle}: expected one error line, got {lines:?}"
        );
        assert!(
            errors[0].contains(needle),
            "'{}' does not mention {needle}",
            errors[0]
        );
        assert!(
            !lines.iter().any(|l| l.contains("panicked")),
            "panicked: {lines:?}"
        );
    }

    // A NaN in a camera is refused by the argument parser, also with a clear message.
    assert_fails_saying(&render(&["--camera-pos", "1,NaN,3"]), "not a finite number");
}

#[test]
fn color_modes_and_high_quality_are_options_of_render() {
    let scene = Scene::sampled("sample.laz", 30_000);
    let laz = &scene.cloud;
    let mut images = Vec::new();
    for (name, extra) in [
        ("rgb", vec!["--color", "rgb"]),
        (
            "elevation",
            vec!["--color", "elevation", "--quality", "high"],
        ),
        ("classes", vec!["--color", "classification"]),
        (
            "fixed",
            vec!["--color", "#ff8000", "--background", "transparent"],
        ),
    ] {
        let png = scene.path(&format!("{name}.png"));
        let mut args = vec!["render", laz.as_str(), "--out"];
        let png_arg = path_arg(&png);
        args.push(&png_arg);
        args.extend(["--size", "200x150", "--point-size", "2"]);
        args.extend(extra.iter().copied());
        let output = pointfarm(&args);
        assert_ok(&output);
        if name == "elevation" {
            assert_says(&output, "accumulate"); // High quality has its own stage.
        }
        images.push(image::open(&png).expect("png").to_rgba8());
    }
    for pair in images.windows(2) {
        assert_ne!(pair[0], pair[1], "every mode gives a different picture");
    }
    let fixed = &images[3];
    assert!(fixed.pixels().any(|p| p.0 == [255, 128, 0, 255]));
    assert!(
        fixed.pixels().any(|p| p.0[3] == 0),
        "transparent background"
    );
    let bad = pointfarm(&["render", laz, "--out", "x.png", "--color", "rainbow"]);
    assert_fails_saying(&bad, "not a color mode");
}

/// `render DIR` renders the files of a folder as one dataset: tiles cut from a file give the
/// image of that file, here and through a server (uploaded file by file and composed).
#[test]
fn a_folder_of_tiles_renders_as_the_file_they_were_cut_from() {
    use pointfarm_render::ingest::{load_point_cloud, write_las, LasWriteOptions};
    let scene = Scene::sampled("sample.laz", 30_000);
    let sampled = load_point_cloud(Path::new(&scene.cloud)).expect("load");
    // Written again from the loaded cloud, so the tiles share its scale and offset.
    let whole = scene.path("whole.laz");
    write_las(&whole, &sampled, &LasWriteOptions::default()).expect("whole");
    let cloud = load_point_cloud(&whole).expect("load whole");
    let tiles = scene.path("tiles");
    std::fs::create_dir_all(tiles.join("east")).expect("tiles");
    let middle = cloud.bounds.center().x;
    let (west, east): (Vec<usize>, Vec<usize>) =
        (0..cloud.len()).partition(|&i| cloud.origin.x + f64::from(cloud.positions[i].x) < middle);
    let options = LasWriteOptions::default();
    write_las(&tiles.join("west.las"), &cloud.select(&west), &options).expect("west");
    write_las(&tiles.join("east/east.laz"), &cloud.select(&east), &options).expect("east");

    let size = ["--size=160x120"];
    render_into(&path_arg(&whole), &scene.path("whole.png"), None, &size);
    let output = render_into(&path_arg(&tiles), &scene.path("tiles.png"), None, &size);
    assert_says(&output, "30000 points in 2 files");
    let image = |name: &str| image::open(scene.path(name)).expect("png").to_rgba8();
    assert!(
        image("whole.png") == image("tiles.png"),
        "the tiles render differently"
    );
    let server = ServeProcess::start(&scene.path("data"));
    let remote = render_into(
        &path_arg(&tiles),
        &scene.path("remote.png"),
        Some(&server.address),
        &size,
    );
    assert_says(&remote, "of 2 files on");
    assert!(
        image("tiles.png") == image("remote.png"),
        "the dataset renders differently through the server\n{}",
        server.log()
    );
    let listed = pointfarm(&["dataset", "list", "--server", &server.address, "--json"]);
    assert_ok(&listed);
    let datasets: serde_json::Value = serde_json::from_str(&stdout(&listed)).expect("json");
    let composed = datasets["datasets"]
        .as_array()
        .expect("a list")
        .iter()
        .find(|d| d["files"].as_array().is_some_and(|f| f.len() == 2));
    assert!(
        composed.is_some(),
        "no dataset of the two files: {datasets}"
    );
}

/// `render --json` prints one object per frame on standard output and nothing else there.
#[test]
fn render_json_reports_every_frame_and_its_points() {
    let scene = Scene::sampled("sample.laz", 20_000);
    let out = scene.path("frames");
    let output = pointfarm(&[
        "render",
        &scene.cloud,
        "--out",
        &path_arg(&out),
        "--turntable=3",
        "--size=96x64",
        "--json",
    ]);
    assert_ok(&output);
    let lines = json_lines(&output);
    assert_eq!(lines.len(), 3, "one object per frame");
    for (i, frame) in lines.iter().enumerate() {
        assert_eq!(frame["frame"], i);
        assert_eq!(frame["pointsTotal"], 20_000);
        let rendered = frame["pointsRendered"].as_u64().expect("pointsRendered");
        assert!(rendered > 0 && rendered <= 20_000, "{frame}");
        assert!(
            frame["timingsMs"]["rasterize"].as_f64().is_some(),
            "{frame}"
        );
        assert_eq!(
            (frame["width"].clone(), frame["height"].clone()),
            (96.into(), 64.into())
        );
    }
    assert_frames(&out, 3, (96, 64));
}

//! The `pointfarm` commands (render, sample, demo, serve, worker, bench), run as a user would.

use std::path::Path;
use std::process::Output;
use std::time::Duration;

use pointfarm_tests::{
    assert_fails_saying, assert_ok, json_lines, json_names, own_stderr_lines, pointfarm,
    pointfarm_bin, run_into_a_closed_pipe, shared_data, signal, stdout, wait_for, ServeProcess,
    WorkerProcess,
};

fn path_arg(path: &Path) -> String {
    path.to_str().expect("temporary paths are UTF-8").to_owned()
}

/// Writes a generated sample cloud of `points` points to `dir/name` and returns its path.
fn sample(dir: &Path, name: &str, points: usize) -> String {
    let path = path_arg(&dir.join(name));
    assert_ok(&pointfarm(&[
        "sample",
        &path,
        "--points",
        &points.to_string(),
    ]));
    path
}

/// A temporary folder holding one generated sample cloud.
struct Scene {
    dir: tempfile::TempDir,
    cloud: String,
}

impl Scene {
    fn sampled(name: &str, points: usize) -> Self {
        let dir = tempfile::tempdir().expect("tempdir");
        let cloud = sample(dir.path(), name, points);
        Self { dir, cloud }
    }

    fn path(&self, name: &str) -> std::path::PathBuf {
        self.dir.path().join(name)
    }
}

/// Fails unless the command's standard output says `needle`.
fn assert_says(output: &Output, needle: &str) {
    let text = stdout(output);
    assert!(text.contains(needle), "no {needle} in:\n{text}");
}

/// Fails unless `dir` holds the frames `0..frames`, each rendered at `size`.
fn assert_frames(dir: &Path, frames: u32, size: (u32, u32)) {
    for i in 0..frames {
        assert_rendered(&dir.join(format!("frame_{i:05}.png")), size.0, size.1);
    }
}

/// Fails unless the PNG has the size and shows something other than its background.
fn assert_rendered(path: &Path, width: u32, height: u32) {
    let image = image::open(path)
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
        .to_rgba8();
    assert_eq!(image.dimensions(), (width, height), "{}", path.display());
    let background = *image.get_pixel(0, 0);
    let drawn = image.pixels().filter(|p| **p != background).count();
    assert!(
        drawn > 1000,
        "{}: only {drawn} pixels drawn",
        path.display()
    );
}

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

    let cases: Vec<(Output, &str)> = vec![
        (pointfarm(&["render", &not_las, "--out", &out]), "notes.las"),
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
            vec!["--colour", "#ff8000", "--background", "transparent"],
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
    assert_fails_saying(&bad, "not a colour mode");
}

#[test]
fn demo_runs_the_service_end_to_end_in_one_process() {
    let scene = Scene::sampled("sample.laz", 20_000);
    let out = scene.path("frames");
    let output = run_ok(
        "demo",
        &scene.cloud,
        &out,
        &["--frames", "2", "--size", "160x120"],
    );
    assert_frames(&out, 2, (160, 120));
    assert_says(&output, "2 frames in");
}

/// SIGTERM (as a container engine sends its first process) stops the demo, its daemon and its
/// worker, saying the job did not end, rather than being ignored.
#[test]
fn the_demo_stops_on_sigterm() {
    use std::io::{BufRead, BufReader};
    let scene = Scene::sampled("sample.laz", 20_000);
    let out = path_arg(&scene.path("frames"));
    let mut demo = std::process::Command::new(pointfarm_bin())
        .args(["demo", &scene.cloud, "--out", &out])
        .args(["--frames", "2000", "--size", "160x120"])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("start the demo");
    let stdout = BufReader::new(demo.stdout.take().expect("stdout"));
    let mut said = Vec::new();
    for line in stdout.lines().map_while(Result::ok) {
        let started = line.starts_with("job ");
        said.push(line);
        if started {
            break;
        }
    }
    assert!(
        said.last().is_some_and(|l| l.starts_with("job ")),
        "{said:?}"
    );
    signal(demo.id(), "TERM");
    let stopped = wait_for(Duration::from_secs(60), "the demo to stop", || {
        demo.try_wait().expect("poll")
    });
    let mut stderr = String::new();
    std::io::Read::read_to_string(&mut demo.stderr.take().expect("stderr"), &mut stderr)
        .expect("stderr");
    assert!(!stopped.success());
    assert!(stderr.contains("stopped before the job ended"), "{stderr}");
}

#[test]
fn remote_render_uploads_submits_follows_and_downloads() {
    let scene = Scene::sampled("sample.laz", 20_000);
    let server = ServeProcess::start(&scene.path("data"));
    let address = server.address.clone();
    let frames = scene.path("remote");
    let options = ["--turntable", "2", "--size", "160x120"];
    render_into(&scene.cloud, &frames, Some(&address), &options);
    assert_frames(&frames, 2, (160, 120));
    let listed = pointfarm(&["jobs", "list", "--server", &address, "--json"]);
    assert_ok(&listed);
    assert_says(&listed, "\"JOB_STATE_SUCCEEDED\"");
    let unknown = pointfarm(&["jobs", "show", "job-missing", "--server", &address]);
    assert_fails_saying(&unknown, "not found");

    // --json through the server: one object per frame on stdout, its file and the frame as
    // the API reports it (a FrameFinished in the proto3 JSON mapping).
    let still = path_arg(&scene.path("remote.png"));
    let output = pointfarm(&[
        "render",
        &scene.cloud,
        "--server",
        &address,
        "--out",
        &still,
        "--size=96x64",
        "--json",
    ]);
    assert_ok(&output);
    let lines = json_lines(&output);
    let [frame] = lines.as_slice() else {
        panic!("one object for one frame:\n{}", stdout(&output));
    };
    assert_eq!(frame["frame"], 0, "{frame}");
    assert_eq!(frame["path"], still.as_str(), "{frame}");
    assert!(frame["jobId"].is_string(), "{frame}");
    let finished: pointfarm_proto::v1::FrameFinished =
        serde_json::from_value(frame["finished"].clone()).expect("a FrameFinished");
    assert!(
        finished.timings.iter().any(|t| t.stage == "rasterize"),
        "{frame}"
    );
}

#[test]
fn fill_and_pintus_shading_render_the_same_locally_and_through_the_service() {
    let options = [
        "--turntable",
        "1",
        "--size",
        "160x120",
        "--fill",
        "--fill-kernel",
        "5",
        "--shading",
        "pintus",
        "--pintus-levels",
        "4",
    ];
    let (scene, output, filled) = render_here_and_there(&options, 1, (160, 120));
    for stage in ["visibility", "fill", "shade"] {
        assert_says(&output, stage);
    }
    // Filling changes the picture.
    let plain = scene.path("plain");
    let options = ["--turntable", "1", "--size", "160x120"];
    render_into(&scene.cloud, &plain, None, &options);
    assert_ne!(filled[0], frame_image(&plain, 0));
}

/// Renders a sample cloud with `options` here and through a served daemon, checks that both
/// give the same `frames` frames of `size`, and returns the scene, the local run's output and
/// its frames.
fn render_here_and_there(
    options: &[&str],
    frames: u32,
    size: (u32, u32),
) -> (Scene, Output, Vec<image::RgbaImage>) {
    let scene = Scene::sampled("sample.laz", 20_000);
    let server = ServeProcess::start(&scene.path("data"));
    let output = render_into(&scene.cloud, &scene.path("local"), None, options);
    let remote = Some(server.address.as_str());
    render_into(&scene.cloud, &scene.path("remote"), remote, options);
    let images = assert_same_frames(scene.dir.path(), frames, size);
    (scene, output, images)
}

/// Renders `laz` into `out` (a file, or a folder for several frames), here or through
/// `server`, with `options`; the render must succeed.
fn render_into(laz: &str, out: &Path, server: Option<&str>, options: &[&str]) -> Output {
    let mut options = options.to_vec();
    if let Some(address) = server {
        options.extend(["--server", address]);
    }
    run_ok("render", laz, out, &options)
}

/// Runs `pointfarm COMMAND CLOUD --out OUT OPTIONS...`, which must succeed.
fn run_ok(command: &str, cloud: &str, out: &Path, options: &[&str]) -> Output {
    let out = path_arg(out);
    let mut args = vec![command, cloud, "--out", out.as_str()];
    args.extend(options);
    let output = pointfarm(&args);
    assert_ok(&output);
    output
}

fn frame_image(dir: &Path, index: u32) -> image::RgbaImage {
    image::open(dir.join(format!("frame_{index:05}.png")))
        .expect("frame")
        .to_rgba8()
}

/// Checks that `dir/local` and `dir/remote` hold the same `frames` frames of `size`, and
/// returns the local ones.
fn assert_same_frames(dir: &Path, frames: u32, size: (u32, u32)) -> Vec<image::RgbaImage> {
    (0..frames)
        .map(|i| {
            assert_rendered(&dir.join(format!("local/frame_{i:05}.png")), size.0, size.1);
            let local = frame_image(&dir.join("local"), i);
            assert_eq!(
                local,
                frame_image(&dir.join("remote"), i),
                "frame {i}: the service rendered another picture"
            );
            local
        })
        .collect()
}

#[test]
fn lens_camera_and_supersampling_render_the_same_locally_and_through_the_service() {
    // The sample scene lies around (500000, 4500000, 100), 120 m across.
    let options = [
        "--size",
        "64x48",
        "--turntable",
        "2",
        "--supersample",
        "2",
        "--ortho",
        "--ortho-height",
        "80",
        "--camera-pos",
        "500000,4499850,180",
        "--camera-target",
        "500000,4500000,100",
        "--near",
        "120",
        "--far",
        "200",
        "--point-size",
        "2",
    ];
    render_here_and_there(&options, 2, (64, 48));
}

#[test]
fn serve_without_an_embedded_worker_renders_through_a_worker_process() {
    let scene = Scene::sampled("sample.laz", 20_000);
    let dir = scene.dir.path();
    let server = ServeProcess::start_with(
        &dir.join("data"),
        &[
            "--no-embedded-worker",
            "--lease-timeout",
            "5",
            "--token",
            "t0k",
            "--worker-token",
            "w0rker",
        ],
    );
    let address = server.address.clone();
    let url = format!("http://{address}");
    // Without the worker token the worker is refused and says so; the client token is not one.
    let refused = pointfarm(&[
        "worker",
        "--server",
        &url,
        "--cache-dir",
        &path_arg(&dir.join("c0")),
    ]);
    assert_fails_saying(&refused, "unauthenticated");
    let refused = pointfarm(&[
        "worker",
        "--server",
        &url,
        "--worker-token",
        "t0k",
        "--cache-dir",
        &path_arg(&dir.join("c0")),
    ]);
    assert_fails_saying(&refused, "permission denied");
    let worker = WorkerProcess::start_with(
        &url,
        &dir.join("cache"),
        "cli-worker",
        &["--worker-token", "w0rker"],
    );
    let frames = dir.join("remote");
    let frames_arg = path_arg(&frames);
    let output = pointfarm(&[
        "render",
        &scene.cloud,
        "--out",
        &frames_arg,
        "--server",
        &address,
        "--token",
        "t0k",
        "--turntable=2",
        "--size=96x64",
    ]);
    assert!(
        output.status.success(),
        "{}\n{}",
        String::from_utf8_lossy(&output.stderr),
        worker.log()
    );
    assert_frames(&frames, 2, (96, 64));
    assert!(worker.log().contains("frame handed in"), "{}", worker.log());
    let leases = pointfarm(&[
        "jobs", "leases", "--server", &address, "--token", "t0k", "--json",
    ]);
    assert_ok(&leases);
    assert_eq!(
        stdout(&leases).trim(),
        "{}",
        "no frame is in flight after the job (an empty ListLeasesResponse)"
    );
}

/// The JSON file a command wrote.
fn read_json(path: &Path) -> serde_json::Value {
    serde_json::from_slice(&std::fs::read(path).expect("json written")).expect("valid json")
}

#[test]
fn bench_writes_its_figures_as_json_and_markdown() {
    let Some(autzen) = shared_data("autzen_trim.laz") else {
        return;
    };
    let data = autzen.parent().expect("the scan's directory");
    let options = [
        "--only",
        "autzen_trim.laz",
        "--modes",
        "hq,basic-32",
        "--size",
        "160x120",
    ];
    let (report, table) = quick_bench(data, &options);
    let workload = &report["workloads"][0];
    assert_eq!(workload["workload"], "autzen_trim.laz");
    assert_eq!(workload["points"], 110_000);
    for method in [&workload["pointlist"], &workload["compute"]] {
        assert!(
            method["frameMs"].as_f64().is_some_and(|ms| ms > 0.0),
            "{method}"
        );
    }
    let modes = json_names(&workload["modes"], "method");
    assert_eq!(modes, ["compute-hq", "compute-basic-32"]);
    // The headline figure belongs to the 10M cloud, which this run left out.
    assert!(report["speedupVsPointlist"].is_null(), "{report}");
    assert!(table.contains("| autzen_trim.laz |"), "{table}");
}

/// Runs `pointfarm bench --quick` on the scans in `data` with `options`, and returns the
/// report it wrote as JSON and its Markdown table.
fn quick_bench(data: &Path, options: &[&str]) -> (serde_json::Value, String) {
    let dir = tempfile::tempdir().expect("tempdir");
    let (json, markdown) = (dir.path().join("bench.json"), dir.path().join("bench.md"));
    let (data, json_arg, markdown_arg) = (path_arg(data), path_arg(&json), path_arg(&markdown));
    let mut args = vec!["bench", "--quick", "--data", &data];
    args.extend(["--json", &json_arg, "--markdown", &markdown_arg]);
    args.extend(options);
    assert_ok(&pointfarm(&args));
    let table = std::fs::read_to_string(&markdown).expect("markdown written");
    (read_json(&json), table)
}

/// `--only ingest` measures loading alone: the real scans found and a generated LAZ file of
/// the size asked, each decoded on all cores and on one and given back by the dataset cache.
#[test]
fn bench_measures_decoding_and_the_dataset_cache() {
    let dir = tempfile::tempdir().expect("tempdir");
    let data = shared_data("autzen_trim.laz")
        .and_then(|scan| scan.parent().map(Path::to_path_buf))
        .unwrap_or_else(|| dir.path().join("no-scans"));
    let options = ["--only", "ingest", "--ingest-points", "30_000"];
    let (report, table) = quick_bench(&data, &options);
    assert!(report["workloads"]
        .as_array()
        .expect("workloads")
        .is_empty());
    let ingest = report["ingest"].as_array().expect("ingest");
    let generated = ingest.last().expect("the generated file");
    assert_eq!(generated["workload"], "ingest-uniform-30000.laz");
    assert_eq!(generated["points"], 30_000);
    for field in [
        "decodeMs",
        "decodeOneThreadMs",
        "cacheHitMs",
        "cacheSpeedup",
    ] {
        assert!(
            generated[field].as_f64().is_some_and(|v| v > 0.0),
            "{field}: {generated}"
        );
    }
    assert!(table.contains("| uniform-30000.laz | 30,000 |"), "{table}");
    if shared_data("autzen_trim.laz").is_some() {
        assert_eq!(ingest.len(), 3, "{report}");
        assert_eq!(ingest[1]["workload"], "ingest-autzen_trim.laz");
        assert_eq!(ingest[1]["points"], 110_000);
    } else {
        assert_eq!(
            report["skipped"].as_array().map(Vec::len),
            Some(2),
            "{report}"
        );
    }
}

/// `--huge POINTS` streams a cube of that many points, reports its memory peak and batches,
/// and a count of nothing is refused before any work.
#[test]
fn bench_streams_a_huge_cloud_of_the_size_asked() {
    let dir = tempfile::tempdir().expect("tempdir");
    let json = dir.path().join("bench.json");
    let output = pointfarm(&[
        "bench",
        "--huge",
        "200_000",
        "--only",
        "uniform-200000",
        "--basic-only",
        "--size",
        "64x48",
        "--json",
        &path_arg(&json),
    ]);
    assert_ok(&output);
    let report = read_json(&json);
    let workloads = report["workloads"].as_array().expect("workloads");
    assert_eq!(workloads.len(), 1, "{report}");
    let huge = &workloads[0];
    assert_eq!(huge["workload"], "uniform-200000");
    assert_eq!(huge["points"], 200_000);
    assert!(huge["ingestMemory"]["peakHostBytes"]
        .as_u64()
        .is_some_and(|b| b > 0));
    // 4096-point batches, all in view of the automatic camera.
    assert_eq!(huge["batches"]["total"], 49);
    assert_eq!(huge["batches"]["listed"], 49);
    let stages = json_names(&huge["compute"]["stages"], "stage");
    assert!(stages.contains(&"cull"), "{stages:?}");

    let refused = pointfarm(&["bench", "--huge", "0"]);
    assert_fails_saying(&refused, "at least one point");
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

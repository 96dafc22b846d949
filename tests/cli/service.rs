//! The service as a user runs it: the demo, `serve`, a worker process, remote renders that
//! match local ones.

use super::*;

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
    let job = first_listed_job(&listed);

    // The daemon logs the job's end once, with its counts.
    let counts = [
        "frames_done=2",
        "frames_total=2",
        "failed_attempts=0",
        "elapsed_s=",
    ];
    let line = logged_once(&server, "job succeeded", &job, &counts);
    assert!(line.contains(" INFO "), "{line}");

    // Cancelling a job that has ended leaves it as it is, says so and succeeds.
    let cancel = pointfarm(&["jobs", "cancel", &job, "--server", &address]);
    assert_ok(&cancel);
    assert_eq!(
        stdout(&cancel).trim(),
        format!("job {job} already succeeded; nothing to cancel")
    );
    let shown = pointfarm(&["jobs", "show", &job, "--server", &address, "--json"]);
    assert_says(&shown, "\"JOB_STATE_SUCCEEDED\"");

    // Fetching the frames of a job the server does not have leaves no folder behind.
    let nowhere = scene.path("fetched-nothing");
    let fetched = pointfarm(&[
        "frames",
        "fetch",
        "job-missing",
        "--out",
        &path_arg(&nowhere),
        "--server",
        &address,
    ]);
    assert_fails_saying(&fetched, "not found");
    assert!(
        !nowhere.exists(),
        "a refused fetch made {}",
        nowhere.display()
    );

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

/// The id of the first job `jobs list --json` listed.
fn first_listed_job(listed: &Output) -> String {
    json_lines(listed)[0]["jobs"][0]["id"]
        .as_str()
        .expect("the job's id")
        .to_owned()
}

/// The one line of `server`'s log that says `what` of `job`, once it is there; it must hold each
/// of `holding`.
fn logged_once(server: &ServeProcess, what: &str, job: &str, holding: &[&str]) -> String {
    let lines = wait_for(Duration::from_secs(10), what, || {
        let lines: Vec<String> = server
            .log()
            .lines()
            .filter(|l| l.contains(what) && l.contains(job))
            .map(str::to_owned)
            .collect();
        (!lines.is_empty()).then_some(lines)
    });
    // A moment more, for a second line that should not come.
    std::thread::sleep(Duration::from_millis(200));
    let again = server.log();
    let count = again
        .lines()
        .filter(|l| l.contains(what) && l.contains(job))
        .count();
    assert_eq!(count, 1, "{what} logged {count} times:\n{again}");
    let line = lines[0].clone();
    for text in holding {
        assert!(line.contains(text), "{line}");
    }
    line
}

/// A file the server cannot read fails its job at once; the daemon logs the job's end once,
/// with the attempt that failed it.
#[test]
fn a_failed_job_s_end_is_logged_once_with_its_attempts() {
    let scene = Scene::sampled("sample.las", 5_000);
    let bytes = std::fs::read(&scene.cloud).expect("read the sample");
    let cut = scene.path("cut.las");
    std::fs::write(&cut, &bytes[..bytes.len() / 2]).expect("write the cut file");
    let server = ServeProcess::start(&scene.path("data"));
    let out = path_arg(&scene.path("cut.png"));
    let rendered = pointfarm(&[
        "render",
        &path_arg(&cut),
        "--server",
        &server.address,
        "--out",
        &out,
        "--size=64x48",
    ]);
    assert_fails_saying(&rendered, "truncated");
    let message = String::from_utf8_lossy(&rendered.stderr);
    assert!(!message.contains("error: error:"), "{message}");
    let listed = pointfarm(&["jobs", "list", "--server", &server.address, "--json"]);
    let job = first_listed_job(&listed);
    let counts = [
        "frames_done=0",
        "frames_total=1",
        "failed_attempts=1",
        "truncated",
    ];
    logged_once(&server, "job failed", &job, &counts);
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

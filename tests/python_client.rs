//! The Python client example (`examples/python/pointfarm_client.py`) against a real daemon:
//! a LAZ file uploaded, keyframed jobs rendered and their frames downloaded through TLS with
//! a bearer token, and a refused call reported in one line with a non-zero exit.
//!
//! The example runs in the virtualenv `deploy/test.sh` makes (`POINTFARM_PYTHON`, else
//! `target/python-venv`); where there is none the tests skip, saying so.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use pointfarm_proto::endpoint::ServerEndpoint;
use pointfarm_proto::v1 as pb;
use pointfarm_proto::v1::job_service_client::JobServiceClient;
use pointfarm_proto::BearerToken;
use pointfarm_tests::pki::TestPki;
use pointfarm_tests::service::scratch_sample;
use pointfarm_tests::{path_arg, test_python, ServeProcess};

const TOKEN: &str = "surveyor-s3cret";

fn example() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../examples/python/pointfarm_client.py")
}

/// Runs the example with `args`, its stub cache in `cache`.
fn run_example(python: &Path, cache: &Path, args: &[&str]) -> Output {
    Command::new(python)
        .arg(example())
        .args(args)
        .env("XDG_CACHE_HOME", cache)
        .env_remove("POINTFARM_SERVER")
        .env_remove("POINTFARM_TOKEN")
        .env_remove("POINTFARM_TOKEN_FILE")
        .env_remove("POINTFARM_TLS_CA")
        .output()
        .expect("run the Python example")
}

fn show(output: &Output) -> String {
    format!(
        "{:?}\nstdout:\n{}\nstderr:\n{}",
        output.status,
        String::from_utf8_lossy(&output.stdout),
        String::from_utf8_lossy(&output.stderr)
    )
}

/// Fails, showing the example's output and the daemon's log, unless the example succeeded.
fn assert_succeeded(output: &Output, server: &ServeProcess) {
    assert!(
        output.status.success(),
        "{}\n{}",
        show(output),
        server.log()
    );
}

/// The job id the example printed (`job ID: N frames of WxH`).
fn job_id(output: &Output) -> String {
    String::from_utf8_lossy(&output.stdout)
        .lines()
        .find_map(|line| line.strip_prefix("job ")?.split(':').next())
        .unwrap_or_else(|| panic!("no job line:\n{}", show(output)))
        .to_owned()
}

/// The job as the daemon at `server` (trusting the CA in `ca`) reports it.
async fn daemon_job(server: &str, ca: &Path, id: &str) -> pb::Job {
    let endpoint = ServerEndpoint::new(server, Some(ca)).expect("endpoint");
    let channel = endpoint
        .endpoint()
        .expect("endpoint")
        .connect()
        .await
        .expect("connect");
    let auth = BearerToken::new(Some(TOKEN)).expect("token");
    let mut jobs = JobServiceClient::with_interceptor(channel, auth);
    jobs.get_job(pb::GetJobRequest { id: id.into() })
        .await
        .expect("GetJob")
        .into_inner()
}

/// The PNG files in `folder`, sorted, each checked to decode at `size`.
fn frames_in(folder: &Path, size: (u32, u32)) -> Vec<String> {
    let mut names: Vec<String> = std::fs::read_dir(folder)
        .expect("the frames folder")
        .map(|entry| {
            entry
                .expect("entry")
                .file_name()
                .into_string()
                .expect("UTF-8")
        })
        .collect();
    names.sort();
    for name in &names {
        let path = folder.join(name);
        let format = image::ImageReader::open(&path)
            .and_then(|r| r.with_guessed_format())
            .expect("open frame")
            .format();
        assert_eq!(format, Some(image::ImageFormat::Png), "{name}");
        let frame = image::open(&path).expect("decode frame");
        assert_eq!((frame.width(), frame.height()), size, "{name}");
    }
    names
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_python_example_uploads_renders_a_camera_path_and_downloads_its_frames() {
    let Some(python) = test_python(&["grpc", "grpc_tools"], "examples/python/requirements.txt")
    else {
        return;
    };
    let (scratch, scan) = scratch_sample("scan.laz", 20_000, 7);
    let dir = scratch.path();
    let token_file = dir.join("client.token");
    std::fs::write(&token_file, format!("{TOKEN}\n")).expect("token file");
    let pki = TestPki::create(dir);
    let server = ServeProcess::start_with(
        &dir.join("data"),
        &[
            "--token",
            TOKEN,
            "--tls-cert",
            path_arg(&pki.cert),
            "--tls-key",
            path_arg(&pki.key),
        ],
    );
    // Through TLS, trusting the test's CA; the certificate names localhost.
    let port = server.address.rsplit(':').next().expect("a port");
    let https = format!("https://localhost:{port}");

    // A camera path file as `pointfarm render --camera-path` reads it, around the scan.
    let bounds = las::Reader::from_path(&scan)
        .expect("read the scan")
        .header()
        .bounds();
    let (cx, cy, cz) = (
        (bounds.min.x + bounds.max.x) / 2.0,
        (bounds.min.y + bounds.max.y) / 2.0,
        (bounds.min.z + bounds.max.z) / 2.0,
    );
    let reach = (bounds.max.x - bounds.min.x).max(bounds.max.y - bounds.min.y) * 1.5;
    let camera_path = dir.join("flight.toml");
    std::fs::write(
        &camera_path,
        format!(
            "frames = 5\ninterpolation = \"linear\"\n\
             [[keyframes]]\nposition = [{}, {}, {}]\ntarget = [{cx}, {cy}, {cz}]\n\
             [[keyframes]]\nposition = [{}, {}, {}]\ntarget = [{cx}, {cy}, {cz}]\nfov_y_deg = 40\n",
            cx - reach,
            cy - reach,
            cz + reach,
            cx + reach,
            cy - reach,
            cz + reach / 2.0,
        ),
    )
    .expect("camera path file");

    // The example on the scan through `address`, trusting the test's CA, with `options`,
    // writing into `out`; it must succeed.
    let run_trusting_the_ca = |address: &str, options: &[&str], out: &Path| {
        let mut args = vec![
            path_arg(&scan),
            "--server",
            address,
            "--tls-ca",
            path_arg(&pki.ca),
        ];
        args.extend(options);
        args.extend(["--out", path_arg(out)]);
        let output = run_example(&python, dir, &args);
        assert_succeeded(&output, &server);
        output
    };

    let out = dir.join("flight");
    let output = run_trusting_the_ca(
        &https,
        &[
            "--token-file",
            path_arg(&token_file),
            "--camera-path",
            path_arg(&camera_path),
            "--size",
            "64x48",
        ],
        &out,
    );
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(stdout.contains("5/5 frames"), "progress printed:\n{stdout}");
    let id = job_id(&output);
    let job = daemon_job(&https, &pki.ca, &id).await;
    assert_eq!(job.state, pb::JobState::Succeeded as i32, "{}", job.error);
    assert_eq!(job.frames_total, 5);
    let names = frames_in(&out, (64, 48));
    let expected: Vec<String> = (0..5).map(|i| format!("frame_{i:05}.png")).collect();
    assert_eq!(names, expected);

    // Without a camera path file: the flyover made from the file's header, the count given.
    let out = dir.join("flyover");
    // A bare address with a CA means TLS.
    let output = run_trusting_the_ca(
        &format!("localhost:{port}"),
        &["--token", TOKEN, "--frames", "3", "--size", "40x30"],
        &out,
    );
    let job = daemon_job(&https, &pki.ca, &job_id(&output)).await;
    assert_eq!(job.state, pb::JobState::Succeeded as i32, "{}", job.error);
    assert_eq!(frames_in(&out, (40, 30)).len(), job.frames_total as usize);
    assert_eq!(job.frames_total, 3);
}

#[test]
fn a_refused_call_ends_the_python_example_with_one_line_and_a_non_zero_exit() {
    let Some(python) = test_python(&["grpc", "grpc_tools"], "examples/python/requirements.txt")
    else {
        return;
    };
    let (scratch, scan) = scratch_sample("scan.las", 2_000, 8);
    let dir = scratch.path();
    // Nothing renders here: no worker.
    let mut server = ServeProcess::start_with(
        &dir.join("data"),
        &["--token", TOKEN, "--no-embedded-worker"],
    );
    let out = dir.join("frames");
    // A wrong token is refused at the upload; a path of no frames at the submission.
    for (token, more, says) in [
        (
            "not-the-token",
            &[][..],
            "unauthenticated: invalid bearer token",
        ),
        (
            TOKEN,
            &["--frames", "0"][..],
            "invalid argument: camera_path.keyframes.frames",
        ),
    ] {
        let mut args = vec![
            path_arg(&scan),
            "--server",
            &server.address,
            "--out",
            path_arg(&out),
        ];
        args.extend(["--token", token]);
        args.extend(more);
        let output = run_example(&python, dir, &args);
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert_eq!(output.status.code(), Some(1), "{}", show(&output));
        assert!(
            stderr.starts_with(&format!("pointfarm_client: {says}")),
            "{stderr}"
        );
        assert_eq!(stderr.lines().count(), 1, "one line: {stderr}");
    }
    assert!(!out.exists(), "no frames folder for a refused job");
    assert!(server.is_running(), "the daemon survives refused calls");
}

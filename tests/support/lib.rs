//! Helpers shared by the end-to-end tests: the `pointfarm` binary, the real scans and
//! generated LAS files.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::OnceLock;
use std::time::Duration;

use pointfarm_render::ingest::write_las;

/// The `pointfarm` binary of this workspace, built (or brought up to date) on first use with
/// the same profile as the running test.
pub fn pointfarm_bin() -> &'static Path {
    static BIN: OnceLock<PathBuf> = OnceLock::new();
    BIN.get_or_init(|| {
        // The test executable lives in target/<profile>/deps/.
        let exe = std::env::current_exe().expect("test executable path");
        let profile_dir = exe
            .parent()
            .and_then(Path::parent)
            .expect("target/<profile>");
        let release = profile_dir.file_name().is_some_and(|n| n == "release");
        let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
        let mut build = Command::new(cargo);
        // The environment of the cargo that built this test, without the variables cargo
        // gives a test of its package (CARGO_PKG_NAME, CARGO_MANIFEST_DIR, ...): a build
        // script that reruns when one of them changes (ring's) would otherwise rebuild
        // everything above it, here and again in the next `cargo test`.
        for (name, _) in std::env::vars_os() {
            let name = name.to_string_lossy();
            let of_the_package = name.starts_with("CARGO_PKG_")
                || [
                    "CARGO_MANIFEST_DIR",
                    "CARGO_MANIFEST_PATH",
                    "CARGO_CRATE_NAME",
                    "CARGO_PRIMARY_PACKAGE",
                    "CARGO_TARGET_TMPDIR",
                ]
                .contains(&&*name);
            if of_the_package {
                build.env_remove(&*name);
            }
        }
        build.args([
            "build",
            "--quiet",
            "-p",
            "pointfarm-cli",
            "--bin",
            "pointfarm",
        ]);
        if release {
            build.arg("--release");
        }
        let status = build.status().expect("run cargo build");
        assert!(status.success(), "building the pointfarm binary failed");
        let bin = profile_dir.join(format!("pointfarm{}", std::env::consts::EXE_SUFFIX));
        assert!(bin.is_file(), "{} missing after the build", bin.display());
        bin
    })
}

/// A path of a test's scratch folder as one argument of a command line.
pub fn path_arg(path: &Path) -> &str {
    path.to_str().expect("temporary paths are UTF-8")
}

/// Runs `pointfarm` with `args`.
pub fn pointfarm(args: &[&str]) -> Output {
    Command::new(pointfarm_bin())
        .args(args)
        .output()
        .expect("run pointfarm")
}

/// The `pointfarm` binary with `environment` (a server's endpoint and credentials, as its
/// `environment()` gives them), to be given its arguments.
pub fn pointfarm_with(environment: &[(&'static str, String)]) -> Command {
    let mut command = Command::new(pointfarm_bin());
    command.envs(environment.iter().map(|(name, value)| (*name, value)));
    command
}

/// Runs `pointfarm` with `args` and `environment`.
pub fn run_with(environment: &[(&'static str, String)], args: &[&str]) -> Output {
    pointfarm_with(environment)
        .args(args)
        .output()
        .expect("run pointfarm")
}

/// The files an `info --json` run that must have succeeded describes, each without its path,
/// and the paths, in the order told: what a folder and an object prefix of the same files
/// must say alike.
pub fn info_files(output: &Output) -> (Vec<serde_json::Value>, Vec<String>) {
    let text = output_text(output);
    assert!(output.status.success(), "{text}");
    let document: serde_json::Value =
        serde_json::from_slice(&output.stdout).unwrap_or_else(|e| panic!("{e}: {text}"));
    let mut files = document["files"].as_array().expect("files").clone();
    let paths = (files.iter_mut())
        .map(|file| {
            let path = file["path"].as_str().expect("a path").to_owned();
            file.as_object_mut().expect("a file").remove("path");
            path
        })
        .collect();
    (files, paths)
}

/// What a command printed on standard output.
pub fn stdout(output: &Output) -> String {
    String::from_utf8_lossy(&output.stdout).into_owned()
}

/// Both outputs of a command, for a failure's message.
pub fn output_text(output: &Output) -> String {
    format!(
        "{}\n{}",
        String::from_utf8_lossy(&output.stdout),
        String::from_utf8_lossy(&output.stderr)
    )
}

/// Runs `pointfarm` with `args` and fails, showing both outputs, unless it succeeded.
pub fn pointfarm_ok(args: &[&str]) -> Output {
    let output = pointfarm(args);
    assert!(
        output.status.success(),
        "pointfarm {args:?} failed:\n{}",
        output_text(&output)
    );
    output
}

/// A scene of `points` generated points sampled to `dir/scene.laz` and exported by `pointfarm
/// export --copc` to `dir/scene.copc.laz`, its cache in `dir/cache`: the scene and the COPC
/// file.
pub fn sampled_copc(dir: &Path, points: u64) -> (PathBuf, PathBuf) {
    let scene = dir.join("scene.laz");
    pointfarm_ok(&["sample", path_arg(&scene), "--points", &points.to_string()]);
    let copc = dir.join("scene.copc.laz");
    let cache = dir.join("cache");
    let export = ["export", path_arg(&scene), "--copc", path_arg(&copc)];
    pointfarm_ok(&[&export[..], &["--cache-dir", path_arg(&cache)]].concat());
    (scene, copc)
}

/// The camera flags `pointfarm render` printed (`camera: --camera-pos=...`), to render again
/// through the same camera.
pub fn printed_camera(output: &Output) -> Vec<String> {
    let text = output_text(output);
    let line = text
        .lines()
        .find_map(|line| line.strip_prefix("camera: "))
        .unwrap_or_else(|| panic!("no camera line in:\n{text}"));
    line.split_whitespace().map(str::to_owned).collect()
}

/// Standard output as JSON Lines: one object a line.
pub fn json_lines(output: &Output) -> Vec<serde_json::Value> {
    stdout(output)
        .lines()
        .map(|line| serde_json::from_str(line).expect("each line is one JSON object"))
        .collect()
}

/// Fails, showing both outputs, unless the command succeeded.
pub fn assert_ok(output: &Output) {
    assert!(
        output.status.success(),
        "pointfarm failed:\n{}\n{}",
        stdout(output),
        String::from_utf8_lossy(&output.stderr)
    );
}

/// Runs `command`, a program other than `pointfarm` that `what` names, and fails with its
/// standard error unless it succeeded; its output.
pub fn run_ok(command: &mut Command, what: &str) -> Output {
    let output = command
        .output()
        .unwrap_or_else(|e| panic!("{what} does not run: {e}"));
    assert!(
        output.status.success(),
        "{what} failed: {}",
        String::from_utf8_lossy(&output.stderr)
    );
    output
}

/// Fails unless the command failed, without a panic, and its standard error says `needle`.
pub fn assert_fails_saying(output: &Output, needle: &str) {
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(
        !output.status.success(),
        "expected a failure saying {needle}"
    );
    assert!(stderr.contains(needle), "{stderr}");
    assert!(!stderr.contains("panicked"), "{stderr}");
}

/// Asserts a failure told in one line: exactly one `error:` line on stderr, saying each of
/// `needles` (the URL or path it concerns, what went wrong), and no panic.
pub fn assert_one_error_line(output: &Output, needles: &[&str]) {
    for needle in needles {
        assert_fails_saying(output, needle);
    }
    let stderr = String::from_utf8_lossy(&output.stderr);
    let errors = stderr.lines().filter(|l| l.starts_with("error:")).count();
    assert_eq!(errors, 1, "{stderr}");
}

/// Asserts that the folders `expected` and `actual` hold the same `frames` frame files
/// (`frame_00000.png` on), pixel for pixel; `what` says what `actual` is.
pub fn assert_same_frames(expected: &Path, actual: &Path, frames: u32, what: &str) {
    for index in 0..frames {
        let name = format!("frame_{index:05}.png");
        let image = |folder: &Path| image::open(folder.join(&name)).expect("png").to_rgba8();
        assert!(image(expected) == image(actual), "{name} differs in {what}");
    }
}

/// Asserts that the PNG files `actual` and `expected` agree within 8/255 on at least 99% of
/// their pixels, as two renders of the same points by different paths do; `what` says what
/// differs where they do not. `name` names the difference image kept for a look.
pub fn assert_pngs_alike(name: &str, actual: &Path, expected: &Path, what: &str) {
    let image = |path: &Path| image::open(path).expect("png").to_rgba8();
    let diff =
        pointfarm_render::testing::compare_images_within(name, &image(actual), &image(expected), 8);
    assert!(
        diff.equal_fraction() >= 0.99,
        "{what}: {} pixels",
        diff.differing
    );
}

/// Runs `pointfarm` with `args` writing into a pipe nobody reads (`| head` after it ended),
/// and fails unless it still ends well and quietly.
pub fn run_into_a_closed_pipe(args: &[&str]) -> Output {
    let (reader, writer) = std::io::pipe().expect("pipe");
    drop(reader);
    let output = Command::new(pointfarm_bin())
        .args(args)
        .stdout(writer)
        .output()
        .expect("run pointfarm");
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(output.status.success(), "{:?}: {stderr}", output.status);
    assert!(!stderr.contains("panicked"), "{stderr}");
    output
}

pub use pointfarm_render::testing::{copc_file, shared_data};

/// The `key` of each object in the JSON array `array` (e.g. each stage's name), in order.
pub fn json_names<'a>(array: &'a serde_json::Value, key: &str) -> Vec<&'a str> {
    let items = array.as_array().map(Vec::as_slice).unwrap_or_default();
    items.iter().filter_map(|item| item[key].as_str()).collect()
}

/// Lines of stderr that are pointfarm's own, without what the Vulkan loader or drivers print
/// on their own (e.g. about XDG_RUNTIME_DIR on machines without a session).
pub fn own_stderr_lines(output: &Output) -> Vec<String> {
    String::from_utf8_lossy(&output.stderr)
        .lines()
        .filter(|l| !l.contains("XDG_RUNTIME_DIR"))
        .map(str::to_owned)
        .collect()
}

/// Whether `program` runs (asked its version with `version_flag`); where it does not, says
/// that the test is skipped and `what_installs_it`.
pub fn installed_or_skip(program: &str, version_flag: &str, what_installs_it: &str) -> bool {
    let found = Command::new(program).arg(version_flag).output().is_ok();
    if !found {
        eprintln!("skipped: {program} is not installed ({what_installs_it})");
    }
    found
}

/// `127.0.0.1:PORT` with a port that was free a moment ago.
pub fn free_address() -> String {
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|probe| probe.local_addr())
        .expect("a free loopback port")
        .port();
    format!("127.0.0.1:{port}")
}

/// `pointfarm serve` as a child process on a loopback port; killed when dropped. Its log and
/// its embedded worker's (at info level) are appended to `serve.log` in its data folder.
pub struct ServeProcess {
    pub address: String,
    child: std::process::Child,
    log: PathBuf,
}

impl ServeProcess {
    /// Starts a daemon on a free port with its data in `data_dir`, and waits until it listens.
    pub fn start(data_dir: &Path) -> Self {
        Self::start_at(&free_address(), data_dir)
    }

    /// Starts a daemon on `address` (e.g. again after a kill) and waits until it listens.
    pub fn start_at(address: &str, data_dir: &Path) -> Self {
        Self::start_with_args(address, data_dir, &[])
    }

    /// Starts a daemon on a free port with more `serve` arguments.
    pub fn start_with(data_dir: &Path, args: &[&str]) -> Self {
        Self::start_with_args(&free_address(), data_dir, args)
    }

    /// Starts a daemon on `address` with more `serve` arguments and waits until it listens.
    pub fn start_with_args(address: &str, data_dir: &Path, args: &[&str]) -> Self {
        Self::start_logging_to(address, data_dir, &data_dir.join("serve.log"), args)
    }

    /// Starts a daemon as [`ServeProcess::start_with_args`] does, its log in `log` (e.g. off a
    /// data folder on a disk that fills up).
    pub fn start_logging_to(address: &str, data_dir: &Path, log: &Path, args: &[&str]) -> Self {
        Self::start_command(Command::new(pointfarm_bin()), address, data_dir, log, args)
    }

    /// Starts a daemon on a free port with `environment` (a server's endpoint and credentials,
    /// which its embedded worker inherits) and more `serve` arguments.
    pub fn start_in_environment(
        environment: &[(&'static str, String)],
        data_dir: &Path,
        args: &[&str],
    ) -> Self {
        let log = data_dir.join("serve.log");
        let command = pointfarm_with(environment);
        Self::start_command(command, &free_address(), data_dir, &log, args)
    }

    /// Starts a daemon on a free port whose open-file limit, soft and hard, is `open_files`
    /// (so that it cannot raise it), with more `serve` arguments.
    pub fn start_with_open_file_limit(data_dir: &Path, open_files: u32, args: &[&str]) -> Self {
        let mut shell = Command::new("sh");
        shell
            .arg("-c")
            .arg(format!("ulimit -n {open_files} && exec \"$0\" \"$@\""))
            .arg(pointfarm_bin());
        let log = data_dir.join("serve.log");
        Self::start_command(shell, &free_address(), data_dir, &log, args)
    }

    /// Starts `command` (the `pointfarm` binary, e.g. with more environment) as
    /// `pointfarm serve` on `address` with its data in `data_dir`, its log in `log`, with more
    /// `serve` arguments, and waits until it listens.
    pub fn start_command(
        mut command: Command,
        address: &str,
        data_dir: &Path,
        log: &Path,
        args: &[&str],
    ) -> Self {
        std::fs::create_dir_all(data_dir).expect("data folder");
        let log = log.to_path_buf();
        let log_file = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&log)
            .expect("serve log file");
        let child = command
            .args(["serve", "--listen", address, "--data-dir"])
            .arg(data_dir)
            .args(args)
            .env("RUST_LOG", "warn,pointfarm=info")
            .env("NO_COLOR", "1")
            .stdout(std::process::Stdio::null())
            .stderr(log_file)
            .spawn()
            .expect("start pointfarm serve");
        let server = Self {
            address: address.to_string(),
            child,
            log,
        };
        tools::wait_until_listening(address, Duration::from_secs(30), "pointfarm serve");
        server
    }

    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    /// The job `id` as `jobs show --json` prints it (the API's JSON mapping).
    pub fn job_json(&self, id: &str) -> serde_json::Value {
        let shown = pointfarm_ok(&["jobs", "show", id, "--server", &self.address, "--json"]);
        let mut shown: serde_json::Value =
            serde_json::from_slice(&shown.stdout).expect("a job as JSON");
        shown["job"].take()
    }

    /// `frames fetch ID --out OUT` against this daemon.
    pub fn fetch_frames(&self, id: &str, out: &Path) -> Output {
        let args = [
            "frames",
            "fetch",
            id,
            "--out",
            path_arg(out),
            "--server",
            &self.address,
        ];
        pointfarm(&args)
    }

    /// What the daemon and its embedded worker have logged, across restarts on this folder.
    pub fn log(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }

    /// The process ids of the embedded workers this folder's daemons started, oldest first.
    pub fn embedded_worker_pids(&self) -> Vec<u32> {
        self.log()
            .lines()
            .filter(|line| line.contains("embedded worker started"))
            .filter_map(|line| line.split("pid=").nth(1))
            .filter_map(|rest| rest.split_whitespace().next()?.parse().ok())
            .collect()
    }

    /// The newest embedded worker's process id, once it has started (waiting up to 60 s).
    pub fn embedded_worker_pid(&self) -> u32 {
        wait_for(Duration::from_secs(60), "an embedded worker", || {
            self.embedded_worker_pids().last().copied()
        })
    }

    /// Whether the daemon is still running.
    pub fn is_running(&mut self) -> bool {
        matches!(self.child.try_wait(), Ok(None))
    }

    /// `kill -9`, and reap it.
    pub fn kill(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }

    /// Sends SIGTERM and waits up to `timeout` for the exit.
    pub fn terminate(&mut self, timeout: Duration) -> Option<std::process::ExitStatus> {
        terminate(&mut self.child, timeout)
    }

    /// Waits up to `timeout` for the process to exit by itself.
    pub fn wait_for_exit(
        &mut self,
        timeout: std::time::Duration,
    ) -> Option<std::process::ExitStatus> {
        exit_within(&mut self.child, timeout)
    }
}

impl Drop for ServeProcess {
    fn drop(&mut self) {
        self.kill();
    }
}

/// `pointfarm worker` as a child process rendering for `server`; killed when dropped. Its
/// log (at info level) goes to a file, shown by [`WorkerProcess::log`].
pub struct WorkerProcess {
    child: std::process::Child,
    log: PathBuf,
}

impl WorkerProcess {
    /// Starts a worker named `name` with its dataset cache in `cache_dir`.
    pub fn start(server: &str, cache_dir: &Path, name: &str) -> Self {
        Self::start_with(server, cache_dir, name, &[])
    }

    /// Starts a worker with more `worker` arguments (e.g. `--token`).
    pub fn start_with(server: &str, cache_dir: &Path, name: &str, args: &[&str]) -> Self {
        Self::start_in(Command::new(pointfarm_bin()), server, cache_dir, name, args)
    }

    /// Starts `command` (the `pointfarm` binary, e.g. with object storage's credentials in
    /// its environment) as [`WorkerProcess::start_with`] starts a worker.
    pub fn start_in(
        mut command: Command,
        server: &str,
        cache_dir: &Path,
        name: &str,
        args: &[&str],
    ) -> Self {
        let log = cache_dir.with_extension("log");
        let log_file = std::fs::File::create(&log).expect("worker log file");
        let child = command
            .args([
                "-v",
                "worker",
                "--server",
                server,
                "--name",
                name,
                "--cache-dir",
            ])
            .arg(cache_dir)
            .args(args)
            .stdout(std::process::Stdio::null())
            .stderr(log_file)
            .spawn()
            .expect("start pointfarm worker");
        Self { child, log }
    }

    pub fn log(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }

    /// `kill -9`, and reap it.
    pub fn kill(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }

    /// Sends SIGTERM and waits up to `timeout` for the exit.
    pub fn terminate(&mut self, timeout: Duration) -> Option<std::process::ExitStatus> {
        terminate(&mut self.child, timeout)
    }
}

impl Drop for WorkerProcess {
    fn drop(&mut self) {
        self.kill();
    }
}

pub mod azurite;
pub mod datasets;
pub mod fake_gcs;
pub mod flights;
pub mod health;
pub mod nginx;
pub mod object_faults;
pub mod pki;
pub mod prometheus;
pub mod rest;
pub mod s3s;
pub mod service;
pub mod stores;
pub mod tiles;
pub mod tools;

/// Sends SIGTERM to `child` and waits up to `timeout` for its exit.
fn terminate(
    child: &mut std::process::Child,
    timeout: Duration,
) -> Option<std::process::ExitStatus> {
    signal(child.id(), "TERM");
    exit_within(child, timeout)
}

/// Sends `signal` (`KILL`, `TERM`) to the process `pid`, which must exist.
pub fn signal(pid: u32, signal: &str) {
    let sent = Command::new("kill")
        .args([format!("-{signal}"), pid.to_string()])
        .status()
        .expect("kill");
    assert!(sent.success(), "kill -{signal} {pid}");
}

/// Whether the process `pid` has ended (a zombie that nobody reaps has ended too).
pub fn process_is_gone(pid: u32) -> bool {
    match std::fs::read_to_string(format!("/proc/{pid}/stat")) {
        // The state follows the parenthesised command name.
        Ok(stat) => stat
            .rsplit_once(") ")
            .is_some_and(|(_, rest)| rest.starts_with('Z') || rest.starts_with('X')),
        Err(_) => true,
    }
}

/// Polls `probe` until it gives a value, panicking after `timeout` with what was awaited.
pub fn wait_for<T>(timeout: Duration, awaited: &str, mut probe: impl FnMut() -> Option<T>) -> T {
    let deadline = std::time::Instant::now() + timeout;
    loop {
        if let Some(value) = probe() {
            return value;
        }
        assert!(
            std::time::Instant::now() < deadline,
            "no {awaited} within {timeout:?}"
        );
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// Writes a LAZ file of `points` points in runs of equal points: it compresses to a small
/// file, but its decoded points need `points` times about 20 bytes of memory.
pub fn write_dense_laz(path: &Path, points: usize) {
    use pointfarm_render::cloud::PointCloud;
    let tile = pointfarm_render::sample::sample_scene(1_000, 1);
    let run = points.div_ceil(tile.len());
    let repeated = |i: usize| i / run;
    let cloud = PointCloud {
        positions: (0..points).map(|i| tile.positions[repeated(i)]).collect(),
        colors: (0..points).map(|i| tile.colors[repeated(i)]).collect(),
        intensity: vec![0; points],
        classification: vec![2; points],
        return_number: vec![1; points],
        ..tile
    };
    write_las(
        path,
        &cloud,
        &pointfarm_render::ingest::LasWriteOptions {
            point_format: 0,
            ..Default::default()
        },
    )
    .expect("write the dense LAZ");
}

/// The child's exit status once it has exited, waiting at most `timeout`.
fn exit_within(
    child: &mut std::process::Child,
    timeout: std::time::Duration,
) -> Option<std::process::ExitStatus> {
    let deadline = std::time::Instant::now() + timeout;
    while std::time::Instant::now() < deadline {
        if let Ok(Some(status)) = child.try_wait() {
            return Some(status);
        }
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    None
}

/// The Python of the tests' virtualenv that can import `modules`: `POINTFARM_PYTHON`, else
/// `python-venv` in this build's target folder. `None` (after saying so) when it is missing
/// or lacks them; a `POINTFARM_PYTHON` given but unusable fails instead. `requirements` names
/// the file `deploy/test.sh` installs them from.
pub fn test_python(modules: &[&str], requirements: &str) -> Option<PathBuf> {
    let given = std::env::var_os("POINTFARM_PYTHON").map(PathBuf::from);
    let python = given.clone().unwrap_or_else(|| {
        // The test executable lives in target/<profile>/deps/.
        let exe = std::env::current_exe().expect("test executable path");
        let target = exe.ancestors().nth(3).expect("the target folder");
        target.join("python-venv/bin/python")
    });
    let usable = Command::new(&python)
        .args(["-c", &format!("import {}", modules.join(", "))])
        .output()
        .is_ok_and(|output| output.status.success());
    match (usable, given) {
        (true, _) => Some(python),
        (false, Some(_)) => panic!(
            "POINTFARM_PYTHON={} cannot import {}",
            python.display(),
            modules.join(" and ")
        ),
        (false, None) => {
            eprintln!(
                "skipped: no Python with {} at {} (deploy/test.sh makes it from {requirements})",
                modules.join(" and "),
                python.display()
            );
            None
        }
    }
}

//! Helpers shared by the end-to-end tests: the `pointfarm` binary, the real scans and
//! generated LAS files.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::OnceLock;

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

/// Runs `pointfarm` with `args`.
pub fn pointfarm(args: &[&str]) -> Output {
    Command::new(pointfarm_bin())
        .args(args)
        .output()
        .expect("run pointfarm")
}

pub use pointfarm_render::testing::shared_data;

/// Lines of stderr that are pointfarm's own, without what the Vulkan loader or drivers print
/// on their own (e.g. about XDG_RUNTIME_DIR on machines without a session).
pub fn own_stderr_lines(output: &Output) -> Vec<String> {
    String::from_utf8_lossy(&output.stderr)
        .lines()
        .filter(|l| !l.contains("XDG_RUNTIME_DIR"))
        .map(str::to_owned)
        .collect()
}

/// `pointfarm serve` as a child process on a loopback port; killed when dropped.
pub struct ServeProcess {
    pub address: String,
    child: std::process::Child,
}

impl ServeProcess {
    /// Starts a daemon on a free port with its data in `data_dir`, and waits until it listens.
    pub fn start(data_dir: &Path) -> Self {
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .and_then(|probe| probe.local_addr())
            .expect("a free loopback port")
            .port();
        Self::start_at(&format!("127.0.0.1:{port}"), data_dir)
    }

    /// Starts a daemon on `address` (e.g. again after a kill) and waits until it listens.
    pub fn start_at(address: &str, data_dir: &Path) -> Self {
        Self::start_with_args(address, data_dir, &[])
    }

    /// Starts a daemon on a free port with more `serve` arguments.
    pub fn start_with(data_dir: &Path, args: &[&str]) -> Self {
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .and_then(|probe| probe.local_addr())
            .expect("a free loopback port")
            .port();
        Self::start_with_args(&format!("127.0.0.1:{port}"), data_dir, args)
    }

    fn start_with_args(address: &str, data_dir: &Path, args: &[&str]) -> Self {
        let child = Command::new(pointfarm_bin())
            .args(["serve", "--listen", address, "--data-dir"])
            .arg(data_dir)
            .args(args)
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .spawn()
            .expect("start pointfarm serve");
        let server = Self {
            address: address.to_string(),
            child,
        };
        for _ in 0..300 {
            if std::net::TcpStream::connect(address).is_ok() {
                return server;
            }
            std::thread::sleep(std::time::Duration::from_millis(100));
        }
        panic!("pointfarm serve did not listen on {address} within 30 s");
    }

    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    /// `kill -9`, and reap it.
    pub fn kill(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
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
        let log = cache_dir.with_extension("log");
        let log_file = std::fs::File::create(&log).expect("worker log file");
        let child = Command::new(pointfarm_bin())
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
    pub fn terminate(&mut self, timeout: std::time::Duration) -> Option<std::process::ExitStatus> {
        let sent = Command::new("kill")
            .args(["-TERM", &self.child.id().to_string()])
            .status()
            .expect("kill -TERM");
        assert!(sent.success());
        exit_within(&mut self.child, timeout)
    }
}

impl Drop for WorkerProcess {
    fn drop(&mut self) {
        self.kill();
    }
}

pub mod service;

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

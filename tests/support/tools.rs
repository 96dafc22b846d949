//! Finding a server binary that deploy/test.sh installs, named by a variable: a test without
//! it skips on a developer's machine, saying so, and fails in CI, where the setup must have
//! installed it.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::time::{Duration, Instant};

/// The file the variable `variable` names, or None, having said that `what` is skipped.
/// Panics where `CI` is set, so that a missing install fails the run instead of hiding.
pub fn tool_or_skip(variable: &str, what: &str) -> Option<PathBuf> {
    let binary = std::env::var_os(variable)
        .map(PathBuf::from)
        .filter(|path| path.is_file());
    if binary.is_none() {
        assert!(
            std::env::var_os("CI").is_none(),
            "{variable} names no {what} binary, and CI must run these tests (deploy/test.sh \
             installs it)"
        );
        eprintln!("skipped: {variable} names no {what} binary (deploy/test.sh installs it)");
    }
    binary
}

/// Waits until something listens on `address`, failing the test naming `what` after
/// `timeout`.
pub fn wait_until_listening(address: &str, timeout: Duration, what: &str) {
    let started = Instant::now();
    while std::net::TcpStream::connect(address).is_err() {
        assert!(
            started.elapsed() < timeout,
            "{what} did not listen on {address}"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// A server deploy/test.sh installs, on a free loopback port with a folder of its own; when
/// dropped the server is killed, then the folder removed.
pub struct ToolServer {
    pub address: String,
    _child: ServerChild,
    pub folder: tempfile::TempDir,
}

impl ToolServer {
    /// Starts the binary `variable` names as `what`, given its arguments by `args(command,
    /// host, port, folder)`, and waits up to `timeout` until it listens; or None, having said
    /// why, without the binary (a failure in CI).
    pub fn start_or_skip(
        variable: &str,
        what: &str,
        timeout: Duration,
        args: impl FnOnce(&mut Command, &str, &str, &Path),
    ) -> Option<Self> {
        let binary = tool_or_skip(variable, what)?;
        let folder = tempfile::tempdir().expect("the server's folder");
        let address = crate::free_address();
        let (host, port) = address.split_once(':').expect("host:port");
        let mut command = Command::new(&binary);
        args(&mut command, host, port, folder.path());
        let child = ServerChild::start_listening(&mut command, &address, timeout, what);
        Some(Self {
            address,
            _child: child,
            folder,
        })
    }
}

/// A server's child process, killed and reaped when dropped, whether the test passes or not.
/// A struct that holds it declares it before the folders the server uses, so that the server
/// stops before they go.
pub struct ServerChild(Child);

impl ServerChild {
    /// Starts `command` as `what`, its standard output discarded.
    pub fn spawn(command: &mut Command, what: &str) -> Self {
        let child = command
            .stdout(Stdio::null())
            .spawn()
            .unwrap_or_else(|e| panic!("start {what}: {e}"));
        Self(child)
    }

    /// Starts `command` as `what`, both its outputs discarded, and waits until it listens on
    /// `address` (which its arguments name), failing the test after `timeout`.
    pub fn start_listening(
        command: &mut Command,
        address: &str,
        timeout: Duration,
        what: &str,
    ) -> Self {
        let server = Self::spawn(command.stderr(Stdio::null()), what);
        wait_until_listening(address, timeout, what);
        server
    }

    /// How the server exited, where it has.
    pub fn exited(&mut self) -> Option<ExitStatus> {
        self.0.try_wait().ok().flatten()
    }
}

impl Drop for ServerChild {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

//! Finding a server binary that deploy/test.sh installs, named by a variable: a test without
//! it skips on a developer's machine, saying so, and fails in CI, where the setup must have
//! installed it.

use std::path::PathBuf;
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

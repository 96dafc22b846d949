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

/// A file in `../shared/data/`, or None (with a message) when that folder is absent.
pub fn shared_data(file: &str) -> Option<PathBuf> {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../shared/data")
        .join(file);
    if path.is_file() {
        Some(path)
    } else {
        eprintln!(
            "skipped: {} not found (the real scans live in ../shared/data)",
            path.display()
        );
        None
    }
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

pub mod service;

//! The child side of a corpus run: loads one file and reports on stdout, in one line, what
//! happened and the process's peak resident memory. A panic that escapes reports from the
//! panic hook first; an abort reports nothing, and the runner's own samples stand in.
//!
//! The peak is the kernel's `VmHWM` from `/proc/self/status`: exact, with no `unsafe` (which
//! the workspace forbids) and no crate for `wait4`'s resource usage.

use std::fs;
use std::path::Path;

use pointfarm_render::ingest::{load_point_cloud, IngestError};

/// The first word of a report line.
pub const LOADED: &str = "loaded";
pub const ERROR: &str = "error";
pub const CONTAINED: &str = "contained";
pub const PANIC: &str = "panic";

/// The exit status of a clean error (a panic exits with 101, an abort by a signal).
pub const ERROR_EXIT: i32 = 2;

/// Loads `path` and prints `<outcome> <peak KiB> <detail>`; gives the exit status.
pub fn load_and_report(path: &Path) -> i32 {
    std::panic::set_hook(Box::new(|info| {
        let peak = peak_kib(Path::new("/proc/self/status")).unwrap_or(0);
        println!("{PANIC} {peak} {}", info.to_string().replace('\n', " "));
    }));
    let result = load_point_cloud(path);
    let peak = peak_kib(Path::new("/proc/self/status")).unwrap_or(0);
    match result {
        Ok(cloud) => {
            println!("{LOADED} {peak} {} points", cloud.len());
            0
        }
        Err(error) => {
            let outcome = match error {
                IngestError::DecoderPanicked { .. } => CONTAINED,
                _ => ERROR,
            };
            println!("{outcome} {peak} {error}");
            ERROR_EXIT
        }
    }
}

/// The peak resident set (`VmHWM`) in a `/proc/<pid>/status` file, in KiB.
pub fn peak_kib(status: &Path) -> Option<u64> {
    let status = fs::read_to_string(status).ok()?;
    let line = status.lines().find(|line| line.starts_with("VmHWM:"))?;
    line.split_whitespace().nth(1)?.parse().ok()
}

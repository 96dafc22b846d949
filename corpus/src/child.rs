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
    peak_in(&fs::read_to_string(status).ok()?)
}

/// The peak of a child from its `/proc/<pid>/status`, once it runs the program `name`: between
/// the fork and the exec the status describes a copy of the parent (a test process holding
/// hundreds of megabytes), which is not the child's memory.
pub fn exec_peak_kib(status: &Path, name: &str) -> Option<u64> {
    let status = fs::read_to_string(status).ok()?;
    let running = status.lines().find_map(|line| line.strip_prefix("Name:"))?;
    // The kernel keeps the first 15 bytes of a program's name.
    let expected = &name.as_bytes()[..name.len().min(15)];
    if running.trim().as_bytes() != expected {
        return None;
    }
    peak_in(&status)
}

fn peak_in(status: &str) -> Option<u64> {
    let line = status.lines().find(|line| line.starts_with("VmHWM:"))?;
    line.split_whitespace().nth(1)?.parse().ok()
}

#[cfg(test)]
mod peak_tests {
    use super::*;

    #[test]
    fn a_child_counts_only_once_it_runs_its_program() {
        let dir = tempfile::tempdir().expect("tempdir");
        let status = dir.path().join("status");
        let write = |name: &str| {
            fs::write(&status, format!("Name:\t{name}\nVmHWM:\t  1118440 kB\n")).expect("write")
        };
        write("fast_subset-3f2");
        assert_eq!(
            exec_peak_kib(&status, "pointfarm-corpus"),
            None,
            "still the parent"
        );
        write("pointfarm-corpu");
        assert_eq!(exec_peak_kib(&status, "pointfarm-corpus"), Some(1_118_440));
        assert_eq!(peak_kib(&status), Some(1_118_440));
    }
}

//! The `pointfarm` commands (render, sample, demo, serve, worker, bench), run as a user would:
//! on local files, through the service, and the benchmark; the helpers they share.

mod bench;
mod local;
mod service;

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

/// The JSON file a command wrote.
fn read_json(path: &Path) -> serde_json::Value {
    serde_json::from_slice(&std::fs::read(path).expect("json written")).expect("valid json")
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

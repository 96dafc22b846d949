//! A flythrough through the daemon over a campaign of 20 tiles that sees one or two of them: the
//! daemon builds the store of the tiles its frames see first and leases every frame against
//! it, then, once the first frame is in, grows the dataset's whole store from it. With the
//! whole store's growth stopped for good (`POINTFARM_TEST_PAUSE_AT=update:0`) the job still
//! finishes, so its frames were drawn before the whole store existed; the daemon killed there
//! and started again, with no job asking, grows the whole store from the part its record
//! names, never serving a half-made store, and removes the part; deleting the dataset takes
//! every store down; the frames equal a flight drawn from a store built whole first, within
//! the fidelity rule. A flight that asks never to build the unseen tiles (`--build-unseen
//! never`) finishes from its part with no whole store built, across a restart too, until a
//! job that needs the whole store has it grown.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::time::Duration;

use pointfarm_render::cut::StoredLod;
use pointfarm_tests::flights::{write_tiles_and_flight_over_one_tile, COLUMNS, ROWS};
use pointfarm_tests::stores::serve_pausing_at;
use pointfarm_tests::{
    assert_pngs_alike, free_address, output_text, pointfarm_bin, pointfarm_ok, wait_for,
    ServeProcess,
};

const POINTS: usize = 1_000_000;
/// Enough for a store cut at pixel error 0, fewer for a flight whose whole store waits.
const NEVER_POINTS: usize = 300_000;
const FRAMES: usize = 3;

/// `pointfarm serve` with its data in `data`, logging to `log`, its builds stopped for good at
/// `pause_at`.
fn serve(address: &str, data: &Path, log: &str, pause_at: Option<&str>) -> ServeProcess {
    let log = data.with_file_name(log);
    let budget = ["--store-memory-budget", "96MiB"];
    serve_pausing_at(address, (data, &log), &budget, pause_at)
}

/// `pointfarm render --server` of `tiles` into `out` through levels of detail, to its end.
fn render(server: &ServeProcess, tiles: &Path, out: &Path, camera: &[&str]) -> Output {
    let mut command = Command::new(pointfarm_bin());
    command.arg("render").arg(tiles).arg("--out").arg(out);
    command.args(["--size=160x120", "--lod-error=0", "--point-size=2"]);
    command.arg(format!("--server=http://{}", server.address));
    command.args(camera).env_remove("POINTFARM_TEST_PAUSE_AT");
    let output = command.output().expect("run pointfarm");
    let log = server.log();
    assert!(
        output.status.success(),
        "{}\n--- daemon:\n{log}",
        output_text(&output)
    );
    output
}

/// The finished stores under `data`, each with how many files it lists.
fn finished_stores(data: &Path) -> Vec<(PathBuf, usize)> {
    let Ok(entries) = std::fs::read_dir(data.join("lod")) else {
        return Vec::new();
    };
    entries
        .map(|entry| entry.expect("entry").path())
        .filter(|path| StoredLod::is_built(path))
        .map(|path| {
            let list = std::fs::read_to_string(path.join("contents.txt")).unwrap_or_default();
            let files = list.lines().count();
            (path, files)
        })
        .collect()
}

/// Seconds from the first line of `log` saying `from` to the first after it saying `to`, by
/// their timestamps (`2026-01-02T03:04:05.678Z`, one day).
fn seconds_between(log: &str, from: &str, to: &str) -> f64 {
    let time = |line: &str| -> f64 {
        let clock = line.split_once('T').expect("a timestamp").1;
        let clock = clock.split_once('Z').expect("a timestamp").0;
        let parts: Vec<f64> = clock
            .split(':')
            .map(|p| p.parse().expect("a number"))
            .collect();
        parts[0] * 3600.0 + parts[1] * 60.0 + parts[2]
    };
    let mut lines = log.lines().skip_while(|l| !l.contains(from));
    let start = time(
        lines
            .next()
            .unwrap_or_else(|| panic!("no {from:?} in\n{log}")),
    );
    let end = lines
        .find(|l| l.contains(to))
        .unwrap_or_else(|| panic!("no {to:?} in\n{log}"));
    time(end) - start
}

/// Deletes every dataset the jobs of `server` rendered.
fn delete_datasets(server: &ServeProcess) {
    let listed = pointfarm_ok(&["jobs", "list", "--server", &server.address, "--json"]);
    let jobs: serde_json::Value = serde_json::from_slice(&listed.stdout).expect("json");
    let mut ids: Vec<&str> = jobs["jobs"]
        .as_array()
        .expect("jobs")
        .iter()
        .map(|job| job["datasetId"].as_str().expect("a dataset id"))
        .collect();
    ids.sort_unstable();
    ids.dedup();
    for id in ids {
        pointfarm_ok(&["dataset", "rm", id, "--server", &server.address]);
    }
}

/// What the daemon logs when it removes a part.
const PART_REMOVED: &str = "camera first: the part's store is removed";

/// Every store folder under `data`, finished or not.
fn store_folders(data: &Path) -> Vec<PathBuf> {
    let Ok(entries) = std::fs::read_dir(data.join("lod")) else {
        return Vec::new();
    };
    entries
        .map(|entry| entry.expect("entry").path())
        .filter(|path| path.is_dir())
        .collect()
}

/// The id of the one job of `server`.
fn only_job(server: &ServeProcess) -> String {
    let listed = pointfarm_ok(&["jobs", "list", "--server", &server.address, "--json"]);
    let jobs: serde_json::Value = serde_json::from_slice(&listed.stdout).expect("json");
    let jobs = jobs["jobs"].as_array().expect("jobs");
    assert_eq!(jobs.len(), 1, "{jobs:?}");
    jobs[0]["id"].as_str().expect("an id").to_owned()
}

fn frame(out: &Path, index: usize) -> PathBuf {
    out.join(format!("frame_{index:05}.png"))
}

#[test]
fn a_flight_through_the_daemon_is_drawn_from_the_tiles_it_sees_before_the_whole_store() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (tiles, flight, _) = write_tiles_and_flight_over_one_tile(dir.path(), POINTS, FRAMES);
    let camera = ["--camera-path", flight.to_str().expect("a UTF-8 path")];
    let all = COLUMNS * ROWS;

    // The whole store's growth stops for good: every frame comes from the part.
    let (address, data) = (free_address(), dir.path().join("daemon"));
    let mut server = serve(&address, &data, "first.log", Some("update:0"));
    let first = dir.path().join("first");
    render(&server, &tiles, &first, &camera);
    let first_seconds = seconds_between(&server.log(), "job submitted", "frame handed in");
    wait_for(Duration::from_secs(300), "the paused growth", || {
        server
            .log()
            .contains("build paused at update:0")
            .then_some(())
    });
    let log = server.log();
    assert!(log.contains("camera first: the store of the"), "{log}");
    assert!(!log.contains("updated the store of"), "{log}");
    // The whole store starts growing only once the first frame is in, which has the cores.
    let at = |line: &str| {
        log.find(line)
            .unwrap_or_else(|| panic!("no {line:?} in\n{log}"))
    };
    assert!(
        at("frame handed in") < at("build paused at update:0"),
        "{log}"
    );
    let stores = finished_stores(&data);
    assert_eq!(stores.len(), 1, "{stores:?}\n{log}");
    let seen = stores[0].1;
    assert!(seen > 0 && seen <= 2, "the part holds {seen} tiles");

    // Killed while it grows the whole store, and started again with no job asking: the
    // whole store is grown anew from the part, which is removed then.
    server.kill();
    let server = serve(&address, &data, "again.log", None);
    // The grown store is moved into place, then opened and marked finished: both are waited for.
    wait_for(Duration::from_secs(300), "the whole store", || {
        let log = server.log();
        let grown = log.contains("updated the store of") && log.contains(PART_REMOVED);
        let finished = finished_stores(&data)
            .iter()
            .any(|(_, files)| *files == all);
        (grown && finished).then_some(())
    });
    let log = server.log();
    assert!(
        log.contains("growing the whole store a stopped daemon left"),
        "{log}"
    );
    let growing = std::fs::read_dir(data.join("lod"))
        .expect("stores")
        .filter(|e| {
            let name = e.as_ref().expect("entry").file_name();
            name.to_string_lossy().ends_with(".growing")
        })
        .count();
    assert_eq!(growing, 0, "a half-made store is left");
    assert!(
        log.contains(&format!("{} files added, 0 removed", all - seen)),
        "{log}"
    );
    let stores = store_folders(&data);
    assert_eq!(stores.len(), 1, "the part is left: {stores:?}\n{log}");

    // A second flight reads the whole store.
    let again = dir.path().join("again");
    render(&server, &tiles, &again, &camera);
    assert!(!server.log().contains("camera first: the store of"));

    // A still view waits for the whole store, ready now; the datasets deleted, no store is
    // left, the part's with the whole one's.
    render(&server, &tiles, &dir.path().join("again.png"), &[]);
    delete_datasets(&server);
    let left = finished_stores(&data);
    assert!(left.is_empty(), "stores left: {left:?}\n{}", server.log());

    // A fresh daemon builds the whole store first (a still view does), then the flight.
    let whole_data = dir.path().join("whole-daemon");
    let whole_server = serve(&free_address(), &whole_data, "whole.log", None);
    render(&whole_server, &tiles, &dir.path().join("still.png"), &[]);
    let whole_log = whole_server.log();
    let whole_seconds = seconds_between(&whole_log, "job submitted", "frame handed in");
    let build_seconds = seconds_between(&whole_log, "building the dataset's levels", "store ready");
    let whole = dir.path().join("whole");
    render(&whole_server, &tiles, &whole, &camera);
    assert!(!whole_server.log().contains("camera first"));
    for i in 0..FRAMES {
        let message =
            "a frame drawn camera first through the daemon differs from the whole store's";
        assert_pngs_alike(
            "daemon-camera-first",
            &frame(&first, i),
            &frame(&whole, i),
            message,
        );
        assert_pngs_alike(
            "daemon-camera-first-again",
            &frame(&again, i),
            &frame(&whole, i),
            message,
        );
    }
    println!(
        "{POINTS} points in {all} tiles, a flight seeing {seen}: its first final frame camera \
         first through the daemon {first_seconds:.2} s after the job's submission; the whole \
         build {build_seconds:.2} s, a still view's first frame on it {whole_seconds:.2} s \
         after its job's submission; {:.1}% of the whole build",
        100.0 * first_seconds / build_seconds
    );
}

#[test]
fn a_flight_that_never_builds_the_unseen_tiles_leaves_the_whole_store_to_jobs_that_need_it() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (tiles, flight, _) = write_tiles_and_flight_over_one_tile(dir.path(), NEVER_POINTS, FRAMES);
    let flight = flight.to_str().expect("a UTF-8 path");
    let camera = ["--camera-path", flight, "--build-unseen", "never"];

    // The job finishes from its part, and no whole store is grown for it.
    let (address, data) = (free_address(), dir.path().join("daemon"));
    let mut server = serve(&address, &data, "never.log", None);
    render(&server, &tiles, &dir.path().join("never"), &camera);
    let log = server.log();
    assert!(log.contains("camera first: the store of"), "{log}");
    assert!(!log.contains("updated the store of"), "{log}");
    let stores = finished_stores(&data);
    assert_eq!(stores.len(), 1, "{stores:?}\n{log}");
    assert!(stores[0].1 <= 2, "the part holds {} tiles", stores[0].1);
    assert_eq!(
        store_folders(&data).len(),
        1,
        "a whole store was started\n{log}"
    );

    // The job's record shows its choice.
    let id = only_job(&server);
    let shown = pointfarm_ok(&["jobs", "show", &id, "--server", &address, "--json"]);
    let shown: serde_json::Value = serde_json::from_slice(&shown.stdout).expect("a job as JSON");
    assert_eq!(shown["job"]["buildUnseen"], "BUILD_UNSEEN_NEVER");
    let shown = pointfarm_ok(&["jobs", "show", &id, "--server", &address]);
    assert!(
        output_text(&shown).contains("build unseen: never"),
        "{}",
        output_text(&shown)
    );

    // Killed and started again, the daemon keeps the part and grows nothing.
    server.kill();
    let server = serve(&address, &data, "never-again.log", None);
    let log = server.log();
    assert!(!log.contains("growing the whole store"), "{log}");
    assert!(!log.contains(PART_REMOVED), "{log}");
    assert_eq!(store_folders(&data), vec![stores[0].0.clone()]);

    // A still view needs the whole store: it is grown from the part, as for any job.
    render(&server, &tiles, &dir.path().join("still.png"), &[]);
    let log = server.log();
    let all = COLUMNS * ROWS;
    assert!(
        log.contains(&format!("{} files added, 0 removed", all - stores[0].1)),
        "{log}"
    );
    delete_datasets(&server);
    let left = store_folders(&data);
    assert!(left.is_empty(), "stores left: {left:?}\n{}", server.log());
}

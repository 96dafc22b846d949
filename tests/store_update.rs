//! A folder of tiles that gains, loses or replaces a tile: `pointfarm render` through levels of
//! detail updates the store of the earlier tiles instead of building it anew, and the frames
//! equal a fresh build's within the fidelity rule. An update killed with SIGKILL where it is about to switch
//! to the new store (the build's test hook, `POINTFARM_TEST_PAUSE_AT=update:0`) leaves the
//! old store whole: the next render updates it again.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::time::Duration;

use pointfarm_render::ingest::{write_las, LasWriteOptions};
use pointfarm_render::sample::sample_scene;
use pointfarm_tests::stores::kill_build_at;
use pointfarm_tests::tiles::ground_plan_tiles;
use pointfarm_tests::{assert_pngs_alike, output_text, path_arg, pointfarm_bin, printed_camera};

/// Tiles per axis: the middle one is the new day's.
const SIDE: usize = 3;
const POINTS: usize = 90_000;
const SIZE: &str = "--size=200x150";

/// The scene cut into `SIDE` x `SIDE` tiles: all but the middle one in `dir/tiles`, the
/// middle one in `dir/later`. Returns both folders.
fn write_tiles(dir: &Path) -> (PathBuf, PathBuf) {
    let cloud = sample_scene(POINTS, 5);
    let tiles = ground_plan_tiles(&cloud, SIDE, SIDE);
    let (now, later) = (dir.join("tiles"), dir.join("later"));
    for folder in [&now, &later] {
        std::fs::create_dir_all(folder).expect("folder");
    }
    let middle = SIDE * SIDE / 2;
    for (index, points) in tiles.iter().enumerate() {
        let folder = if index == middle { &later } else { &now };
        let path = folder.join(format!("tile-{index}.las"));
        write_las(&path, &cloud.select(points), &LasWriteOptions::default()).expect("tile");
    }
    (now, later)
}

/// `pointfarm render` of `tiles` into `out` through the store cache `cache`, at `camera`.
fn render(tiles: &Path, out: &Path, cache: &Path, camera: &[String]) -> Command {
    let mut command = Command::new(pointfarm_bin());
    command
        .args([
            "render",
            path_arg(tiles),
            "--out",
            path_arg(out),
            SIZE,
            "--lod-error",
            "0",
        ])
        .args(["--cache-dir", path_arg(cache), "--json"])
        .args(camera)
        .env("RUST_LOG", "pointfarm_render=info")
        .env_remove("POINTFARM_TEST_PAUSE_AT");
    command
}

fn run(command: &mut Command) -> Output {
    let output = command.output().expect("run pointfarm");
    assert!(output.status.success(), "{}", output_text(&output));
    output
}

/// The points the frame's report says the dataset holds.
fn points_total(output: &Output) -> u64 {
    let text = String::from_utf8_lossy(&output.stdout);
    let line = text.lines().next().expect("a frame report");
    let report: serde_json::Value = serde_json::from_str(line).expect("JSON");
    report["pointsTotal"].as_u64().expect("pointsTotal")
}

/// The camera the first render chose, as flags, so every render shares it.
fn camera_of(output: &Output) -> Vec<String> {
    let mut flags = printed_camera(output);
    flags.push("--point-size=2".to_owned());
    flags
}

/// The first render of `tiles`, which builds the store in `dir/cache` and chooses the camera
/// every later render shares. Returns the cache, the render's output and the camera.
fn first_render(dir: &Path, tiles: &Path) -> (PathBuf, Output, Vec<String>) {
    let cache = dir.join("cache");
    let auto = run(&mut render(tiles, &dir.join("first.png"), &cache, &[]));
    let camera = camera_of(&auto);
    (cache, auto, camera)
}

/// Moves the new day's tile into the tiles' folder.
fn add_the_new_tile(tiles: &Path, later: &Path) {
    let name = format!("tile-{}.las", SIDE * SIDE / 2);
    std::fs::rename(later.join(&name), tiles.join(&name)).expect("move the new tile");
}

/// The render's log says it updated the store with the new tile rather than building anew,
/// and it drew every point.
fn assert_updated_with_the_new_tile(output: &Output) {
    let log = output_text(output);
    assert!(log.contains("updated store: 1 files added"), "{log}");
    assert!(
        log.contains("store updated: 1 added, 0 removed, 0 changed file(s)"),
        "{log}"
    );
    assert!(!log.contains("levels of detail:"), "built anew:\n{log}");
    assert_eq!(points_total(output), POINTS as u64);
}

/// `updated` looks like the frame of a store built anew in `dir` from every tile.
fn assert_draws_as_a_fresh_build(
    dir: &Path,
    tiles: &Path,
    camera: &[String],
    updated: &Path,
    name: &str,
    message: &str,
) {
    let fresh = dir.join("fresh.png");
    let output = run(&mut render(tiles, &fresh, &dir.join("fresh-cache"), camera));
    assert!(output_text(&output).contains("levels of detail:"));
    assert_pngs_alike(name, updated, &fresh, message);
}

#[test]
fn a_folder_that_gains_a_tile_updates_its_store_and_draws_as_a_fresh_build() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (tiles, later) = write_tiles(dir.path());
    let (cache, auto, camera) = first_render(dir.path(), &tiles);
    let day_one = points_total(&auto);
    assert!(day_one < POINTS as u64);

    add_the_new_tile(&tiles, &later);
    let updated = dir.path().join("updated.png");
    let output = run(&mut render(&tiles, &updated, &cache, &camera));
    assert_updated_with_the_new_tile(&output);
    // The earlier files' store was taken over, not copied.
    let stores = std::fs::read_dir(cache.join("lod")).expect("the store cache");
    assert_eq!(
        stores
            .filter(|e| e.as_ref().is_ok_and(|e| e.path().is_dir()))
            .count(),
        1
    );

    assert_draws_as_a_fresh_build(
        dir.path(),
        &tiles,
        &camera,
        &updated,
        "store-update",
        "the updated store's frame differs from a fresh build's",
    );
}

#[test]
fn an_update_killed_before_it_switches_leaves_the_old_store_to_update_again() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (tiles, later) = write_tiles(dir.path());
    let (cache, _, camera) = first_render(dir.path(), &tiles);

    add_the_new_tile(&tiles, &later);
    let updated = dir.path().join("updated.png");
    kill_build_at(
        render(&tiles, &updated, &cache, &camera),
        Some("update:0"),
        Duration::ZERO,
    );
    // The old store, taken over and unfinished, still holds the earlier points whole: the
    // next render updates it rather than building anew.
    let output = run(&mut render(&tiles, &updated, &cache, &camera));
    assert_updated_with_the_new_tile(&output);

    assert_draws_as_a_fresh_build(
        dir.path(),
        &tiles,
        &camera,
        &updated,
        "store-update-killed",
        "the store updated after a kill draws unlike a fresh build",
    );
}

/// A store of the folder's tiles, then a render after `change` to the folder: the log says the
/// store was updated as `said` rather than built anew, the frame holds `points` points and
/// looks like a fresh build's.
fn assert_change_updates_the_store(
    change: impl FnOnce(&Path, &Path),
    said: &str,
    points: impl FnOnce(u64) -> u64,
    name: &str,
) {
    let dir = tempfile::tempdir().expect("tempdir");
    let (tiles, later) = write_tiles(dir.path());
    add_the_new_tile(&tiles, &later);
    let (cache, auto, camera) = first_render(dir.path(), &tiles);
    assert_eq!(points_total(&auto), POINTS as u64);

    change(&tiles, &later);
    let updated = dir.path().join("updated.png");
    let output = run(&mut render(&tiles, &updated, &cache, &camera));
    let log = output_text(&output);
    assert!(log.contains(said), "{log}");
    assert!(!log.contains("levels of detail:"), "built anew:\n{log}");
    assert_eq!(points_total(&output), points(POINTS as u64));
    assert_draws_as_a_fresh_build(
        dir.path(),
        &tiles,
        &camera,
        &updated,
        name,
        "the updated store's frame differs from a fresh build's",
    );
}

#[test]
fn a_folder_that_loses_a_tile_updates_its_store_and_draws_as_a_fresh_build() {
    let removed = std::cell::Cell::new(0);
    assert_change_updates_the_store(
        |tiles, later| {
            let name = "tile-1.las";
            let tile = pointfarm_render::ingest::DatasetSource::open(&[tiles.join(name)])
                .expect("open the tile");
            removed.set(pointfarm_render::lod::PointSource::point_count(&tile));
            std::fs::rename(tiles.join(name), later.join(name)).expect("move the tile out");
        },
        "store updated: 0 added, 1 removed, 0 changed file(s)",
        |all| all - removed.get(),
        "store-update-removed",
    );
}

#[test]
fn a_folder_with_a_replaced_tile_updates_its_store_and_draws_as_a_fresh_build() {
    let cloud = sample_scene(POINTS, 5);
    let tile = 3;
    let points = &ground_plan_tiles(&cloud, SIDE, SIDE)[tile];
    // The tile processed again: every other point of it.
    let thinned: Vec<usize> = points.iter().step_by(2).copied().collect();
    let dropped = (points.len() - thinned.len()) as u64;
    assert_change_updates_the_store(
        |tiles, _| {
            let path = tiles.join(format!("tile-{tile}.las"));
            write_las(&path, &cloud.select(&thinned), &LasWriteOptions::default()).expect("tile");
        },
        "store updated: 0 added, 0 removed, 1 changed file(s)",
        |all| all - dropped,
        "store-update-replaced",
    );
}

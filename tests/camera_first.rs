//! A folder of 20 tiles and a low flythrough over two of them: `pointfarm render` builds the
//! store camera first. The first frame is drawn once the tiles it sees are built, before the
//! rest of the path's and long before the tiles no frame sees (the order of the render's
//! lines); the frames equal those of a store built whole first within the fidelity rule; and
//! the finished store holds the same points in the same cube as a fresh build of every tile,
//! each point in one node. With `--build-unseen never` the unseen tiles are never built.

use std::path::Path;
use std::process::{Command, Output};

use pointfarm_tests::flights::{write_flight, write_tiles, COLUMNS, ROWS};
use pointfarm_tests::stores::{every_node, store_folder};
use pointfarm_tests::{assert_pngs_alike, output_text, path_arg, pointfarm_bin, run_ok};

const POINTS: usize = 200_000;
const FRAMES: usize = 3;
const SIZE: &str = "--size=160x120";

fn render(tiles: &Path, out: &Path, cache: &Path, camera: &[&str]) -> Command {
    let mut command = Command::new(pointfarm_bin());
    command
        .args(["render", path_arg(tiles), "--out", path_arg(out), SIZE])
        .args(["--lod-error", "0", "--point-size", "2"])
        .args(["--cache-dir", path_arg(cache)])
        .args(camera)
        .env_remove("POINTFARM_TEST_PAUSE_AT");
    command
}

fn run(command: &mut Command) -> Output {
    run_ok(command, "pointfarm render")
}

/// The place of the first line of `lines` holding `text`.
fn line_of(lines: &[&str], text: &str) -> usize {
    lines
        .iter()
        .position(|line| line.contains(text))
        .unwrap_or_else(|| panic!("no {text:?} in:\n{}", lines.join("\n")))
}

/// How many tiles a camera-first stage's line names.
fn tiles_in(line: &str) -> usize {
    let (_, after) = line.split_once(" (").expect("a count");
    let (count, _) = after.split_once(' ').expect("a count");
    count.parse().expect("a number")
}

/// Every point of the finished store under `cache` (its positions to the millimetre), sorted,
/// and the store's cube.
fn store_content(cache: &Path) -> (Vec<[i64; 3]>, String) {
    let (nodes, cube) = every_node(&store_folder(cache));
    let mut points: Vec<[i64; 3]> = nodes
        .iter()
        .flat_map(|node| node.world_positions())
        .map(|p| (p * 1000.0).round().to_array().map(|v| v as i64))
        .collect();
    points.sort_unstable();
    (points, format!("{cube:?}"))
}

#[test]
fn a_flythrough_draws_its_first_frame_from_the_tiles_it_sees_and_the_store_ends_whole() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (tiles, bounds) = write_tiles(dir.path(), POINTS);
    let flight = write_flight(dir.path(), &bounds, FRAMES);
    let path = ["--camera-path", path_arg(&flight)];

    let first = dir.path().join("first");
    let cache = dir.path().join("cache");
    let output = run(&mut render(&tiles, &first, &cache, &path));
    let text = String::from_utf8_lossy(&output.stdout).into_owned();
    let lines: Vec<&str> = text.lines().collect();
    let seen_first = line_of(
        &lines,
        "camera first: building the files the first frame sees",
    );
    let frame = |i: usize| line_of(&lines, &format!("frame_{i:05}.png"));
    let unseen = line_of(&lines, "camera first: building the files no frame sees");
    assert!(seen_first < frame(0), "{text}");
    assert!(frame(FRAMES - 1) < unseen, "{text}");
    // Each stage after the first updated the store rather than building it anew.
    let stages = lines.iter().filter(|l| l.contains("camera first:")).count();
    let updates = lines.iter().filter(|l| l.contains("store updated")).count();
    assert_eq!(updates, stages - 1, "{text}");
    let first_tiles = tiles_in(lines[seen_first]);
    let unseen_tiles = tiles_in(lines[unseen]);
    assert!(first_tiles <= 4, "{text}");
    assert!(unseen_tiles >= 14, "{text}");
    if let Some(path_line) = lines
        .iter()
        .position(|l| l.contains("the rest of the camera path sees"))
    {
        assert!(frame(0) < path_line && path_line < frame(1), "{text}");
        assert_eq!(
            first_tiles + tiles_in(lines[path_line]) + unseen_tiles,
            COLUMNS * ROWS
        );
    }

    // A store of every tile built whole first (a still view builds it so), then the flight.
    let whole_cache = dir.path().join("whole-cache");
    run(&mut render(
        &tiles,
        &dir.path().join("still.png"),
        &whole_cache,
        &[],
    ));
    let whole = dir.path().join("whole");
    let output = run(&mut render(&tiles, &whole, &whole_cache, &path));
    assert!(!output_text(&output).contains("camera first"));
    for i in 0..FRAMES {
        let name = format!("frame_{i:05}.png");
        assert_pngs_alike(
            "camera-first",
            &first.join(&name),
            &whole.join(&name),
            "a frame drawn camera first differs from the whole store's",
        );
    }

    let (points, cube) = store_content(&cache);
    let (fresh_points, fresh_cube) = store_content(&whole_cache);
    assert_eq!(points.len(), POINTS);
    assert_eq!(cube, fresh_cube);
    assert!(points == fresh_points, "the stores hold other points");

    // A second flight opens the finished store as it is.
    let again = run(&mut render(
        &tiles,
        &dir.path().join("again"),
        &cache,
        &path,
    ));
    assert!(
        !output_text(&again).contains("camera first"),
        "{}",
        output_text(&again)
    );
}

#[test]
fn never_building_the_unseen_tiles_keeps_the_store_to_the_flights() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (tiles, bounds) = write_tiles(dir.path(), POINTS);
    let flight = write_flight(dir.path(), &bounds, FRAMES);
    let cache = dir.path().join("cache");
    let out = dir.path().join("frames");
    let path = [
        "--camera-path",
        path_arg(&flight),
        "--build-unseen",
        "never",
    ];
    let output = run(&mut render(&tiles, &out, &cache, &path));
    let text = output_text(&output);
    assert!(!text.contains("the files no frame sees"), "{text}");
    let (points, _) = store_content(&cache);
    assert!(points.len() < POINTS / 2, "{} points", points.len());
    assert!(out.join(format!("frame_{:05}.png", FRAMES - 1)).exists());

    // A later render of every tile adds the rest to the same store.
    let whole = dir.path().join("whole.png");
    let output = run(&mut render(&tiles, &whole, &cache, &[]));
    assert!(
        output_text(&output).contains("store updated"),
        "{}",
        output_text(&output)
    );
    let (points, _) = store_content(&cache);
    assert_eq!(points.len(), POINTS);
}

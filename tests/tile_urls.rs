//! Final frames of LAS/LAZ tiles by URL, against real servers on loopback: a campaign of
//! generated tiles (three LAZ, one LAS of more than one streamed block, one empty) served by `s3s-fs`
//! and by nginx. The store built by streaming them renders the frames of the same files here
//! pixel for pixel, fetching about the tiles' bytes once; a second render opens it after one
//! listing; an object replaced after it was listed, or while the build streams it, fails the
//! build naming it, and no store is left. Each test skips, saying so, without nginx or
//! `s3s-fs`.

use std::path::{Path, PathBuf};
use std::process::Output;

use pointfarm_render::cut::StoredLod;
use pointfarm_render::ingest::{write_las, LasWriteOptions};
use pointfarm_render::lod::BuildProgress;
use pointfarm_render::remote::{ObjectUrl, RemoteClient, RemoteSettings};
use pointfarm_render::sample::sample_scene;
use pointfarm_render::source::{listed_tiles, open_tile_source};
use pointfarm_render::testing::{write_empty_files, write_scene_tiles};
use pointfarm_tests::nginx::NginxServer;
use pointfarm_tests::s3s::{run_s3, S3sServer};
use pointfarm_tests::{assert_same_frames, json_lines, output_text, path_arg, pointfarm_ok};

const BUCKET: &str = "campaigns";
/// The options of every render: frames from levels of detail, so both sides cut a store.
const OPTIONS: [&str; 6] = [
    "--size=160x120",
    "--turntable",
    "2",
    "--lod-error",
    "1",
    "--json",
];

/// Three LAZ tiles of 60,000 points and one LAS tile of 300,000 (over 8 MiB: streamed in
/// more than one block) in `folder`; their paths.
fn write_campaign(folder: &Path) -> Vec<PathBuf> {
    let mut tiles = write_scene_tiles(folder, 60_000, 3);
    let big = folder.join("t4.las");
    write_las(&big, &sample_scene(300_000, 4), &LasWriteOptions::default()).expect("LAS tile");
    assert!(std::fs::metadata(&big).expect("LAS tile").len() > 8 << 20);
    tiles.push(big);
    // An empty tile, as a tiling leaves where there were no points: it changes nothing.
    tiles.extend(write_empty_files(folder, &["t5.laz"]));
    tiles
}

fn total_bytes(paths: &[PathBuf]) -> u64 {
    (paths.iter())
        .map(|path| std::fs::metadata(path).expect("tile").len())
        .sum()
}

/// `pointfarm ARGS` with the S3 server's endpoint and credentials in its environment, which
/// must succeed.
fn pointfarm_s3(server: &S3sServer, args: &[&str]) -> Output {
    let output = run_s3(&server.environment(), args);
    assert!(output.status.success(), "{}", output_text(&output));
    output
}

/// `render INPUT` into `out` with the store cache `cache` and [`OPTIONS`].
fn render_args<'a>(input: &'a str, out: &'a Path, cache: &'a Path) -> Vec<&'a str> {
    let mut args = vec![
        "render",
        input,
        "--out",
        path_arg(out),
        "--cache-dir",
        path_arg(cache),
    ];
    args.extend(OPTIONS);
    args
}

/// What the last frame's report says was fetched: (requests, bytes).
fn fetched(output: &Output) -> (u64, u64) {
    let frames = json_lines(output);
    let last = frames.last().expect("a frame");
    let count = |key: &str| last["fetched"][key].as_u64().expect("fetched counts");
    (count("requests"), count("bytes"))
}

#[test]
fn final_frames_of_a_prefix_in_s3_are_the_frames_of_the_files_here() {
    let root = tempfile::tempdir().expect("root");
    let folder = root.path().join(BUCKET).join("tiles");
    let paths = write_campaign(&folder);
    let Some(server) = S3sServer::start_or_skip(root.path()) else {
        return;
    };
    let prefix = format!("s3://{BUCKET}/tiles/");
    let here = root.path().join("here");
    pointfarm_ok(&render_args(
        path_arg(&folder),
        &here,
        &root.path().join("cache-here"),
    ));

    let cache = root.path().join("cache");
    let by_url = root.path().join("by-url");
    let output = pointfarm_s3(&server, &render_args(&prefix, &by_url, &cache));
    let text = output_text(&output);
    assert_same_frames(&here, &by_url, 2, "the final frames of the tiles in S3");
    assert!(json_lines(&output)
        .iter()
        .all(|frame| frame["preview"] == false));
    // Each tile read once, and its header, records and chunk table once more by range.
    let total = total_bytes(&paths);
    let (requests, bytes) = fetched(&output);
    eprintln!("built from S3: fetched {bytes} bytes of {total} in {requests} requests");
    assert!(
        bytes >= total && bytes <= total + 4 * 64 * 1024,
        "{bytes} bytes of {total}: {text}"
    );
    assert!(requests < 40, "{requests} requests: {text}");
    assert!(text.contains(&format!("from {prefix}")), "{text}");

    // The store is kept under the tiles' versions: a second render lists them and reads none.
    let again = root.path().join("again");
    let output = pointfarm_s3(&server, &render_args(&prefix, &again, &cache));
    let text = output_text(&output);
    assert_eq!(fetched(&output), (1, 0), "{text}");
    assert_same_frames(&here, &again, 2, "the frames from the kept store");

    // With --preview, the tiles' chunk starts are drawn while a store builds, then the
    // same final frames.
    let previewed = root.path().join("previewed");
    let preview_cache = root.path().join("cache-preview");
    let mut args = render_args(&prefix, &previewed, &preview_cache);
    args.push("--preview");
    let output = pointfarm_s3(&server, &args);
    let frames = json_lines(&output);
    assert_eq!(frames[0]["preview"], true, "{}", output_text(&output));
    assert!(frames.iter().any(|frame| frame["preview"] == false));
    assert_same_frames(&here, &previewed, 2, "the final frames after a preview");
}

#[test]
fn an_object_replaced_after_its_listing_or_during_the_build_fails_it_naming_the_object() {
    let root = tempfile::tempdir().expect("root");
    let folder = root.path().join("tiles");
    let paths = write_campaign(&folder);
    let Some(server) = NginxServer::start_or_skip(root.path()) else {
        return;
    };
    let client = RemoteClient::new(RemoteSettings::default()).expect("client");
    let url = |name: &str| ObjectUrl::parse(&server.url(&format!("tiles/{name}"))).expect("URL");
    let names = ["t1.laz", "t2.laz", "t3.laz", "t4.las"];
    let listed = |client: &RemoteClient| {
        (names.iter())
            .flat_map(|name| listed_tiles(client, &url(name)).expect("HEAD"))
            .collect::<Vec<_>>()
    };
    // Another size makes another ETag, whatever the second.
    let replace = |path: &Path, points: usize| {
        write_las(path, &sample_scene(points, 9), &LasWriteOptions::default()).expect("replaced");
    };

    let tiles = listed(&client);
    replace(&paths[1], 50_000);
    let error = open_tile_source(&client, &tiles)
        .err()
        .expect("a replaced tile");
    let text = error.to_string();
    assert!(
        text.contains(url("t2.laz").as_str()) && text.contains("changed"),
        "{text}"
    );

    let tiles = listed(&client);
    let source = open_tile_source(&client, &tiles).expect("the tiles checked");
    replace(&paths[3], 310_000);
    let store = root.path().join("cache").join("store");
    std::fs::create_dir_all(&store).expect("store folder");
    let build = pointfarm_render::cut::StoreBuild {
        folder: &store,
        memory_budget: 256 << 20,
        disk_budget: None,
        on_build: &mut |_| {},
        progress: &BuildProgress::new(),
    };
    let built = StoredLod::open_or_build_source(&source, build);
    let text = built
        .err()
        .expect("a tile replaced while streamed")
        .to_string();
    assert!(
        text.contains(url("t4.las").as_str()) && text.contains("changed"),
        "{text}"
    );
    assert!(!StoredLod::is_built(&store), "a store of two versions");

    // One object by URL renders as the file here.
    let one = url("t1.laz");
    let cache = root.path().join("cache-one");
    let here = root.path().join("here");
    pointfarm_ok(&render_args(path_arg(&paths[0]), &here, &cache));
    let by_url = root.path().join("by-url");
    let output = pointfarm_ok(&render_args(one.as_str(), &by_url, &cache));
    assert_same_frames(&here, &by_url, 2, "one tile by URL");
    let size = std::fs::metadata(&paths[0]).expect("tile").len();
    let (_, bytes) = fetched(&output);
    assert!(
        bytes >= size && bytes < 2 * size + 64 * 1024,
        "{bytes} of {size}"
    );
}

//! `pointfarm render` of a COPC file, run as a user would: its own hierarchy read node by
//! node (no store built), every node drawn as the same points read whole, a coarse pixel
//! error reading less than the file, a damaged hierarchy refused naming the file; `info`
//! describing a COPC file's octree.

use std::path::{Path, PathBuf};
use std::process::Output;

use pointfarm_render::ingest::{load_point_cloud, write_las, LasWriteOptions};
use pointfarm_render::testing::compare_images_within;
use pointfarm_tests::{assert_fails_saying, output_text, pointfarm, pointfarm_ok};

fn arg(path: &Path) -> &str {
    path.to_str().expect("test paths are UTF-8")
}

fn copc_file(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("data/copc")
        .join(name)
}

/// The one frame's report of `render --json`.
fn report(output: &Output) -> serde_json::Value {
    let stdout = String::from_utf8_lossy(&output.stdout);
    let line = stdout.lines().next().expect("one frame");
    serde_json::from_str(line).expect("a JSON object")
}

#[test]
fn a_copc_file_renders_node_by_node_as_its_points_read_whole() {
    let dir = tempfile::tempdir().expect("tempdir");
    let copc = copc_file("simple.copc.laz");
    let cache = dir.path().join("cache");
    // A fixed point size: adaptive points take the spacing of the leaves here, of the points
    // themselves when resident.
    let size = "--size=200x150";
    let points = "--point-size=3";
    let out = dir.path().join("copc.png");
    let rendered = pointfarm_ok(&[
        "render",
        arg(&copc),
        "--out",
        arg(&out),
        size,
        points,
        "--lod-error",
        "0",
        "--cache-dir",
        arg(&cache),
        "--json",
    ]);
    let said = output_text(&rendered);
    assert!(
        said.contains("COPC: reading its hierarchy node by node (65 nodes in 1 page"),
        "{said}"
    );
    assert!(!cache.exists(), "no store is built for a COPC file");
    let frame = report(&rendered);
    assert_eq!(frame["pointsTotal"], 1065, "{frame}");
    assert_eq!(frame["pointsRendered"], 1065, "{frame}");
    assert_eq!(frame["cut"]["nodes"], 65, "{frame}");

    // The same points as a plain LAZ file, rendered resident.
    let plain = dir.path().join("plain.laz");
    let cloud = load_point_cloud(&copc).expect("the file read whole");
    write_las(&plain, &cloud, &LasWriteOptions::default()).expect("write");
    let resident = dir.path().join("resident.png");
    let said = output_text(&pointfarm_ok(&[
        "render",
        arg(&plain),
        "--out",
        arg(&resident),
        size,
        points,
    ]));
    assert!(!said.contains("COPC"), "{said}");
    let image = |path: &Path| image::open(path).expect("png").to_rgba8();
    let diff = compare_images_within("copc-cli", &image(&out), &image(&resident), 8);
    assert!(
        diff.equal_fraction() >= 0.99,
        "the COPC file's every node differs from its points read whole: {} pixels",
        diff.differing
    );
}

#[test]
fn a_coarse_pixel_error_reads_less_than_the_file() {
    let dir = tempfile::tempdir().expect("tempdir");
    let copc = copc_file("simple_with_page.copc.laz");
    let out = dir.path().join("coarse.png");
    let rendered = pointfarm_ok(&[
        "render",
        arg(&copc),
        "--out",
        arg(&out),
        "--size=200x150",
        "--lod-error",
        "8",
        "--json",
    ]);
    assert!(
        output_text(&rendered).contains("in 2 pages"),
        "{}",
        output_text(&rendered)
    );
    let frame = report(&rendered);
    let file_len = std::fs::metadata(&copc).expect("size").len();
    let bytes_read = frame["cut"]["bytesRead"].as_u64().expect("bytes read");
    assert!(bytes_read > 0 && bytes_read < file_len / 2, "{frame}");
    assert!(frame["cut"]["nodes"].as_u64() < Some(65), "{frame}");
    assert!(frame["pointsRendered"].as_u64() < Some(1065), "{frame}");
}

#[test]
fn a_damaged_copc_hierarchy_is_refused_naming_the_file() {
    let dir = tempfile::tempdir().expect("tempdir");
    let mut bytes = std::fs::read(copc_file("simple.copc.laz")).expect("read");
    // The root page's second entry: its chunk moved past the end of the file.
    let info = 375 + 54;
    let page = u64::from_le_bytes(bytes[info + 40..info + 48].try_into().expect("8")) as usize;
    let beyond = bytes.len() as u64 + 1_000;
    bytes[page + 32 + 16..page + 32 + 24].copy_from_slice(&beyond.to_le_bytes());
    let damaged = dir.path().join("damaged.copc.laz");
    std::fs::write(&damaged, &bytes).expect("write");
    let output = pointfarm(&[
        "render",
        arg(&damaged),
        "--out",
        arg(&dir.path().join("x.png")),
    ]);
    assert_fails_saying(&output, "damaged.copc.laz: COPC hierarchy is inconsistent");

    // `info` still describes the file, as plain LAZ, and says why its octree is not read.
    let described = info_json(&damaged);
    let error = described["copc"]["error"].as_str().expect("an error");
    assert!(error.contains("damaged.copc.laz"), "{error}");
    assert_eq!(described["points"], "1065");
}

/// The one file's `FileDescription` of `info --no-points --json`.
fn info_json(file: &Path) -> serde_json::Value {
    let output = pointfarm_ok(&["info", arg(file), "--no-points", "--json"]);
    let description: serde_json::Value =
        serde_json::from_slice(&output.stdout).expect("one JSON document");
    description["files"][0].clone()
}

/// `info` reports a COPC file's octree from its hierarchy pages, as laspy's test data
/// documents it (65 nodes over 4 levels, part of them in a child page); a plain LAZ has none.
#[test]
fn info_describes_a_copc_files_octree() {
    let paged = info_json(&copc_file("simple_with_page.copc.laz"));
    let copc = &paged["copc"];
    assert_eq!(copc["nodes"], "65", "{copc}");
    assert_eq!(copc["depth"], 3, "{copc}");
    assert_eq!(copc["hierarchyPages"], 2, "{copc}");
    assert!(copc["spacing"].as_f64().is_some_and(|s| s > 0.0), "{copc}");
    assert!(copc.get("error").is_none(), "{copc}");
    let one_page = info_json(&copc_file("simple.copc.laz"));
    assert_eq!(one_page["copc"]["nodes"], "65");
    assert_eq!(one_page["copc"]["hierarchyPages"], 1);
    let text = output_text(&pointfarm_ok(&[
        "info",
        arg(&copc_file("simple.copc.laz")),
        "--no-points",
    ]));
    assert!(text.contains("copc        65 nodes in 4 levels"), "{text}");

    let plain = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/lone-star.laz");
    if plain.exists() {
        assert!(info_json(&plain).get("copc").is_none());
    }
}

//! `pointfarm render` of a COPC file, run as a user would: its own hierarchy read node by
//! node (no store built), every node drawn as the same points read whole, a coarse pixel
//! error reading less than the file, a damaged hierarchy refused naming the file; the same
//! through a daemon and a worker process, which fetches the file's chunks node by node;
//! `info` describing a COPC file's octree; `render --preview` of a COPC file, coarse cuts
//! first.

use std::path::{Path, PathBuf};
use std::process::Output;

use pointfarm_render::ingest::{load_point_cloud, write_las, LasWriteOptions};
use pointfarm_tests::{
    assert_fails_saying, assert_ok, assert_pngs_alike, assert_same_frames, copc_file, json_lines,
    output_text, path_arg, pointfarm, pointfarm_ok, sampled_copc,
};

/// `pointfarm render INPUT --out OUT ARGS...`, which must succeed.
fn render_ok(input: &Path, out: &Path, args: &[&str]) -> Output {
    let mut all = vec!["render", path_arg(input), "--out", path_arg(out)];
    all.extend_from_slice(args);
    pointfarm_ok(&all)
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
    let rendered = render_ok(
        &copc,
        &out,
        &[
            size,
            points,
            "--lod-error",
            "0",
            "--cache-dir",
            path_arg(&cache),
            "--json",
        ],
    );
    let said = output_text(&rendered);
    assert!(
        said.contains("COPC: reading its hierarchy node by node (65 nodes in the 1 page read;"),
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
    let said = output_text(&render_ok(&plain, &resident, &[size, points]));
    assert!(!said.contains("COPC"), "{said}");
    assert_pngs_alike(
        "copc-cli",
        &out,
        &resident,
        "the COPC file's every node differs from its points read whole",
    );
}

#[test]
fn a_coarse_pixel_error_reads_less_than_the_file() {
    let dir = tempfile::tempdir().expect("tempdir");
    let copc = copc_file("simple_with_page.copc.laz");
    let out = dir.path().join("coarse.png");
    // Its points lie far apart for their 200x150 frame: at 8 pixels most nodes are needed.
    let rendered = render_ok(
        &copc,
        &out,
        &["--size=200x150", "--lod-error", "32", "--json"],
    );
    assert!(
        output_text(&rendered).contains("in the 2 pages read"),
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

/// `render --preview` of a COPC file: every frame first from coarse cuts of its hierarchy,
/// reported as previews with their completeness, then the final frames over them, equal to a
/// render without previews; a pixel error as coarse as a preview's renders final frames at
/// once.
#[test]
fn a_copc_file_is_previewed_from_coarse_cuts_then_rendered_final() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (_, copc) = sampled_copc(dir.path(), 300_000);
    let render = |out: &Path, more: &[&str]| {
        let mut args = vec![
            "render",
            path_arg(&copc),
            "--out",
            path_arg(out),
            "--size=160x120",
        ];
        args.extend(["--turntable", "3", "--lod-error", "0.5", "--json"]);
        args.extend_from_slice(more);
        pointfarm_ok(&args)
    };
    let frames = dir.path().join("frames");
    let output = render(&frames, &["--preview"]);
    let reports = json_lines(&output);
    assert_eq!(reports.len(), 6, "{}", output_text(&output));
    let (previews, finals) = reports.split_at(3);
    for (index, (preview, last)) in previews.iter().zip(finals).enumerate() {
        assert_eq!(preview["frame"], index as u64);
        assert_eq!(last["frame"], index as u64);
        assert_eq!(preview["preview"], true, "{preview}");
        assert_eq!(last["preview"], false, "{last}");
        assert_eq!(
            preview["camera"], last["camera"],
            "framed as the final frame"
        );
        assert_eq!(preview["pointsTotal"], 300_000, "{preview}");
        let drawn = |report: &serde_json::Value| report["pointsRendered"].as_u64().expect("drawn");
        assert!(
            drawn(preview) > 0 && drawn(preview) < drawn(last),
            "{preview} {last}"
        );
        let completeness = preview["completeness"].as_f64().expect("completeness");
        assert!((completeness - drawn(preview) as f64 / 300_000.0).abs() < 1e-12);
        assert!(preview["cut"].is_object() && last["cut"].is_object());
    }
    // The final frames find the previews' nodes cached.
    let hits = |report: &serde_json::Value| {
        let cut = &report["cut"];
        cut["gpuHits"].as_u64().unwrap_or(0) + cut["hostHits"].as_u64().unwrap_or(0)
    };
    assert!(hits(&finals[0]) > 0, "{}", finals[0]);
    assert!(output_text(&output).contains("final frames:"));

    let normal = dir.path().join("normal");
    let plain = render(&normal, &[]);
    assert!(json_lines(&plain).iter().all(|r| r["preview"] == false));
    assert_same_frames(&normal, &frames, 3, "the render with previews");

    let coarse = render_ok(
        &copc,
        &dir.path().join("coarse.png"),
        &["--size=160x120", "--lod-error", "8", "--preview", "--json"],
    );
    assert!(json_lines(&coarse).iter().all(|r| r["preview"] == false));
    assert!(
        output_text(&coarse).contains("is a preview's already"),
        "{}",
        output_text(&coarse)
    );
}

/// `simple.copc.laz` as `damage` leaves it, written into `dir` as `name`.
fn damaged_simple_copc(dir: &Path, name: &str, damage: impl FnOnce(&mut [u8])) -> PathBuf {
    let mut bytes = std::fs::read(copc_file("simple.copc.laz")).expect("read");
    damage(&mut bytes);
    let damaged = dir.join(name);
    std::fs::write(&damaged, &bytes).expect("write");
    damaged
}

/// `simple.copc.laz` written into `dir` with the chunk of its root page's second entry moved
/// past the end of the file.
fn damaged_copc(dir: &Path) -> PathBuf {
    damaged_simple_copc(dir, "damaged.copc.laz", |bytes| {
        let info = 375 + 54;
        let page = u64::from_le_bytes(bytes[info + 40..info + 48].try_into().expect("8")) as usize;
        let beyond = bytes.len() as u64 + 1_000;
        bytes[page + 32 + 16..page + 32 + 24].copy_from_slice(&beyond.to_le_bytes());
    })
}

#[test]
fn a_damaged_copc_hierarchy_is_refused_naming_the_file() {
    let dir = tempfile::tempdir().expect("tempdir");
    let damaged = damaged_copc(dir.path());
    let output = pointfarm(&[
        "render",
        path_arg(&damaged),
        "--out",
        path_arg(&dir.path().join("x.png")),
    ]);
    assert_fails_saying(&output, "damaged.copc.laz: COPC hierarchy is inconsistent");

    // `info` still describes the file, as plain LAZ, and says why its octree is not read.
    let described = info_json(&damaged);
    let error = described["copc"]["error"].as_str().expect("an error");
    assert!(error.contains("damaged.copc.laz"), "{error}");
    assert_eq!(described["points"], "1065");
}

/// `simple.copc.laz` written into `dir` with every byte of its LAZ chunk table's entries set to
/// 0xFF, which the laz crate's table decoder indexes out of bounds with.
fn copc_with_a_chunk_table_of_ones(dir: &Path) -> PathBuf {
    damaged_simple_copc(dir, "ones.copc.laz", |bytes| {
        let data_start = u32::from_le_bytes(bytes[96..100].try_into().expect("4")) as usize;
        let table = u64::from_le_bytes(bytes[data_start..data_start + 8].try_into().expect("8"));
        let first_evlr = u64::from_le_bytes(bytes[235..243].try_into().expect("8"));
        bytes[table as usize + 8..first_evlr as usize].fill(0xFF);
    })
}

#[test]
fn a_chunk_table_of_ones_is_an_error_naming_the_file_on_every_path() {
    let dir = tempfile::tempdir().expect("tempdir");
    let damaged = copc_with_a_chunk_table_of_ones(dir.path());
    let out = dir.path().join("x.png");
    for args in [
        vec!["info", path_arg(&damaged)],
        vec!["render", path_arg(&damaged), "--out", path_arg(&out)],
        vec![
            "render",
            path_arg(&damaged),
            "--out",
            path_arg(&out),
            "--preview",
        ],
    ] {
        let output = pointfarm(&args);
        assert_fails_saying(&output, "ones.copc.laz");
        assert_eq!(output.status.code(), Some(1), "{args:?}");
    }
}

/// A count of the API's JSON mapping, where 64-bit counts are strings.
fn count(value: &serde_json::Value) -> u64 {
    value
        .as_u64()
        .or_else(|| value.as_str().and_then(|s| s.parse().ok()))
        .unwrap_or(0)
}

/// Through a daemon and a worker process, a COPC dataset is rendered from the file's own
/// hierarchy: no store is built, the worker fetches the chunks its cuts need (less than the
/// file at a coarse pixel error) and draws what a local render draws; a damaged file fails
/// its job naming the file, and the daemon goes on rendering.
#[test]
fn a_copc_dataset_renders_through_the_service_from_its_own_hierarchy() {
    let dir = tempfile::tempdir().expect("tempdir");
    let copc = copc_file("simple_with_page.copc.laz");
    let data = dir.path().join("data");
    let server = pointfarm_tests::ServeProcess::start_with(&data, &["--no-embedded-worker"]);
    let worker_cache = dir.path().join("worker-cache");
    let worker = pointfarm_tests::WorkerProcess::start(&server.address, &worker_cache, "far");
    let remote_render = |file: &Path, out: &str, more: &[&str]| {
        let out = dir.path().join(out);
        let mut args = vec!["render", path_arg(file), "--out", path_arg(&out), "--json"];
        args.extend(["--server", &server.address]);
        if !more.iter().any(|arg| arg.starts_with("--size")) {
            args.push("--size=200x150");
        }
        args.extend(more);
        pointfarm(&args)
    };

    let failed = remote_render(&damaged_copc(dir.path()), "damaged.png", &["--lod-error=1"]);
    assert_fails_saying(&failed, "damaged.copc.laz");
    assert_fails_saying(&failed, "COPC hierarchy is inconsistent");

    // A coarse pixel error: the frame's cut fetched less than half the file.
    let coarse = remote_render(&copc, "coarse.png", &["--lod-error=32"]);
    assert_ok(&coarse);
    let frames = json_lines(&coarse);
    let cut = &frames[0]["finished"]["cut"];
    let fetched = count(&cut["bytesRead"]) + count(&cut["readAheadBytes"]);
    let file_len = std::fs::metadata(&copc).expect("size").len();
    assert!(
        fetched > 0 && fetched < file_len / 2,
        "{fetched} of {file_len} bytes fetched: {cut}"
    );
    assert!(count(&cut["pointsRendered"]) < 1065, "{cut}");

    // A preview job: every frame first from a coarse cut, reported as a preview with its
    // completeness, then every frame final. The file's points lie so far apart that a
    // preview's cut of a larger frame draws all of them.
    let previewed = remote_render(
        &copc,
        "previewed",
        &[
            "--preview",
            "--turntable=3",
            "--lod-error=0",
            "--size=48x36",
        ],
    );
    assert_ok(&previewed);
    let reports = json_lines(&previewed);
    let is_preview = |report: &serde_json::Value| report["finished"]["preview"] == true;
    assert_eq!(reports.len(), 6, "{reports:?}\n{}", server.log());
    let (previews, finals) = reports.split_at(3);
    let drawn = |report: &serde_json::Value| count(&report["finished"]["cut"]["pointsRendered"]);
    for report in previews {
        assert!(is_preview(report), "{report}");
        let completeness = report["finished"]["completeness"].as_f64().unwrap_or(0.0);
        assert!(completeness > 0.0 && completeness < 1.0, "{report}");
        assert!(
            (completeness - drawn(report) as f64 / 1065.0).abs() < 1e-9,
            "{report}"
        );
    }
    for (index, report) in finals.iter().enumerate() {
        assert_eq!(report["frame"], index, "{report}");
        assert!(!is_preview(report), "{report}");
        assert_eq!(drawn(report), 1065, "{report}");
    }

    // Every node: the same image as the file rendered here.
    let options = ["--point-size=3", "--lod-error=0"];
    let remote = remote_render(&copc, "remote.png", &options);
    assert_ok(&remote);
    let local = dir.path().join("local.png");
    render_ok(&copc, &local, &[&["--size=200x150"], &options[..]].concat());
    assert_pngs_alike(
        "copc-service",
        &dir.path().join("remote.png"),
        &local,
        &format!(
            "the COPC file renders differently through the service ({})",
            worker.log()
        ),
    );

    // Read from the file's own hierarchy: no store built, no file downloaded.
    let served = server.log();
    assert!(served.contains("no store built"), "{served}");
    assert!(!served.contains("store ready for workers"), "{served}");
    let stores = std::fs::read_dir(data.join("lod")).map_or(0, Iterator::count);
    assert_eq!(stores, 0, "the daemon built a store");
    let log = worker.log();
    assert!(log.contains("daemon_store=true"), "{log}");
    assert!(!log.contains("dataset file downloaded"), "{log}");
    let own_stores = std::fs::read_dir(worker_cache.join("lod")).map_or(0, Iterator::count);
    assert_eq!(own_stores, 0, "the worker built a store of its own");
}

/// The one file's `FileDescription` of `info --no-points --json`.
fn info_json(file: &Path) -> serde_json::Value {
    let output = pointfarm_ok(&["info", path_arg(file), "--no-points", "--json"]);
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
        path_arg(&copc_file("simple.copc.laz")),
        "--no-points",
    ]));
    assert!(text.contains("copc        65 nodes in 4 levels"), "{text}");

    let plain = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/lone-star.laz");
    if plain.exists() {
        assert!(info_json(&plain).get("copc").is_none());
    }
}

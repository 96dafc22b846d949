//! `pointfarm render` from levels of detail, run as a user would: a folder of tiles rendered
//! out of core as the file they were cut from, the store kept and reused, what each frame
//! reports, and the options refused where they do not apply.

use std::path::Path;

use pointfarm_render::ingest::{load_point_cloud, write_las, LasWriteOptions};
use pointfarm_render::sample::sample_scene;
use pointfarm_render::testing::{write_empty_files, write_scene_tiles};
use pointfarm_tests::service::{scratch_sample, write_sample};
use pointfarm_tests::{
    assert_pngs_alike, assert_same_frames, json_lines, json_names, output_text, path_arg,
    pointfarm, pointfarm_ok, printed_camera,
};

/// A scene written whole and as four tiles (LAS and LAZ, one in a subfolder).
fn scene_and_tiles(dir: &Path, points: usize) -> (std::path::PathBuf, std::path::PathBuf) {
    let whole = dir.join("whole.laz");
    write_las(
        &whole,
        &sample_scene(points, 9),
        &LasWriteOptions::default(),
    )
    .expect("whole");
    let cloud = load_point_cloud(&whole).expect("load whole");
    let tiles = dir.join("tiles");
    std::fs::create_dir_all(tiles.join("north")).expect("tiles");
    let centre = cloud.bounds.center() - cloud.origin;
    let mut quarters: [Vec<usize>; 4] = Default::default();
    for (i, p) in cloud.positions.iter().enumerate() {
        let quarter =
            usize::from(f64::from(p.x) >= centre.x) + 2 * usize::from(f64::from(p.y) >= centre.y);
        quarters[quarter].push(i);
    }
    let names = ["sw.las", "se.laz", "north/nw.laz", "north/ne.las"];
    for (name, quarter) in names.iter().zip(&quarters) {
        write_las(
            &tiles.join(name),
            &cloud.select(quarter),
            &LasWriteOptions::default(),
        )
        .expect("tile");
    }
    (whole, tiles)
}

#[test]
fn tiles_render_from_levels_of_detail_as_the_file_they_were_cut_from() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (whole, tiles) = scene_and_tiles(dir.path(), 40_000);
    let cache = dir.path().join("cache");
    let size = "--size=200x150";
    let (resident, cut) = (dir.path().join("resident.png"), dir.path().join("cut.png"));
    // The automatic camera frames each source's own sample of the points, the resident
    // cloud's and the store's coarsest nodes, and adaptive points take each one's measured
    // spacing: the two are compared through one camera with points of one size.
    let auto = pointfarm_ok(&[
        "render",
        path_arg(&whole),
        "--out",
        path_arg(&resident),
        size,
    ]);
    let mut camera = printed_camera(&auto);
    camera.push("--point-size=2".to_owned());
    let mut args = vec![
        "render",
        path_arg(&whole),
        "--out",
        path_arg(&resident),
        size,
    ];
    args.extend(camera.iter().map(String::as_str));
    pointfarm_ok(&args);
    // Renders the tiles through their store; says whether the store was built first.
    let render_tiles = |out: &Path, lod_error: &str, more: &[&str]| {
        let mut args = vec!["render", path_arg(&tiles), "--out", path_arg(out), size];
        args.extend(["--lod-error", lod_error, "--cache-dir", path_arg(&cache)]);
        args.extend_from_slice(more);
        let output = pointfarm_ok(&args);
        let built = output_text(&output).contains("levels of detail:");
        (output, built)
    };
    let camera: Vec<&str> = camera.iter().map(String::as_str).collect();
    let (first, built) = render_tiles(&cut, "0", &camera);
    assert!(built, "{}", output_text(&first));
    assert_pngs_alike(
        "lod-tiles",
        &cut,
        &resident,
        "the tiles' cut at --lod-error 0 differs from the whole file",
    );

    // The store is kept: a turntable reuses it, and each frame reports its cut.
    let frames = dir.path().join("frames");
    let (again, built) = render_tiles(&frames, "0.5", &["--turntable", "3", "--json"]);
    assert!(!built, "built again:\n{}", output_text(&again));
    let reports: Vec<serde_json::Value> = String::from_utf8_lossy(&again.stdout)
        .lines()
        .map(|line| serde_json::from_str(line).expect("one JSON object a line"))
        .collect();
    assert_eq!(reports.len(), 3);
    for report in &reports {
        let cut = &report["cut"];
        assert_eq!(report["pointsTotal"], 40_000);
        assert!(report["pointsRendered"].as_u64() <= Some(40_000));
        assert!(cut["nodes"].as_u64() > Some(0), "{report}");
        for stage in ["select", "load", "rasterize"] {
            assert!(report["timingsMs"][stage].is_number(), "{stage}: {report}");
        }
    }
    assert!(reports[0]["cut"]["nodesRead"].as_u64() > Some(0));
    assert!(reports[0]["cut"]["bytesRead"].as_u64() > Some(0));
    assert!(
        reports[2]["cut"]["gpuHits"].as_u64() > Some(0),
        "{}",
        reports[2]
    );

    // A changed file updates the store, not builds it anew: its points are taken out and
    // read again, and the cut still draws the whole file.
    let tile = tiles.join("sw.las");
    let bytes = std::fs::read(&tile).expect("read tile");
    std::thread::sleep(std::time::Duration::from_millis(20));
    std::fs::write(&tile, bytes).expect("rewrite tile");
    let (updated, built) = render_tiles(&cut, "0", &camera);
    let text = output_text(&updated);
    assert!(!built, "built anew:\n{text}");
    assert!(
        text.contains("store updated: 0 added, 0 removed, 1 changed file(s)"),
        "{text}"
    );
    assert_pngs_alike(
        "lod-tiles-updated",
        &cut,
        &resident,
        "the updated store's cut at --lod-error 0 differs from the whole file",
    );
}

#[test]
fn level_of_detail_options_are_checked_and_refused_through_a_server() {
    let (dir, cloud) = scratch_sample("scene.laz", 2_000, 3);
    let out = dir.path().join("out.png");
    let cache = dir.path().join("cache");
    let refused = |args: &[&str], expected: &str| {
        let mut all = vec![
            "render",
            path_arg(&cloud),
            "--out",
            path_arg(&out),
            "--cache-dir",
            path_arg(&cache),
        ];
        all.extend(args);
        let output = pointfarm(&all);
        assert!(!output.status.success(), "{args:?} was accepted");
        assert!(
            output_text(&output).contains(expected),
            "{args:?}:\n{}",
            output_text(&output)
        );
        assert_ne!(
            output.status.code(),
            Some(101),
            "a panic:\n{}",
            output_text(&output)
        );
    };
    refused(&["--lod-error=-1"], "not a number from 0");
    refused(&["--lod-error", "1000"], "lod_error");
    refused(&["--memory-budget", "1KiB"], "memory_budget");
    refused(&["--memory-budget", "plenty"], "not a size");
    refused(
        &["--memory-budget", "1GiB", "--server", "http://127.0.0.1:9"],
        "--memory-budget",
    );
}

/// A job with a pixel error renders from levels of detail on the server's worker as it does
/// here, and `jobs show` reports each frame's cut.
#[test]
fn a_job_renders_from_levels_of_detail_through_the_service_as_here() {
    let dir = tempfile::tempdir().expect("tempdir");
    // The tiles, one of them empty: uploaded, stored and rendered as here.
    let (_, tiles) = scene_and_tiles(dir.path(), 30_000);
    write_empty_files(&tiles, &["north/empty.laz"]);
    let cache = dir.path().join("cache");
    let (local, remote) = (dir.path().join("local"), dir.path().join("remote"));
    let options = ["--size=160x120", "--turntable", "2", "--lod-error", "0.5"];
    let mut args = vec![
        "render",
        path_arg(&tiles),
        "--out",
        path_arg(&local),
        "--cache-dir",
        path_arg(&cache),
        "--json",
    ];
    args.extend(options);
    let rendered = pointfarm_ok(&args);
    let local_frames: Vec<serde_json::Value> = String::from_utf8_lossy(&rendered.stdout)
        .lines()
        .map(|line| serde_json::from_str(line).expect("a JSON frame"))
        .collect();
    let server = pointfarm_tests::ServeProcess::start(&dir.path().join("data"));
    let mut args = vec![
        "render",
        path_arg(&tiles),
        "--out",
        path_arg(&remote),
        "--server",
        &server.address,
    ];
    args.extend(options);
    pointfarm_ok(&args);
    for frame in ["frame_00000.png", "frame_00001.png"] {
        let image = |dir: &Path| image::open(dir.join(frame)).expect("png").to_rgba8();
        assert!(
            image(&local) == image(&remote),
            "{frame} differs through the service\n{}",
            server.log()
        );
    }
    // The embedded worker read the daemon's store node by node, and no file.
    let log = server.log();
    assert!(log.contains("daemon_store=true"), "{log}");
    assert_eq!(
        log.matches("dataset file downloaded").count(),
        0,
        "files downloaded:\n{log}"
    );
    let listed = pointfarm_ok(&["jobs", "list", "--server", &server.address, "--json"]);
    let jobs: serde_json::Value = serde_json::from_slice(&listed.stdout).expect("json");
    let id = jobs["jobs"][0]["id"].as_str().expect("a job id").to_owned();
    let shown = pointfarm_ok(&["jobs", "show", &id, "--server", &server.address, "--json"]);
    let shown: serde_json::Value = serde_json::from_slice(&shown.stdout).expect("json");
    // The job in the API's JSON mapping: each frame's cut, its 64-bit counts as strings.
    let job: pointfarm_proto::v1::Job =
        serde_json::from_value(shown["job"].clone()).expect("a Job");
    assert_eq!(job.frames.len(), 2, "{shown}");
    for frame in &job.frames {
        let cut = frame.cut.expect("a cut");
        assert_eq!(cut.points_total, 30_000, "{shown}");
        assert!(cut.nodes > 0, "{shown}");
    }
    assert_eq!(
        shown["job"]["frames"][0]["cut"]["pointsTotal"], "30000",
        "{shown}"
    );
    // A cold first frame fetched what a local one reads: the coarse sections alone of the
    // nodes it draws small.
    let local_read = local_frames[0]["cut"]["bytesRead"].as_u64();
    let first = job.frames[0].cut.expect("a cut");
    assert_eq!(Some(first.bytes_read), local_read, "{shown}");
    // 16 B a point and 20 a node coarse, 24 and 28 whole.
    let (nodes, points) = (first.nodes_read, first.points_rendered);
    assert!(
        nodes > 0 && first.bytes_read <= 17 * points + 32 * nodes,
        "{shown}"
    );
    let stages = json_names(&shown["stageStatistics"], "stage");
    for stage in ["build", "select", "load"] {
        assert!(stages.contains(&stage), "{stage} missing from {stages:?}");
    }
    let text = output_text(&pointfarm_ok(&[
        "jobs",
        "show",
        &id,
        "--server",
        &server.address,
    ]));
    assert!(text.contains("levels of detail, 2 frames"), "{text}");

    // Restarted, the daemon opens the store it built, and its worker reads it again.
    let mut server = server;
    let address = server.address.clone();
    let downloads = |log: &str| log.matches("dataset file downloaded").count();
    let before = downloads(&server.log());
    assert!(server
        .terminate(std::time::Duration::from_secs(60))
        .is_some_and(|s| s.success()));
    let server = pointfarm_tests::ServeProcess::start_at(&address, &dir.path().join("data"));
    let again = dir.path().join("again");
    let mut args = vec![
        "render",
        path_arg(&tiles),
        "--out",
        path_arg(&again),
        "--server",
        &server.address,
        // A job that asks for previews; with its store built there is nothing to preview.
        "--preview",
    ];
    args.extend(options);
    let rendered = output_text(&pointfarm_ok(&args));
    assert!(rendered.contains("2 final frames in"), "{rendered}");
    // The log goes on in the same file.
    let log = server.log();
    assert_eq!(downloads(&log), before, "downloaded again:\n{log}");
    assert!(log.contains("built=false"), "{log}");
    let image = |dir: &Path| {
        image::open(dir.join("frame_00001.png"))
            .expect("png")
            .to_rgba8()
    };
    assert!(
        image(&again) == image(&local),
        "the reopened store renders differently\n{log}"
    );
}

/// A worker on another machine renders a dataset too large to render resident from the
/// daemon's store, fetching the nodes its cuts need: no file downloaded, no store of its own,
/// the same images as a local render.
#[test]
fn a_worker_process_reads_the_daemons_store_node_by_node() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (whole, _) = scene_and_tiles(dir.path(), 20_000);
    let options = ["--size=120x90", "--turntable", "2", "--lod-error", "0.25"];
    let (local, cache) = (dir.path().join("local"), dir.path().join("cache"));
    let mut args = vec!["render", path_arg(&whole), "--out", path_arg(&local)];
    args.extend(["--cache-dir", path_arg(&cache)]);
    args.extend(options);
    pointfarm_ok(&args);

    let data = dir.path().join("data");
    let server = pointfarm_tests::ServeProcess::start_with(&data, &["--no-embedded-worker"]);
    let worker_cache = dir.path().join("worker-cache");
    let worker = pointfarm_tests::WorkerProcess::start(&server.address, &worker_cache, "far");
    let remote = dir.path().join("remote");
    let mut args = vec!["render", path_arg(&whole), "--out", path_arg(&remote)];
    args.extend(["--server", &server.address]);
    args.extend(options);
    pointfarm_ok(&args);
    let log = worker.log();
    for frame in ["frame_00000.png", "frame_00001.png"] {
        let image = |dir: &Path| image::open(dir.join(frame)).expect("png").to_rgba8();
        assert!(
            image(&local) == image(&remote),
            "{frame} differs through the daemon's store\n{log}"
        );
    }
    assert!(log.contains("daemon_store=true"), "{log}");
    assert!(!log.contains("dataset file downloaded"), "{log}");
    let own_stores = std::fs::read_dir(worker_cache.join("lod")).map_or(0, Iterator::count);
    assert_eq!(own_stores, 0, "the worker built a store of its own");
    // The daemon built the store once, while the worker handed its frame back.
    let served = server.log();
    assert_eq!(
        served.matches("store ready for workers").count(),
        1,
        "{served}"
    );
}

/// The stores in `--cache-dir` within `--cache-size`: a new dataset's build removes the store
/// used least recently, and a build that alone needs more than the size is refused.
#[test]
fn local_stores_are_kept_within_the_cache_size() {
    let dir = tempfile::tempdir().expect("tempdir");
    let cache = dir.path().join("cache");
    let out = dir.path().join("out.png");
    let (first, second) = (dir.path().join("first.las"), dir.path().join("second.las"));
    write_sample(&first, 20_000, 1);
    write_sample(&second, 20_000, 2);
    let render = |file: &Path, size: Option<&str>| {
        let mut args = vec![
            "render",
            path_arg(file),
            "--out",
            path_arg(&out),
            "--size=64x48",
        ];
        args.extend(["--lod-error", "0", "--cache-dir", path_arg(&cache)]);
        args.extend(size.map(|s| ["--cache-size", s]).into_iter().flatten());
        pointfarm(&args)
    };
    let stores = || -> Vec<String> {
        let mut names: Vec<String> = std::fs::read_dir(cache.join("lod"))
            .expect("stores")
            .map(|e| e.expect("entry").file_name().to_string_lossy().into_owned())
            .collect();
        names.sort();
        names
    };
    let built = render(&first, None);
    assert!(built.status.success(), "{}", output_text(&built));
    let [first_store] = stores().try_into().expect("one store");
    let first_bytes = walkdir_bytes(&cache.join("lod").join(&first_store));

    // Room for the second build's need, not for the first store beside it.
    let source =
        pointfarm_render::ingest::DatasetSource::open(std::slice::from_ref(&second)).expect("open");
    let record = pointfarm_render::lod::disk::spill_record_bytes(&source);
    let need = pointfarm_render::lod::disk::build_disk_bytes(20_000, true, record);
    let size = (need + first_bytes / 2).to_string();
    let second_built = render(&second, Some(&size));
    assert!(
        second_built.status.success(),
        "{}",
        output_text(&second_built)
    );
    let left = stores();
    assert_eq!(left.len(), 1, "{left:?}");
    assert_ne!(
        left[0], first_store,
        "the store used least recently was removed"
    );

    let refused = render(&first, Some("1KiB"));
    assert!(!refused.status.success());
    let message = output_text(&refused);
    assert!(message.contains("budget"), "{message}");
    assert_ne!(refused.status.code(), Some(101), "a panic:\n{message}");
}

/// Bytes of the files below `folder`.
fn walkdir_bytes(folder: &Path) -> u64 {
    std::fs::read_dir(folder)
        .into_iter()
        .flatten()
        .map(|entry| {
            let entry = entry.expect("entry");
            let meta = entry.metadata().expect("metadata");
            if meta.is_dir() {
                walkdir_bytes(&entry.path())
            } else {
                meta.len()
            }
        })
        .sum()
}

#[test]
fn a_preview_renders_from_chunk_starts_while_the_store_builds_then_the_final_frames() {
    let dir = tempfile::tempdir().expect("tempdir");
    // Three LAZ tiles of three 50,000-point chunks each (a generated scene per seed).
    let tiles = dir.path().join("tiles");
    write_scene_tiles(&tiles, 120_000, 3);
    let size = "--size=160x120";
    let render = |out: &Path, cache: &Path, more: &[&str]| {
        let mut args = vec!["render", path_arg(&tiles), "--out", path_arg(out), size];
        args.extend(["--turntable", "3", "--lod-error", "0.5", "--json"]);
        args.extend(["--cache-dir", path_arg(cache)]);
        args.extend_from_slice(more);
        pointfarm_ok(&args)
    };
    let frames = dir.path().join("frames");
    let cache = dir.path().join("cache");
    let output = render(&frames, &cache, &["--preview"]);
    let reports = json_lines(&output);
    let previews = reports
        .iter()
        .take_while(|report| report["preview"] == true)
        .count();
    // The preview draws the first frame at least, from the chunk starts, then again with the
    // nodes stored so far as the build goes on, then the final frames follow, all of them.
    assert!(previews >= 1, "{}", output_text(&output));
    let finals = &reports[previews..];
    assert_eq!(finals.len(), 3, "{}", output_text(&output));
    let mut pass = 0;
    let mut drawn_before = 0;
    for (index, report) in reports[..previews].iter().enumerate() {
        let frame = report["frame"].as_u64().expect("frame");
        if index > 0 && frame == 0 {
            pass += 1;
        }
        assert_eq!(report["pointsTotal"], 360_000, "{report}");
        let drawn = report["pointsRendered"].as_u64().expect("points");
        if pass == 0 {
            // Nine chunk starts at most of 360,000 points.
            assert!((1..=9).contains(&drawn), "{report}");
        } else {
            // Each redraw adds the nodes stored since the one before.
            assert!(drawn > 9 && drawn <= 360_009, "{report}");
            if frame == 0 {
                assert!(drawn >= drawn_before, "{report}");
                drawn_before = drawn;
            }
        }
        let completeness = report["completeness"].as_f64().expect("completeness");
        // The share drawn, at most 1: a cut's points may stand for more than the files hold.
        assert!(
            (completeness - (drawn as f64 / 360_000.0).min(1.0)).abs() < 1e-12,
            "{report}"
        );
    }
    eprintln!("{} preview passes", pass + 1);
    for (index, report) in finals.iter().enumerate() {
        assert_eq!(report["frame"], index as u64);
        assert_eq!(report["preview"], false, "{report}");
        assert!(report["cut"].is_object(), "{report}");
        assert!(report["completeness"].as_f64() > Some(0.01), "{report}");
        // A preview looks from where the final frame does; it frames the files' box, the
        // final frame the points' robust box its store's coarsest nodes give.
        for preview in reports[..previews]
            .iter()
            .filter(|p| p["frame"] == index as u64)
        {
            let (final_view, preview_view) = (view_of(report), view_of(preview));
            assert!(
                (0..3).all(|axis| (final_view[axis] - preview_view[axis]).abs() < 1e-6),
                "{final_view:?} against {preview_view:?}"
            );
        }
    }
    assert!(output_text(&output).contains("final frames:"));

    // The final frames are a normal render's, pixel for pixel (a store built apart).
    let normal = dir.path().join("normal");
    let plain = render(&normal, &dir.path().join("cache2"), &[]);
    assert!(json_lines(&plain).iter().all(|r| r["preview"] == false));
    assert_same_frames(&normal, &frames, 3, "the render with previews");

    // With the store built there is nothing to preview: final frames at once, and it says so.
    let again = render(&frames, &cache, &["--preview"]);
    assert!(json_lines(&again).iter().all(|r| r["preview"] == false));
    assert!(
        output_text(&again).contains("built already"),
        "{}",
        output_text(&again)
    );
    // A dataset rendered resident has no store to wait for either.
    let still = dir.path().join("still.png");
    let tile = tiles.join("t1.laz");
    let resident = pointfarm_ok(&[
        "render",
        path_arg(&tile),
        "--out",
        path_arg(&still),
        "--preview",
    ]);
    assert!(
        output_text(&resident).contains("render resident, nothing to build"),
        "{}",
        output_text(&resident)
    );
    assert!(!output_text(&resident).contains("preview of"));
}

/// The unit vector from a frame report's camera target to its position.
fn view_of(report: &serde_json::Value) -> [f64; 3] {
    let vector = |name: &str| -> Vec<f64> {
        let values = report["camera"][name].as_array().expect("a vector");
        values
            .iter()
            .map(|v| v.as_f64().expect("a number"))
            .collect()
    };
    let (position, target) = (vector("position"), vector("target"));
    let offset: Vec<f64> = (0..3).map(|axis| position[axis] - target[axis]).collect();
    let length = offset.iter().map(|v| v * v).sum::<f64>().sqrt();
    [offset[0] / length, offset[1] / length, offset[2] / length]
}

#[test]
fn empty_tiles_change_no_frame_and_no_export_and_a_dataset_of_them_is_refused() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (_, tiles) = scene_and_tiles(dir.path(), 20_000);
    let cache = dir.path().join("cache");
    let fresh_cache = dir.path().join("fresh-cache");
    let run = |args: &[&str], out: &Path| -> (Vec<u8>, String) {
        let output = pointfarm_ok(args);
        (std::fs::read(out).expect("output"), output_text(&output))
    };
    let render = |name: &str, more: &[&str]| {
        let out = dir.path().join(name);
        let mut args = vec!["render", path_arg(&tiles), "--out", path_arg(&out)];
        args.extend_from_slice(&["--size=160x120"]);
        args.extend_from_slice(more);
        run(&args, &out)
    };
    let export = |name: &str, cache: &Path| {
        let out = dir.path().join(name);
        let args = ["export", path_arg(&tiles), "--copc", path_arg(&out)];
        run(
            &[&args[..], &["--cache-dir", path_arg(cache)]].concat(),
            &out,
        )
        .0
    };
    let lod = |cache: &Path| -> Vec<String> {
        vec![
            "--lod-error=0.5".into(),
            format!("--cache-dir={}", cache.display()),
        ]
    };
    let lod_args = lod(&cache);
    let lod_args: Vec<&str> = lod_args.iter().map(String::as_str).collect();
    let (resident, _) = render("resident.png", &[]);
    let (cut, _) = render("cut.png", &lod_args);
    let copc = export("tiles.copc.laz", &cache);

    // The first file in the dataset's order is empty now, where the first file decided.
    write_empty_files(&tiles, &["a_empty.laz", "north/empty.las"]);
    assert!(
        render("resident-2.png", &[]).0 == resident,
        "resident frame changed"
    );
    let (updated, text) = render("cut-2.png", &lod_args);
    assert!(
        text.contains("store updated: 2 added, 0 removed, 0 changed file(s): 0 points in"),
        "{text}"
    );
    assert!(updated == cut, "the updated store's frame changed");
    let fresh_args = lod(&fresh_cache);
    let fresh_args: Vec<&str> = fresh_args.iter().map(String::as_str).collect();
    assert!(
        render("cut-3.png", &fresh_args).0 == cut,
        "a fresh store's frame changed"
    );
    assert!(
        export("fresh.copc.laz", &fresh_cache) == copc,
        "the export changed"
    );
    let info = pointfarm_ok(&["info", path_arg(&tiles.join("a_empty.laz"))]);
    assert!(output_text(&info).contains("points      0"));

    // A dataset of empty files alone has nothing to render, said in one line.
    let empty_only = dir.path().join("empty-only");
    std::fs::create_dir_all(&empty_only).expect("folder");
    write_empty_files(&empty_only, &["a.laz", "b.las"]);
    let out = dir.path().join("nothing.png");
    for more in [&[][..], &lod_args[..]] {
        let mut args = vec!["render", path_arg(&empty_only), "--out", path_arg(&out)];
        args.extend_from_slice(more);
        pointfarm_tests::assert_one_error_line(
            &pointfarm(&args),
            &["none of the dataset's 2 files contains a point"],
        );
    }
    assert!(!out.exists());
}

//! A level-of-detail store whose bytes fail their checks heals itself, once: `pointfarm
//! render` builds its store again and renders the frame it would have rendered; a daemon
//! builds its store again, counts it, and its job succeeds; damage that comes back after that
//! rebuild fails the job, naming the dataset, instead of building again and again.

use std::path::{Path, PathBuf};

use pointfarm_render::cut::{StoredLod, ELEVATION_SAMPLE_POINTS};
use pointfarm_render::ingest::{write_las, LasWriteOptions};
use pointfarm_render::lod::NodeInfo;
use pointfarm_render::sample::sample_scene;
use pointfarm_tests::prometheus::scrape;
use pointfarm_tests::{free_address, output_text, path_arg, pointfarm, pointfarm_ok, ServeProcess};

/// A LAZ file of the sample scene, small enough to build in a moment.
fn scene(dir: &Path) -> PathBuf {
    let file = dir.join("scene.laz");
    write_las(&file, &sample_scene(20_000, 9), &LasWriteOptions::default())
        .expect("write the scene");
    file
}

/// The payload file of the one store in `lod`.
fn payload_of_the_store_in(lod: &Path) -> PathBuf {
    let stores: Vec<PathBuf> = std::fs::read_dir(lod)
        .expect("the stores' folder")
        .map(|entry| entry.expect("entry").path())
        .filter(|path| path.is_dir())
        .collect();
    let [store] = stores.as_slice() else {
        panic!("one store in {}: {stores:?}", lod.display());
    };
    let payload = store.join("nodes.bin");
    assert!(payload.is_file(), "{} missing", payload.display());
    payload
}

/// Flips bits all along the payload file `path`, as a failing disk might: every node record
/// is damaged, its length unchanged.
fn flip_bytes(path: &Path) {
    let mut bytes = std::fs::read(path).expect("read the payload");
    assert!(bytes.len() > 1_000, "a payload of {} bytes", bytes.len());
    for at in (0..bytes.len()).step_by(97) {
        bytes[at] ^= 0x5a;
    }
    std::fs::write(path, bytes).expect("damage the payload");
}

/// `pointfarm render` of `file` into `out` from its store in `cache`, at `lod_error` pixels.
fn render_from_a_store(
    file: &Path,
    cache: &Path,
    lod_error: &str,
    out: &Path,
) -> std::process::Output {
    pointfarm_ok(&[
        "render",
        path_arg(file),
        "--out",
        path_arg(out),
        "--size=160x120",
        "--lod-error",
        lod_error,
        "--cache-dir",
        path_arg(cache),
    ])
}

fn image(path: &Path) -> image::RgbaImage {
    image::open(path).expect("png").to_rgba8()
}

#[test]
fn a_local_store_that_fails_its_checks_is_built_again_and_draws_the_same_frame() {
    let dir = tempfile::tempdir().expect("tempdir");
    let file = scene(dir.path());
    let cache = dir.path().join("cache");
    // A pixel error asks for levels of detail: a store, not a resident cloud.
    let render = |out: &Path| render_from_a_store(&file, &cache, "0.5", out);
    let first = dir.path().join("first.png");
    let built = output_text(&render(&first));
    assert!(built.contains("levels of detail:"), "{built}");
    assert!(!built.contains("rebuilding"), "{built}");
    let payload = payload_of_the_store_in(&cache.join("lod"));

    flip_bytes(&payload);
    let healed = dir.path().join("healed.png");
    let output = render(&healed);
    let text = output_text(&output);
    let stdout = String::from_utf8_lossy(&output.stdout);
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(
        stdout.contains("failed its checks") && stdout.contains("rebuilding it"),
        "{text}"
    );
    assert!(stdout.contains("levels of detail:"), "built again: {text}");
    assert!(stderr.contains("rebuilding a damaged store"), "{text}");
    assert!(
        image(&healed) == image(&first),
        "the rebuilt store draws another frame\n{text}"
    );

    // Built again, the store is whole: the next render opens it as it is.
    let again = dir.path().join("again.png");
    let text = output_text(&render(&again));
    assert!(!text.contains("rebuilding"), "{text}");
    assert!(!text.contains("levels of detail:"), "built again: {text}");
    assert!(image(&again) == image(&first));

    // A payload file cut short is damage too.
    let file = std::fs::OpenOptions::new()
        .write(true)
        .open(&payload)
        .expect("open the payload");
    let len = file.metadata().expect("metadata").len();
    file.set_len(len / 2).expect("cut the payload short");
    drop(file);
    let cut_short = dir.path().join("cut-short.png");
    let text = output_text(&render(&cut_short));
    assert!(text.contains("rebuilding it"), "{text}");
    assert!(image(&cut_short) == image(&first));
}

/// A store larger than the sample of coarse nodes read as it opens, damaged only where that
/// sample does not reach: the damage is found by the frame's own reads, the store built again
/// there, and the frame drawn from the new store as from the first.
#[test]
fn damage_a_frame_reads_builds_the_store_again_and_draws_the_frame_from_it() {
    let dir = tempfile::tempdir().expect("tempdir");
    let file = dir.path().join("large.laz");
    let points = ELEVATION_SAMPLE_POINTS as usize + 150_000;
    write_las(&file, &sample_scene(points, 4), &LasWriteOptions::default())
        .expect("write the scene");
    let cache = dir.path().join("cache");
    // Every node read whole: no coarse reads at a pixel error of 0.
    let render = |out: &Path| render_from_a_store(&file, &cache, "0", out);
    let first = dir.path().join("first.png");
    render(&first);
    let payload = payload_of_the_store_in(&cache.join("lod"));
    let folder = payload.parent().expect("the store's folder").to_owned();

    // The nodes past the coarse sample (taken by key, up to its points) as it opens.
    let store = StoredLod::open_or_build(&[], &folder, 64 << 20, None, &mut |_| {})
        .expect("open the store");
    let mut nodes: Vec<NodeInfo> = store.dataset.hierarchy().stored_nodes().copied().collect();
    drop(store);
    nodes.sort_by_key(|n| n.key);
    let mut sampled = 0;
    let unsampled: Vec<NodeInfo> = nodes
        .into_iter()
        .skip_while(|n| {
            let in_sample = sampled < ELEVATION_SAMPLE_POINTS;
            sampled += u64::from(n.point_count);
            in_sample
        })
        .collect();
    assert!(!unsampled.is_empty(), "every node is in the sample");
    let mut bytes = std::fs::read(&payload).expect("read the payload");
    for node in &unsampled {
        let last = node.pieces(node.byte_len).last().expect("a piece");
        bytes[(last.end - 9) as usize] ^= 0x5a;
    }
    std::fs::write(&payload, bytes).expect("damage the payload");

    let healed = dir.path().join("healed.png");
    let text = output_text(&render(&healed));
    assert!(text.contains("failed its checks"), "{text}");
    assert_eq!(text.matches("rebuilding it").count(), 1, "{text}");
    assert!(
        image(&healed) == image(&first),
        "the rebuilt store draws another frame\n{text}"
    );
}

const REBUILDS: &str = "pointfarm_store_rebuilds_total";

#[test]
fn a_daemon_store_that_fails_its_checks_is_built_again_once_then_reported() {
    let dir = tempfile::tempdir().expect("tempdir");
    let file = scene(dir.path());
    let data = dir.path().join("data");
    let metrics = free_address();
    let server = ServeProcess::start_with(&data, &["--metrics-listen", &metrics]);
    // Each job asks for its own pixel error: the embedded worker opens the daemon's store
    // again for it, with empty node caches, and reads its nodes from the daemon.
    let job = |name: &str, lod_error: &str| {
        let out = dir.path().join(name);
        let output = pointfarm(&[
            "render",
            path_arg(&file),
            "--out",
            path_arg(&out),
            "--size=160x120",
            "--lod-error",
            lod_error,
            "--server",
            &server.address,
        ]);
        (output, out)
    };
    let (first, _) = job("first.png", "0.5");
    assert!(first.status.success(), "{}", output_text(&first));
    assert_eq!(scrape(&metrics).get(REBUILDS).copied(), Some(0.0));
    let payload = payload_of_the_store_in(&data.join("lod"));

    // Damaged on disk: the daemon finds it as it serves the next job's nodes, builds the
    // store again once, and the frame tried again renders from the new store.
    flip_bytes(&payload);
    let (second, healed) = job("second.png", "0.25");
    assert!(
        second.status.success(),
        "{}\n{}",
        output_text(&second),
        server.log()
    );
    let log = server.log();
    assert_eq!(
        log.matches("rebuilding a damaged store").count(),
        1,
        "{log}"
    );
    assert!(
        log.lines()
            .any(|line| line.contains("rebuilding a damaged store") && line.contains("dataset=")),
        "{log}"
    );
    assert_eq!(scrape(&metrics).get(REBUILDS).copied(), Some(1.0));
    // The frame a local render draws of the same file.
    let local = dir.path().join("local.png");
    pointfarm_ok(&[
        "render",
        path_arg(&file),
        "--out",
        path_arg(&local),
        "--size=160x120",
        "--lod-error",
        "0.25",
        "--cache-dir",
        path_arg(&dir.path().join("cache")),
    ]);
    assert!(
        image(&healed) == image(&local),
        "the rebuilt store draws another frame\n{log}"
    );

    // The damage comes back: the job fails saying so, naming the dataset by its id and its
    // file's name, and nothing is built a second time.
    flip_bytes(&payload_of_the_store_in(&data.join("lod")));
    let (third, _) = job("third.png", "1");
    let text = output_text(&third);
    assert!(!third.status.success(), "{text}");
    assert_ne!(third.status.code(), Some(101), "a panic:\n{text}");
    assert!(text.contains("failed its checks again"), "{text}");
    assert!(
        text.contains("dataset ") && text.contains("(scene.laz)"),
        "{text}"
    );
    assert!(!text.contains(path_arg(&data)), "a server path:\n{text}");
    let log = server.log();
    assert_eq!(
        log.matches("rebuilding a damaged store").count(),
        1,
        "{log}"
    );
    assert_eq!(scrape(&metrics).get(REBUILDS).copied(), Some(1.0));
}

//! A campaign that grows through the server: `pointfarm render --server` of a folder of tiles
//! that gained a tile uploads the new tile, composes the dataset of all of them, and the daemon
//! makes its store by updating a copy of the earlier dataset's store, not by building it whole.
//! Its frames equal a fresh daemon's within the fidelity rule, its store holds the same points
//! (each in one node), and the earlier dataset still renders from its own store, untouched. A
//! dataset composed without a tile is made the same way. An update killed part way (the build's
//! test hook, `POINTFARM_TEST_PAUSE_AT=update:0`) never leaves a store to serve: the daemon
//! started again makes it anew, and a preview job meanwhile draws the new content's sample.
//! A chain of growths holds the earlier payloads as hard-linked layers, none copied: the last
//! store renders the same once the earlier stores' folders are gone, and a grown store
//! published to object storage (`s3s-fs`, skipped without `POINTFARM_TEST_S3S_FS`) is the one
//! payload object its layers make together. A growth from a store mostly of dead bytes is
//! compacted into one file (`store_growth/compaction.rs`).

use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::time::Duration;

use pointfarm_bench::daemon_log::number_after;
use pointfarm_render::cloud::PointCloud;
use pointfarm_render::cut::StoredLod;
use pointfarm_render::ingest::{write_las, LasWriteOptions};
use pointfarm_render::sample::sample_scene;
use pointfarm_tests::s3s::S3Bucket;
use pointfarm_tests::stores::{every_node, serve_pausing_at};
use pointfarm_tests::tiles::ground_plan_tiles;
use pointfarm_tests::{
    assert_pngs_alike, free_address, output_text, pointfarm_bin, pointfarm_with, wait_for,
    ServeProcess,
};

#[path = "store_growth/compaction.rs"]
mod compaction;

/// Tiles across and along: 21, the middle one the new day's.
const ACROSS: usize = 3;
const ALONG: usize = 7;
/// Points of the campaign whose update is timed against its whole build.
const POINTS: usize = 1_050_000;
/// Points of the campaign whose update is killed.
const KILLED_POINTS: usize = 210_000;
const SIZE: &str = "200x150";
/// The tile a crew drops from the first day's.
const DROPPED: usize = 1;
/// A tile inside the others' cube, which the earliest day of a chain of growths lacks.
const INNER: usize = ACROSS + 1;

/// The scene's tiles, every one in `dir/all`, and the folders of the campaign's days as links
/// to them: `day1` without the middle tile, `day2` with every tile, `less` as `day1` without
/// tile [`DROPPED`], `least` as `less` without tile [`INNER`].
struct Campaign {
    day1: PathBuf,
    day2: PathBuf,
    less: PathBuf,
    least: PathBuf,
    /// Flags of the camera every render shares.
    camera: Vec<String>,
}

fn tile_name(index: usize) -> String {
    format!("tile-{index:02}.las")
}

fn write_campaign(dir: &Path, points: usize) -> Campaign {
    let cloud = sample_scene(points, 11);
    let tiles = ground_plan_tiles(&cloud, ACROSS, ALONG);
    let all = dir.join("all");
    std::fs::create_dir_all(&all).expect("folder");
    for (index, points) in tiles.iter().enumerate() {
        let path = all.join(tile_name(index));
        write_las(&path, &cloud.select(points), &LasWriteOptions::default()).expect("tile");
    }
    let middle = ACROSS * ALONG / 2;
    let day = |name: &str, leave_out: &[usize]| {
        let folder = dir.join(name);
        std::fs::create_dir_all(&folder).expect("folder");
        for index in (0..tiles.len()).filter(|i| !leave_out.contains(i)) {
            let name = tile_name(index);
            std::fs::hard_link(all.join(&name), folder.join(&name)).expect("link a tile");
        }
        folder
    };
    Campaign {
        day1: day("day1", &[middle]),
        day2: day("day2", &[]),
        less: day("less", &[middle, DROPPED]),
        least: day("least", &[middle, DROPPED, INNER]),
        camera: camera_flags(&cloud),
    }
}

/// Flags of a camera that looks at the whole of `cloud` from above one side.
fn camera_flags(cloud: &PointCloud) -> Vec<String> {
    let (min, size) = (cloud.bounds.min, cloud.bounds.size());
    let center = min + size * 0.5;
    let reach = size.x.max(size.y);
    let xyz = |[x, y, z]: [f64; 3]| format!("{x},{y},{z}");
    let position = [
        center.x + 0.2 * reach,
        center.y - 0.9 * reach,
        center.z + 0.8 * reach,
    ];
    vec![
        format!("--camera-pos={}", xyz(position)),
        format!("--camera-target={}", xyz(center.to_array())),
        "--camera-up=0,0,1".to_owned(),
        "--point-size=2".to_owned(),
    ]
}

/// `pointfarm serve` with its data in `data`, its builds stopped for good at `pause_at`; each
/// start logs to a file of its own beside `data`.
fn serve(address: &str, data: &Path, pause_at: Option<&str>) -> ServeProcess {
    static STARTS: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
    let start = STARTS.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let log = data.with_file_name(format!("serve-{start}.log"));
    let budget = ["--store-memory-budget", "96MiB"];
    serve_pausing_at(address, (data, &log), &budget, pause_at)
}

/// `pointfarm render --server` of `tiles` into `out` through levels of detail.
fn render(server: &ServeProcess, tiles: &Path, out: &Path, camera: &[String]) -> Command {
    let mut command = Command::new(pointfarm_bin());
    command.arg("render").arg(tiles).arg("--out").arg(out);
    command.arg(format!("--size={SIZE}")).arg("--lod-error=0");
    command.arg(format!("--server=http://{}", server.address));
    command.args(camera).env_remove("POINTFARM_TEST_PAUSE_AT");
    command
}

fn run(command: &mut Command, server: &ServeProcess) -> Output {
    let output = command.output().expect("run pointfarm");
    assert!(
        output.status.success(),
        "{}\n--- daemon:\n{}",
        output_text(&output),
        server.log()
    );
    output
}

/// Stops `server` as an operator would, waiting for it to end.
fn stop(server: &mut ServeProcess) {
    server
        .terminate(Duration::from_secs(30))
        .expect("the daemon stops");
}

/// A campaign of `points` points written under a temporary folder, with the folder of a
/// daemon's data beside it and the address every start of that daemon listens on.
fn site(points: usize) -> (tempfile::TempDir, Campaign, PathBuf, String) {
    let dir = tempfile::tempdir().expect("tempdir");
    let campaign = write_campaign(dir.path(), points);
    let data = dir.path().join("daemon");
    (dir, campaign, data, free_address())
}

/// The id of the dataset a `render --server` says it rendered.
fn dataset_of(output: &Output) -> String {
    let text = output_text(output);
    let at = text.find(": dataset ds-").expect("the dataset's id") + ": dataset ".len();
    text[at..]
        .split_whitespace()
        .next()
        .expect("an id")
        .to_owned()
}

/// The seconds a daemon's log gives on its first line saying `message`.
fn seconds_said(log: &str, message: &str) -> Option<f64> {
    let line = log.lines().find(|l| l.contains(message))?;
    number_after(line, " seconds=")
}

/// The finished store under `data` that lists `files` files.
fn store_of(data: &Path, files: usize) -> PathBuf {
    let lod = data.join("lod");
    std::fs::read_dir(&lod)
        .expect("the daemon's stores")
        .map(|entry| entry.expect("entry").path())
        .find(|path| {
            StoredLod::is_built(path)
                && std::fs::read_to_string(path.join("contents.txt"))
                    .is_ok_and(|list| list.lines().count() == files)
        })
        .unwrap_or_else(|| panic!("no store of {files} files in {}", lod.display()))
}

/// Every point of the store in `folder`, from every node, as millimetres and attributes,
/// sorted: two stores of the same points, each in one node, give the same list.
fn store_points(folder: &Path) -> Vec<[i64; 6]> {
    let (nodes, _) = every_node(folder);
    let mut points: Vec<[i64; 6]> = nodes
        .iter()
        .flat_map(|node| {
            let positions = node.world_positions();
            (0..node.len())
                .map(|i| {
                    let mm = |v: f64| (v * 1000.0).round() as i64;
                    let p = positions[i];
                    [
                        mm(p.x),
                        mm(p.y),
                        mm(p.z),
                        i64::from(node.intensity[i]),
                        i64::from(node.classification[i]),
                        i64::from(node.return_number[i]),
                    ]
                })
                .collect::<Vec<_>>()
        })
        .collect();
    points.sort_unstable();
    points
}

/// Renders `tiles` (`files` files) on a fresh daemon in `dir/name`, which builds their store
/// whole, and asserts that `frame` looks like its frame and that the store in `store` holds
/// the fresh store's points (`what` says of which store); returns them.
fn assert_as_a_fresh_build(
    dir: &Path,
    name: &str,
    (tiles, files): (&Path, usize),
    camera: &[String],
    (store, frame): (PathBuf, &Path),
    what: &str,
) -> Vec<[i64; 6]> {
    let fresh_data = dir.join(name);
    let mut server = serve(&free_address(), &fresh_data, None);
    let fresh = dir.join(format!("{name}.png"));
    run(&mut render(&server, tiles, &fresh, camera), &server);
    let log = server.log();
    assert!(!log.contains("updated the store of"), "{log}");
    stop(&mut server);
    let message = format!("{what}'s frame differs from a fresh build's");
    assert_pngs_alike(name, frame, &fresh, &message);
    let points = store_points(&store);
    assert!(
        points == store_points(&store_of(&fresh_data, files)),
        "{what} holds other points than a fresh build's"
    );
    points
}

#[test]
fn a_campaign_that_grows_or_drops_a_tile_through_the_server_updates_its_store() {
    let (dir, campaign, data, address) = site(POINTS);
    let camera = &campaign.camera;
    let mut server = serve(&address, &data, None);

    // Day one: its store is built whole.
    let day1 = dir.path().join("day1.png");
    let said = run(&mut render(&server, &campaign.day1, &day1, camera), &server);
    let day1_id = dataset_of(&said);
    let whole = seconds_said(&server.log(), "levels of detail built").expect("a whole build");

    // Day two: the new tile is uploaded, the dataset composed, and its store updated.
    let day2 = dir.path().join("day2.png");
    run(&mut render(&server, &campaign.day2, &day2, camera), &server);
    let log = server.log();
    let from_day1 = format!("from the store of dataset {day1_id}");
    assert!(
        log.contains(&format!("{from_day1}: 1 files added, 0 removed")),
        "{log}"
    );
    let updated = seconds_said(&log, "updated the store of").expect("an update");
    assert_eq!(
        log.matches("levels of detail built").count(),
        1,
        "built whole again:\n{log}"
    );
    println!(
        "whole build of 20 tiles: {whole:.2} s; store of 21 tiles updated from it: \
         {updated:.2} s ({:.0}%)",
        100.0 * updated / whole
    );

    // A tile dropped from day one's: updated from day one's store, the nearest (one tile
    // removed, where day two's needs two).
    let less = dir.path().join("less.png");
    run(&mut render(&server, &campaign.less, &less, camera), &server);
    let log = server.log();
    assert!(
        log.contains(&format!("{from_day1}: 0 files added, 1 removed")),
        "{log}"
    );
    assert_eq!(log.matches("levels of detail built").count(), 1, "{log}");

    // Day one's dataset renders as before from its own store, opened again from disk.
    stop(&mut server);
    let mut server = serve(&address, &data, None);
    let again = dir.path().join("day1-again.png");
    run(
        &mut render(&server, &campaign.day1, &again, camera),
        &server,
    );
    assert_pngs_alike(
        "growth-day1",
        &again,
        &day1,
        "day one's dataset draws otherwise after its store was grown from",
    );
    stop(&mut server);

    // Each updated store draws and holds what a fresh daemon's build does.
    let day2_fresh = (campaign.day2.as_path(), 21);
    let grown = (store_of(&data, 21), day2.as_path());
    let what = "the grown store";
    let points = assert_as_a_fresh_build(dir.path(), "fresh-day2", day2_fresh, camera, grown, what);
    assert_eq!(points.len(), POINTS, "every point once");
    let less_fresh = (campaign.less.as_path(), 19);
    let less = (store_of(&data, 19), less.as_path());
    let what = "the store less a tile";
    assert_as_a_fresh_build(dir.path(), "fresh-less", less_fresh, camera, less, what);
}

#[test]
fn an_update_killed_part_way_is_made_again_and_a_preview_meanwhile_shows_the_new_tile() {
    let (dir, campaign, data, address) = site(KILLED_POINTS);
    let camera = &campaign.camera;
    let mut server = serve(&address, &data, Some("update:0"));
    let day1 = dir.path().join("day1.png");
    run(&mut render(&server, &campaign.day1, &day1, camera), &server);

    // Day two's render asks for previews; its store's update stops for good before it switches.
    let preview = dir.path().join("day2-preview.png");
    let mut previewing = render(&server, &campaign.day2, &preview, camera)
        .arg("--preview")
        .spawn()
        .expect("start pointfarm");
    wait_for(
        Duration::from_secs(300),
        "the paused update and a preview",
        || (server.log().contains("build paused at update:0") && preview.exists()).then_some(()),
    );
    let _ = previewing.kill();
    let _ = previewing.wait();
    let log = server.log();
    // The preview is of day two's files, the new tile's among them.
    let sampled = log
        .lines()
        .find(|l| l.contains("preview sample read") && l.contains("files=21"));
    assert!(sampled.is_some(), "{log}");
    server.kill();

    // Nothing half-updated is left where a store is served from.
    let folders: Vec<PathBuf> = std::fs::read_dir(data.join("lod"))
        .expect("stores")
        .map(|e| e.expect("entry").path())
        .collect();
    assert_eq!(
        folders
            .iter()
            .filter(|f| f.to_string_lossy().ends_with(".growing"))
            .count(),
        1,
        "{folders:?}"
    );
    assert_eq!(
        folders.iter().filter(|f| StoredLod::is_built(f)).count(),
        1,
        "{folders:?}"
    );

    // Started again: the update is made anew from a fresh copy, and draws as a fresh build.
    let server = serve(&address, &data, None);
    let day2 = dir.path().join("day2.png");
    run(&mut render(&server, &campaign.day2, &day2, camera), &server);
    let log = server.log();
    assert!(
        log.contains("removing the store update a stopped daemon left"),
        "{log}"
    );
    assert!(log.contains(": 1 files added, 0 removed"), "{log}");
    assert!(
        !log.contains("levels of detail built"),
        "built whole:\n{log}"
    );
    drop(server);
    let day2_fresh = (campaign.day2.as_path(), 21);
    let updated = (store_of(&data, 21), day2.as_path());
    let what = "the store updated after a kill";
    assert_as_a_fresh_build(dir.path(), "fresh-day2", day2_fresh, camera, updated, what);
}

#[test]
fn a_store_built_before_stores_listed_their_files_is_listed_at_start_and_grows_a_chain() {
    let (dir, campaign, data, address) = site(POINTS);
    let camera = &campaign.camera;
    let mut server = serve(&address, &data, None);
    let first = dir.path().join("least.png");
    let said = run(
        &mut render(&server, &campaign.least, &first, camera),
        &server,
    );
    let first_id = dataset_of(&said);
    stop(&mut server);

    // The first day's store as one built before stores listed their files: without its list.
    let store = store_of(&data, 18);
    let listed = std::fs::read_to_string(store.join("contents.txt")).expect("a file list");
    std::fs::remove_file(store.join("contents.txt")).expect("unlist the store");

    // Started again, the daemon lists it from the dataset's record, proven by the store's facts.
    let mut server = serve(&address, &data, None);
    let log = server.log();
    assert!(
        log.contains("listed the files of a store built before stores listed them"),
        "{log}"
    );
    let derived = std::fs::read_to_string(store.join("contents.txt")).expect("listed again");
    assert_eq!(
        derived, listed,
        "the derived list differs from the one the build wrote"
    );

    // Three growths, each from the store before it, each linking the earlier payload.
    let mut from = first_id;
    let mut last = PathBuf::new();
    for (tiles, name) in [
        (&campaign.less, "less"),
        (&campaign.day1, "day1"),
        (&campaign.day2, "day2"),
    ] {
        last = dir.path().join(format!("{name}.png"));
        let said = run(&mut render(&server, tiles, &last, camera), &server);
        let grown = format!("from the store of dataset {from}: 1 files added, 0 removed");
        assert!(server.log().contains(&grown), "{}", server.log());
        from = dataset_of(&said);
    }
    let log = server.log();
    assert!(
        !log.contains("levels of detail built"),
        "built whole:\n{log}"
    );
    let copies: Vec<&str> = log
        .lines()
        .filter(|l| l.contains("copied the earlier store to update"))
        .collect();
    assert_eq!(copies.len(), 3, "{log}");
    for line in &copies {
        assert_eq!(
            number_after(line, " payload_bytes_copied="),
            Some(0.0),
            "{log}"
        );
    }
    stop(&mut server);

    // The earlier stores' folders gone, the last one holds its three layers and draws the same.
    let grown = store_of(&data, 21);
    let layers = std::fs::read_to_string(grown.join("nodes.bin.layers")).expect("layers");
    assert_eq!(layers.lines().count(), 3, "{layers}");
    for files in [18, 19, 20] {
        std::fs::remove_dir_all(store_of(&data, files)).expect("an earlier store removed");
    }
    let restarted = (address.as_str(), data.as_path());
    let again = (dir.path().join("growth-chain.png"), last.as_path());
    let what = "the grown store once the earlier stores are gone";
    let log = render_restarted(restarted, &campaign.day2, camera, again, what);
    assert!(
        !log.contains("levels of detail built") && !log.contains("updated the store of"),
        "made again:\n{log}"
    );

    // The end of the chain holds and draws what a fresh daemon's build does.
    let day2_fresh = (campaign.day2.as_path(), 21);
    let grown = (store_of(&data, 21), last.as_path());
    let what = "the store grown three times";
    assert_as_a_fresh_build(dir.path(), "fresh-day2", day2_fresh, camera, grown, what);

    // A layer changed underneath refuses the store when it opens: it is built again, whole.
    let layer = store_of(&data, 21).join("nodes.bin.0");
    let mut bytes = std::fs::read(&layer).expect("the layer");
    let middle = bytes.len() / 2;
    bytes[middle] ^= 0x55;
    std::fs::write(&layer, &bytes).expect("change the layer");
    let rebuilt = (dir.path().join("growth-refused-layer.png"), last.as_path());
    let what = "the store built again after its layer changed";
    let log = render_restarted(restarted, &campaign.day2, camera, rebuilt, what);
    assert!(
        log.contains("rebuilding a damaged store") && log.contains("payload layers are damaged"),
        "{log}"
    );
    assert!(log.contains("levels of detail built"), "{log}");
    assert!(!layer.exists(), "the refused layers are gone");
}

/// Renders `tiles` into `out` through a daemon started again at `address` over `data`,
/// asserts that the frame looks like `expected` (`what`'s frame), and returns the daemon's log.
fn render_restarted(
    (address, data): (&str, &Path),
    tiles: &Path,
    camera: &[String],
    (out, expected): (PathBuf, &Path),
    what: &str,
) -> String {
    let server = serve(address, data, None);
    run(&mut render(&server, tiles, &out, camera), &server);
    let name = out
        .file_stem()
        .expect("a name")
        .to_string_lossy()
        .into_owned();
    assert_pngs_alike(&name, &out, expected, &format!("{what} draws otherwise"));
    server.log()
}

#[test]
fn a_grown_store_is_published_as_the_one_payload_its_layers_make() {
    let Some(bucket) = S3Bucket::start_or_skip("pointfarm-grown") else {
        return;
    };
    let dir = tempfile::tempdir().expect("tempdir");
    let campaign = write_campaign(dir.path(), KILLED_POINTS);
    let camera = &campaign.camera;
    let data = dir.path().join("daemon");
    let mut command = pointfarm_with(&bucket.server.environment());
    command.env_remove("POINTFARM_TEST_PAUSE_AT");
    let server = ServeProcess::start_command(
        command,
        &free_address(),
        &data,
        &dir.path().join("serve.log"),
        &[
            "--store-memory-budget",
            "96MiB",
            "--store-url",
            "s3://pointfarm-grown/farm",
        ],
    );
    run(
        &mut render(
            &server,
            &campaign.day1,
            &dir.path().join("day1.png"),
            camera,
        ),
        &server,
    );
    run(
        &mut render(
            &server,
            &campaign.day2,
            &dir.path().join("day2.png"),
            camera,
        ),
        &server,
    );
    assert!(
        server.log().contains("updated the store of"),
        "{}",
        server.log()
    );
    wait_for(Duration::from_secs(120), "both stores published", || {
        (server.log().matches("store published").count() == 2).then_some(())
    });

    // The grown store's payload is its layer, the first day's, then its own file: published,
    // they are the one object a store built whole would be.
    let grown = store_of(&data, 21);
    let layers = std::fs::read_to_string(grown.join("nodes.bin.layers")).expect("layers");
    assert_eq!(layers.lines().count(), 1, "{layers}");
    let flattened = [
        std::fs::read(grown.join("nodes.bin.0")).expect("the layer"),
        std::fs::read(grown.join("nodes.bin")).expect("its own file"),
    ]
    .concat();
    let sha256 = grown.file_name().expect("a name").to_string_lossy();
    let key = format!("farm/{sha256}/nodes.bin");
    let published = std::fs::read(bucket.stored(&key)).expect("the published payload");
    assert_eq!(published.len(), flattened.len());
    assert!(published == flattened, "the published payload differs");
}

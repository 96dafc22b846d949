//! A level-of-detail store build killed with SIGKILL resumes: `pointfarm export` builds a
//! dataset's store, is stopped for good at a point of each stage by the build's test hook
//! (`POINTFARM_TEST_PAUSE_AT`, render/src/lod/pause.rs) or at a random moment, killed there,
//! and run again. The resumed run takes up what the killed one recorded (its log says from
//! which point its counting pass went on, or how many units it took over), and its store is
//! the uninterrupted build's node for node, point for point, attribute row for attribute row;
//! the COPC files exported from both are the same bytes.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use pointfarm_render::ingest::{write_las, LasWriteOptions};
use pointfarm_tests::stores::{
    assert_same_nodes, kill_build_at, logged, store_folder, store_nodes,
};
use pointfarm_tests::{output_text, path_arg, pointfarm_bin};

/// Points of the dataset: enough for several partitions and nodes above them on two cores.
const POINTS: usize = 1_000_000;
const MEMORY_BUDGET: &str = "64MiB";
/// Points of the dense dataset: several times the plan's partition size.
const DENSE_POINTS: usize = 1_000_000;

/// Two overlapping scans in a folder: the counting pass reads a batch of each.
fn write_dataset(dir: &Path) -> PathBuf {
    let folder = dir.join("scans");
    std::fs::create_dir_all(&folder).expect("folder");
    for seed in [7, 8] {
        let cloud = pointfarm_render::sample::sample_scene(POINTS / 2, seed);
        let path = folder.join(format!("scan-{seed}.las"));
        write_las(&path, &cloud, &LasWriteOptions::default()).expect("write the dataset");
    }
    folder
}

/// A scan of `DENSE_POINTS` points within a metre, and two points 10 km away on either side:
/// the counting grid cannot tell the dense points apart, so their partition, far above the
/// plan's size, is split on disk, level after level.
fn write_dense_dataset(dir: &Path) -> PathBuf {
    let path = dir.join("dense.las");
    let mut builder = las::Builder::from((1, 2));
    let transform = |offset| las::Transform {
        scale: 0.001,
        offset,
    };
    builder.transforms = las::Vector {
        x: transform(600_000.0),
        y: transform(5_000_000.0),
        z: transform(0.0),
    };
    let header = builder.into_header().expect("a header");
    let mut writer = las::Writer::from_path(&path, header).expect("a writer");
    let spread = |i: u32, k: u32| f64::from((i.wrapping_mul(k) >> 7) % 1000) / 1000.0;
    let dense = (0..DENSE_POINTS as u32).map(|i| {
        (
            600_300.0 + spread(i, 2_654_435_761),
            5_000_300.0 + spread(i, 40_503),
            10.0 + spread(i, 1_103_515_245),
        )
    });
    // The dense metre lies within one cell of every grid down to the finest split level.
    let outliers = [
        (610_000.0, 5_010_000.0, 0.0),
        (590_000.0, 4_990_000.0, 1_000.0),
    ];
    for (x, y, z) in dense.chain(outliers) {
        let point = las::Point {
            x,
            y,
            z,
            ..Default::default()
        };
        writer.write_point(point).expect("a point");
    }
    writer.close().expect("close the dataset");
    path
}

/// `pointfarm export` of `input` into `cache`, writing `copc`, on `threads` threads when
/// given (the build's own choice otherwise).
fn export(input: &Path, cache: &Path, copc: &Path, threads: Option<&str>) -> Command {
    let mut command = Command::new(pointfarm_bin());
    command
        .args([
            "export",
            path_arg(input),
            "--copc",
            path_arg(copc),
            "--force",
        ])
        .args([
            "--cache-dir",
            path_arg(cache),
            "--memory-budget",
            MEMORY_BUDGET,
        ])
        .env("RUST_LOG", "pointfarm_render=info")
        .env_remove("POINTFARM_TEST_PAUSE_AT");
    match threads {
        Some(threads) => command.env("RAYON_NUM_THREADS", threads),
        None => command.env_remove("RAYON_NUM_THREADS"),
    };
    command
}

/// Runs `command` to its end and returns its stderr, failing unless it succeeded.
fn run(command: &mut Command) -> String {
    let output = command.output().expect("run pointfarm");
    assert!(output.status.success(), "{}", output_text(&output));
    String::from_utf8_lossy(&output.stderr).into_owned()
}

/// How many units the resumed run took from the killed one, from its log; `None` when it
/// started over.
fn resumed_units(stderr: &str) -> Option<u64> {
    logged(stderr, "resuming a build", "units")
}

/// The point the resumed run's counting pass took up from; `None` when it did not.
fn counting_resumed_at(stderr: &str) -> Option<u64> {
    logged(stderr, "resuming a build's counting pass", "points")
}

struct Reference {
    input: PathBuf,
    threads: Option<&'static str>,
    partitions: u64,
    /// The uninterrupted export's wall time.
    seconds: f64,
    nodes: Vec<String>,
    copc: Vec<u8>,
    _dir: tempfile::TempDir,
}

/// The uninterrupted export of the dataset `write` writes, on `threads` threads when given.
fn reference(write: fn(&Path) -> PathBuf, threads: Option<&'static str>) -> Reference {
    let dir = tempfile::tempdir().expect("tempdir");
    let input = write(dir.path());
    let cache = dir.path().join("uninterrupted");
    let copc = dir.path().join("uninterrupted.copc.laz");
    // Built (when out of date) before the clock starts.
    let mut command = export(&input, &cache, &copc, threads);
    let started = Instant::now();
    let log = run(&mut command);
    let seconds = started.elapsed().as_secs_f64();
    assert!(resumed_units(&log).is_none(), "nothing to resume:\n{log}");
    Reference {
        seconds,
        partitions: logged(&log, "counted", "partitions").expect("the partitions counted"),
        nodes: store_nodes(&cache),
        copc: std::fs::read(&copc).expect("the COPC file"),
        input,
        threads,
        _dir: dir,
    }
}

/// Kills a build at `stage` (or after `after`), resumes it and checks the resumed store
/// against the uninterrupted one; returns the resumed run's log.
fn kill_and_resume(reference: &Reference, stage: Option<&str>, after: Duration) -> String {
    let dir = tempfile::tempdir().expect("tempdir");
    let cache = dir.path().join("cache");
    let copc = dir.path().join("resumed.copc.laz");
    let export = || export(&reference.input, &cache, &copc, reference.threads);
    let killed = kill_build_at(export(), stage, after);
    assert!(killed || stage.is_none(), "the paused build was running");
    let log = run(&mut export());
    assert_same_nodes(
        &store_nodes(&cache),
        &reference.nodes,
        &format!("{stage:?}"),
    );
    let exported = std::fs::read(&copc).expect("the COPC file");
    assert!(
        exported == reference.copc,
        "{stage:?}: the COPC files differ"
    );
    let spill = store_folder(&cache).join("spill");
    let left: Vec<_> = std::fs::read_dir(&spill)
        .map(|entries| entries.map(|e| e.expect("entry").path()).collect())
        .unwrap_or_default();
    assert!(
        left.is_empty(),
        "{stage:?}: the finished build left {left:?}"
    );
    log
}

#[test]
fn a_build_killed_in_any_stage_resumes_to_the_same_store() {
    // One thread: each unit is durable before the next starts, so the units a kill leaves
    // recorded are exactly those before it (on more threads, units queued beside it may be
    // synced together after it, and are done again).
    let reference = reference(write_dataset, Some("1"));
    // Killed in the first file of the counting pass, the build starts over.
    let log = kill_and_resume(&reference, Some("counting:0"), Duration::ZERO);
    assert_eq!(resumed_units(&log), None, "counted again");
    assert_eq!(counting_resumed_at(&log), None, "counted again");
    // Killed in the second file once the first is checkpointed, it counts from the second;
    // killed as the second file starts, before its checkpoint, it starts over.
    for stage in ["checkpoint:0", "counting:1"] {
        let log = kill_and_resume(&reference, Some(stage), Duration::ZERO);
        let from = counting_resumed_at(&log);
        eprintln!("{stage}: counting resumed at point {from:?}");
        let expected = (stage == "checkpoint:0").then_some(POINTS as u64 / 2);
        assert_eq!(from, expected, "{stage}");
    }
    // Killed with a unit's nodes written but not recorded: exactly the units recorded before
    // it are taken over, the rest done again.
    let partitions = reference.partitions;
    assert!(partitions >= 4, "{partitions} partitions");
    for (stage, recorded) in [
        ("partition:0", 0),
        ("partition:2", 2),
        ("parent:0", partitions),
        ("parent:1", partitions + 1),
    ] {
        let units = resumed_units(&kill_and_resume(&reference, Some(stage), Duration::ZERO));
        eprintln!("{stage}: {units:?} units taken over");
        assert_eq!(units, Some(recorded), "{stage}");
    }
    // Killed with every unit recorded: only the hierarchy is left to write.
    let log = kill_and_resume(&reference, Some("hierarchy:0"), Duration::ZERO);
    let units = resumed_units(&log);
    eprintln!("hierarchy:0: {units:?} units taken over");
    assert!(
        units.is_some_and(|units| units > partitions + 1),
        "{units:?}"
    );
}

#[test]
fn a_build_killed_at_random_moments_resumes_to_the_same_store() {
    let reference = reference(write_dataset, None);
    let seed = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .expect("clock")
        .subsec_nanos();
    for i in 0..2u32 {
        // From the start to the end of an uninterrupted export.
        let share = f64::from(seed.wrapping_mul(2_654_435_761).wrapping_add(i * 977) % 1000);
        let millis = (reference.seconds * share) as u64;
        eprintln!(
            "killing after {millis} ms of {:.0}",
            1000.0 * reference.seconds
        );
        kill_and_resume(&reference, None, Duration::from_millis(millis));
    }
}

/// A partition split on disk, killed in its second split with the children's files written
/// but the split not yet recorded: the first split is taken over, the second done again. On
/// one thread, so that no partition is recorded beside the splits.
#[test]
fn a_build_killed_in_a_split_resumes_to_the_same_store() {
    let reference = reference(write_dense_dataset, Some("1"));
    let units = resumed_units(&kill_and_resume(
        &reference,
        Some("split:1"),
        Duration::ZERO,
    ));
    eprintln!("split:1: {units:?} units taken over");
    assert_eq!(units, Some(1), "the first split taken over");
}

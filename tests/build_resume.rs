//! A level-of-detail store build killed with SIGKILL resumes: `pointfarm export` builds a
//! dataset's store, is stopped for good at a point of each stage by the build's test hook
//! (`POINTFARM_TEST_PAUSE_AT`, render/src/lod/pause.rs) or at a random moment, killed there,
//! and run again. The resumed run takes up what the killed one recorded (its log says from
//! which point its counting pass went on, or how many units it took over), and its store is
//! the uninterrupted build's node for node, point for point, attribute row for attribute row;
//! the COPC files exported from both are the same bytes.

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use pointfarm_render::cut::StoredLod;
use pointfarm_render::ingest::{write_las, LasWriteOptions};
use pointfarm_render::lod::{read_nodes, NodeKey};
use pointfarm_tests::{output_text, pointfarm_bin};

/// Points of the dataset: enough for several partitions and nodes above them on two cores.
const POINTS: usize = 1_000_000;
const MEMORY_BUDGET: &str = "64MiB";

fn arg(path: &Path) -> &str {
    path.to_str().expect("temporary paths are UTF-8")
}

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

/// `pointfarm export` of `input` into `cache`, writing `copc`.
fn export(input: &Path, cache: &Path, copc: &Path) -> Command {
    let mut command = Command::new(pointfarm_bin());
    command
        .args(["export", arg(input), "--copc", arg(copc), "--force"])
        .args(["--cache-dir", arg(cache), "--memory-budget", MEMORY_BUDGET])
        .env("RUST_LOG", "pointfarm_render=info")
        .env_remove("POINTFARM_TEST_PAUSE_AT");
    command
}

/// Runs `command` to its end and returns its stderr, failing unless it succeeded.
fn run(command: &mut Command) -> String {
    let output = command.output().expect("run pointfarm");
    assert!(output.status.success(), "{}", output_text(&output));
    String::from_utf8_lossy(&output.stderr).into_owned()
}

/// Starts `command` and kills it with SIGKILL once it says the build paused at `stage`, or,
/// with no stage, after `after`. Returns whether the build was still under way when killed.
fn kill_at(mut command: Command, stage: Option<&str>, after: Duration) -> bool {
    if let Some(stage) = stage {
        command.env("POINTFARM_TEST_PAUSE_AT", stage);
    }
    let mut child = command
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("start pointfarm");
    let stderr = child.stderr.take().expect("stderr");
    let (lines, said) = mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(stderr).lines().map_while(Result::ok) {
            let _ = lines.send(line);
        }
    });
    let deadline = Instant::now() + Duration::from_secs(300);
    let mut heard = Vec::new();
    if let Some(stage) = stage {
        let wanted = format!("build paused at {stage}");
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match said.recv_timeout(left) {
                Ok(line) if line.contains(&wanted) => break,
                Ok(line) => heard.push(line),
                Err(_) => panic!("never paused at {stage}:\n{}", heard.join("\n")),
            }
        }
    } else {
        std::thread::sleep(after);
    }
    let running = child.try_wait().expect("poll").is_none();
    child.kill().expect("SIGKILL");
    child.wait().expect("reap");
    running
}

/// The one store folder under `cache`.
fn store_folder(cache: &Path) -> PathBuf {
    let lod = cache.join("lod");
    let mut folders: Vec<PathBuf> = std::fs::read_dir(&lod)
        .expect("the store cache")
        .map(|entry| entry.expect("entry").path())
        .filter(|path| path.is_dir())
        .collect();
    assert_eq!(folders.len(), 1, "{folders:?}");
    folders.pop().expect("one store")
}

/// The store's nodes as the cut reads them: each node's hierarchy entry (without where its
/// bytes lie), decoded points and attribute rows.
fn store_nodes(cache: &Path) -> Vec<String> {
    let folder = store_folder(cache);
    let stored = StoredLod::open_or_build(&[], &folder, 64 << 20, None, &mut |_| {})
        .expect("a finished store");
    let dataset = &stored.dataset;
    let hierarchy = dataset.hierarchy();
    let keys: Vec<NodeKey> = hierarchy.nodes().iter().map(|n| n.key).collect();
    let records = dataset.records().as_ref();
    let points = read_nodes(records, hierarchy, &keys).expect("every node reads back");
    let rows = records
        .read_attribute_rows(hierarchy, hierarchy.nodes())
        .expect("the store keeps attributes")
        .expect("every attributes section reads back");
    hierarchy
        .nodes()
        .iter()
        .zip(points)
        .zip(rows)
        .map(|((info, points), rows)| {
            format!(
                "{} points {} grid {} children {:08b}: {points:?} rows {rows:?}",
                info.key, info.point_count, info.sample_grid, info.child_mask
            )
        })
        .collect()
}

/// The number after `name=` on the first line of `stderr` that says `message`.
fn logged(stderr: &str, message: &str, name: &str) -> Option<u64> {
    let line = stderr.lines().find(|l| l.contains(message))?;
    let at = line.find(&format!(" {name}="))? + name.len() + 2;
    let digits: String = line[at..]
        .chars()
        .take_while(char::is_ascii_digit)
        .collect();
    digits.parse().ok()
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
    partitions: u64,
    /// The uninterrupted export's wall time.
    seconds: f64,
    nodes: Vec<String>,
    copc: Vec<u8>,
    _dir: tempfile::TempDir,
}

fn reference() -> Reference {
    let dir = tempfile::tempdir().expect("tempdir");
    let input = write_dataset(dir.path());
    let cache = dir.path().join("uninterrupted");
    let copc = dir.path().join("uninterrupted.copc.laz");
    // Built (when out of date) before the clock starts.
    let mut command = export(&input, &cache, &copc);
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
        _dir: dir,
    }
}

/// Kills a build at `stage` (or after `after`), resumes it and checks the resumed store
/// against the uninterrupted one; returns the resumed run's log.
fn kill_and_resume(reference: &Reference, stage: Option<&str>, after: Duration) -> String {
    let dir = tempfile::tempdir().expect("tempdir");
    let cache = dir.path().join("cache");
    let copc = dir.path().join("resumed.copc.laz");
    let killed = kill_at(export(&reference.input, &cache, &copc), stage, after);
    assert!(killed || stage.is_none(), "the paused build was running");
    let log = run(&mut export(&reference.input, &cache, &copc));
    let nodes = store_nodes(&cache);
    assert_eq!(nodes.len(), reference.nodes.len(), "{stage:?}: nodes");
    for (resumed, uninterrupted) in nodes.iter().zip(&reference.nodes) {
        assert!(resumed == uninterrupted, "{stage:?}: a node differs");
    }
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
    let reference = reference();
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
    // Killed with a unit's nodes written but not recorded (the other threads wait to record
    // theirs): exactly the units recorded before it are taken over, the rest done again.
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
    let reference = reference();
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

//! A level-of-detail store's content, compared between builds: a store built by a run that
//! was killed and resumed must equal an uninterrupted build's node for node. Builds are stopped
//! where a test wants them by the build's test hook (`POINTFARM_TEST_PAUSE_AT`).

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use pointfarm_bench::daemon_log::number_after;
use pointfarm_render::cut::StoredLod;
use pointfarm_render::lod::{read_nodes, NodeKey, NodePoints, RootCube};

use crate::{pointfarm_bin, ServeProcess};

/// The one store folder under `cache`'s `lod` folder (a CLI cache, or a daemon's data).
pub fn store_folder(cache: &Path) -> PathBuf {
    let lod = cache.join("lod");
    let mut folders: Vec<PathBuf> = std::fs::read_dir(&lod)
        .expect("the store cache")
        .map(|entry| entry.expect("entry").path())
        .filter(|path| path.is_dir())
        .collect();
    assert_eq!(folders.len(), 1, "{folders:?}");
    folders.pop().expect("one store")
}

/// Every node of the finished store in `folder`, read whole, and the store's cube. The store
/// must not be open elsewhere (its index is locked while it is).
pub fn every_node(folder: &Path) -> (Vec<NodePoints>, RootCube) {
    let stored = StoredLod::open_or_build(&[], folder, 64 << 20, None, &mut |_| {})
        .expect("a finished store");
    let hierarchy = stored.dataset.hierarchy();
    let keys: Vec<NodeKey> = hierarchy.nodes().iter().map(|n| n.key).collect();
    let nodes = read_nodes(stored.dataset.records().as_ref(), hierarchy, &keys).expect("nodes");
    (nodes, hierarchy.cube)
}

/// The nodes of the finished store under `cache` as the cut reads them: each node's
/// hierarchy entry (without where its bytes lie), decoded points and attribute rows. The
/// store must not be open elsewhere (its index is locked while it is).
pub fn store_nodes(cache: &Path) -> Vec<String> {
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

/// Asserts that `resumed` holds the nodes of `uninterrupted`, in order, naming `what`.
pub fn assert_same_nodes(resumed: &[String], uninterrupted: &[String], what: &str) {
    assert_eq!(resumed.len(), uninterrupted.len(), "{what}: nodes");
    for (resumed, uninterrupted) in resumed.iter().zip(uninterrupted) {
        // Not assert_eq: a node's points would fill the screen.
        assert!(resumed == uninterrupted, "{what}: a node differs");
    }
}

/// The count after `name=` on the first line of `log` that says `message`.
pub fn logged(log: &str, message: &str, name: &str) -> Option<u64> {
    let line = log.lines().find(|l| l.contains(message))?;
    count_after(line, &format!(" {name}="))
}

/// The whole number following `key` in a log line, read as the benchmarks read a daemon's.
pub fn count_after(line: &str, key: &str) -> Option<u64> {
    let number = number_after(line, key)?;
    // Counts are far below 2^53, where every whole number is exact in an f64.
    (number.fract() == 0.0).then_some(number as u64)
}

/// Starts `command` (a `pointfarm` build) and kills it with SIGKILL once it says the build
/// paused at `stage` (`POINTFARM_TEST_PAUSE_AT`), or, with no stage, after `after`. Returns whether the build was still under way when killed.
pub fn kill_build_at(mut command: Command, stage: Option<&str>, after: Duration) -> bool {
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

/// `pointfarm serve ARGS` on `address` over `data`, logging to `log`, its store builds stopped
/// for good at `pause_at` (`POINTFARM_TEST_PAUSE_AT`) where given and run through where not,
/// whatever the test's own environment says.
pub fn serve_pausing_at(
    address: &str,
    (data, log): (&Path, &Path),
    args: &[&str],
    pause_at: Option<&str>,
) -> ServeProcess {
    serve_command_pausing_at(
        Command::new(pointfarm_bin()),
        address,
        (data, log),
        args,
        pause_at,
    )
}

/// [`serve_pausing_at`] running `command`, a `pointfarm` command with its own environment.
pub fn serve_command_pausing_at(
    mut command: Command,
    address: &str,
    (data, log): (&Path, &Path),
    args: &[&str],
    pause_at: Option<&str>,
) -> ServeProcess {
    match pause_at {
        Some(stage) => command.env("POINTFARM_TEST_PAUSE_AT", stage),
        None => command.env_remove("POINTFARM_TEST_PAUSE_AT"),
    };
    ServeProcess::start_command(command, address, data, log, args)
}

//! What resuming a level-of-detail store build costs: a campaign's store built once without a
//! stop, then built again killed (SIGKILL) at `--kills` random moments and resumed each time,
//! the total wall time of all the runs against the uninterrupted one's. Each build is a
//! process of its own (this program with `--build`) opening the store as the CLI and the
//! daemon do (`StoredLod::open_or_build`); the two stores are compared node for node, point
//! for point. docs/perf/lod-build-resume.md has its figures.
//!
//! ```text
//! lod-build-resume [--points N] [--files N] [--kills N] [--seed N] [--budget-mib N] [--dir DIR]
//! ```

use std::path::{Path, PathBuf};
use std::process::{Command, ExitCode, Stdio};
use std::time::{Duration, Instant};

use pointfarm_bench::campaign::{CampaignFlags, ScratchCampaign};
use pointfarm_bench::cli::{exit_code, parse_flags};
use pointfarm_render::cut::StoredLod;
use pointfarm_render::lod::read_nodes;
use rand::{Rng, SeedableRng};

const USAGE: &str = "usage: lod-build-resume [--points N] [--files N] [--kills N] [--seed N] \
                     [--budget-mib N] [--dir DIR]";

struct Args {
    campaign: CampaignFlags,
    kills: usize,
    seed: u64,
}

fn main() -> ExitCode {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let outcome = match args.first().map(String::as_str) {
        Some("--build") => build(&args[1..]),
        _ => parse(&args).and_then(|args| measure(&args)),
    };
    exit_code("lod-build-resume", outcome)
}

fn parse(args: &[String]) -> Result<Args, String> {
    let mut parsed = Args {
        campaign: CampaignFlags::new(20_000_000, 20),
        kills: 5,
        seed: 1,
    };
    parse_flags(args, USAGE, |flag, value| {
        match flag {
            "--kills" => parsed.kills = value.number()? as usize,
            "--seed" => parsed.seed = value.number()?,
            _ => return parsed.campaign.apply(flag, &value),
        }
        Ok(true)
    })?;
    Ok(parsed)
}

/// The child: opens (building or resuming) the store in `FOLDER` from the files of `TILES`.
fn build(args: &[String]) -> Result<(), String> {
    let [tiles, folder, budget_mib] = args else {
        return Err("--build TILES FOLDER BUDGET_MIB".into());
    };
    let files = tile_files(Path::new(tiles))?;
    let budget = budget_mib.parse::<u64>().map_err(|e| e.to_string())? << 20;
    let stored = StoredLod::open_or_build(&files, Path::new(folder), budget, None, &mut |_| {})
        .map_err(|e| e.to_string())?;
    if let Some((report, seconds)) = &stored.built {
        println!(
            "built in {seconds:.2} s: counting resumed {}, {} units resumed, {} partitions",
            report.counting_resumed, report.resumed_units, report.partitions
        );
    }
    Ok(())
}

fn tile_files(dir: &Path) -> Result<Vec<PathBuf>, String> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(|e| format!("{}: {e}", dir.display()))?
        .filter_map(|entry| entry.ok().map(|e| e.path()))
        .filter(|path| path.extension().is_some_and(|ext| ext == "laz"))
        .collect();
    files.sort();
    Ok(files)
}

/// One build process, killed after `kill_after` if it runs that long; its wall time and
/// whether it finished.
fn run_build(
    args: &Args,
    tiles: &Path,
    folder: &Path,
    kill_after: Option<Duration>,
) -> (f64, bool) {
    let exe = std::env::current_exe().expect("this program's path");
    let started = Instant::now();
    let mut child = Command::new(exe)
        .args([
            "--build",
            &tiles.to_string_lossy(),
            &folder.to_string_lossy(),
        ])
        .arg(args.campaign.budget_mib.to_string())
        .stdout(Stdio::piped())
        .spawn()
        .expect("start a build");
    let finished = loop {
        if let Some(status) = child.try_wait().expect("poll the build") {
            assert!(status.success(), "a build failed: {status}");
            break true;
        }
        if kill_after.is_some_and(|limit| started.elapsed() >= limit) {
            child.kill().expect("SIGKILL");
            child.wait().expect("reap");
            break false;
        }
        std::thread::sleep(Duration::from_millis(10));
    };
    let seconds = started.elapsed().as_secs_f64();
    if finished {
        let output = child.wait_with_output().expect("output");
        print!("    {}", String::from_utf8_lossy(&output.stdout));
    }
    (seconds, finished)
}

fn measure(args: &Args) -> Result<(), String> {
    let ScratchCampaign {
        scratch,
        tiles,
        written,
    } = args.campaign.write("lod-build-resume")?;
    println!(
        "{} points in {} LAZ files",
        written.points,
        written.laz.len()
    );

    let uninterrupted = scratch.path().join("uninterrupted");
    println!("uninterrupted build:");
    let (whole, _) = run_build(args, &tiles, &uninterrupted, None);

    // The kill moments: `kills` random points of the uninterrupted build's time, in order;
    // each run is killed once it has run from the previous moment to its own.
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(args.seed);
    let mut moments: Vec<f64> = (0..args.kills)
        .map(|_| rng.random_range(0.02..0.98))
        .collect();
    moments.sort_by(f64::total_cmp);
    let resumed = scratch.path().join("resumed");
    let mut total = 0.0;
    let mut previous = 0.0;
    let mut finished = false;
    for moment in &moments {
        let after = Duration::from_secs_f64((moment - previous) * whole);
        let (seconds, done) = run_build(args, &tiles, &resumed, Some(after));
        println!(
            "killed at {:.0}% of the build: ran {seconds:.2} s",
            100.0 * moment
        );
        total += seconds;
        previous = *moment;
        if done {
            finished = true;
            break;
        }
    }
    if !finished {
        println!("resumed to the end:");
        total += run_build(args, &tiles, &resumed, None).0;
    }
    let same = same_store(&uninterrupted, &resumed)?;
    println!(
        "uninterrupted {whole:.2} s; killed {} times and resumed: {total:.2} s in all, {:.3}x; \
         the same store node for node: {same}",
        moments.len(),
        total / whole
    );
    if !same {
        return Err("the resumed store differs from the uninterrupted one".into());
    }
    Ok(())
}

/// Whether the finished stores in `a` and `b` hold the same nodes of the same points.
fn same_store(a: &Path, b: &Path) -> Result<bool, String> {
    let open = |folder: &Path| {
        StoredLod::open_or_build(&[], folder, 64 << 20, None, &mut |_| {})
            .map_err(|e| e.to_string())
    };
    let (a, b) = (open(a)?, open(b)?);
    let (ha, hb) = (a.dataset.hierarchy(), b.dataset.hierarchy());
    let entries = |h: &pointfarm_render::lod::LodHierarchy| -> Vec<_> {
        h.nodes()
            .iter()
            .map(|n| (n.key, n.point_count, n.sample_grid, n.child_mask))
            .collect()
    };
    if entries(ha) != entries(hb) {
        return Ok(false);
    }
    let keys: Vec<_> = ha.nodes().iter().map(|n| n.key).collect();
    for batch in keys.chunks(256) {
        let read = |s: &StoredLod, h| read_nodes(s.dataset.records().as_ref(), h, batch);
        let (pa, pb) = (
            read(&a, ha).map_err(|e| e.to_string())?,
            read(&b, hb).map_err(|e| e.to_string())?,
        );
        if pa != pb {
            return Ok(false);
        }
    }
    Ok(true)
}

//! What resuming a level-of-detail store build costs: a campaign's store built once without a
//! stop, then built again killed (SIGKILL) at `--kills` random moments and resumed each time,
//! the total wall and CPU time of all the runs against the uninterrupted one's (the CPU time,
//! user and system of the build processes, is the figure that holds on a shared host; the load
//! averages are printed beside). Each build is a process of its own (this program with
//! `--build`) opening the store as the CLI and the daemon do (`StoredLod::open_or_build`); the
//! two stores are compared node for node, point for point. docs/perf/lod-build-resume.md has
//! its figures.
//!
//! ```text
//! lod-build-resume [--points N] [--files N] [--kills N] [--seed N] [--budget-mib N] [--dir DIR]
//! ```

use std::path::Path;
use std::process::{Command, ExitCode, Stdio};
use std::time::{Duration, Instant};

use pointfarm_bench::campaign::cpu::{children_cpu_s, pid_cpu_s};
use pointfarm_bench::campaign::{CampaignFlags, ScratchCampaign};
use pointfarm_bench::cli::{exit_code, laz_files, parse_flags};
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
    let files = laz_files(Path::new(tiles))?;
    let budget = budget_mib.parse::<u64>().map_err(|e| e.to_string())? << 20;
    let stored = StoredLod::open_or_build(&files, Path::new(folder), budget, None, &mut |_| {})
        .map_err(|e| e.to_string())?;
    if let Some((report, seconds)) = &stored.built {
        let t = &report.timings;
        println!(
            "  built in {seconds:.2} s (counting {:.2} s, partitions {:.2} s, upper levels \
             {:.2} s): counting resumed {}, {} units resumed, {} partitions",
            t.counting.as_secs_f64(),
            t.partitions.as_secs_f64(),
            t.upper_levels.as_secs_f64(),
            report.counting_resumed,
            report.resumed_units,
            report.partitions
        );
    }
    Ok(())
}

/// What one build process took.
struct Run {
    wall_s: f64,
    /// User and system CPU of the process, counted once it was reaped (killed or not).
    cpu_s: f64,
    /// Its CPU read from `/proc/PID/stat` just before the kill: the check that a killed
    /// process's time is counted in `cpu_s`.
    cpu_before_kill_s: Option<f64>,
    finished: bool,
}

/// One build process, killed after `kill_after` if it runs that long.
fn run_build(args: &Args, tiles: &Path, folder: &Path, kill_after: Option<Duration>) -> Run {
    let exe = std::env::current_exe().expect("this program's path");
    let children_before = children_cpu_s();
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
    let mut cpu_before_kill_s = None;
    let finished = loop {
        if let Some(status) = child.try_wait().expect("poll the build") {
            assert!(status.success(), "a build failed: {status}");
            break true;
        }
        if kill_after.is_some_and(|limit| started.elapsed() >= limit) {
            cpu_before_kill_s = pid_cpu_s(child.id());
            child.kill().expect("SIGKILL");
            child.wait().expect("reap");
            break false;
        }
        std::thread::sleep(Duration::from_millis(10));
    };
    let wall_s = started.elapsed().as_secs_f64();
    let cpu_s = children_cpu_s() - children_before;
    if finished {
        let output = child.wait_with_output().expect("output");
        print!("{}", String::from_utf8_lossy(&output.stdout));
    }
    Run {
        wall_s,
        cpu_s,
        cpu_before_kill_s,
        finished,
    }
}

/// The 1-, 5- and 15-minute load averages (Linux), for reading the wall times of a shared host.
fn load_averages() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .map(|line| {
            line.split_whitespace()
                .take(3)
                .collect::<Vec<_>>()
                .join(" ")
        })
        .unwrap_or_else(|_| "unknown".into())
}

fn measure(args: &Args) -> Result<(), String> {
    println!("load average at the start: {}", load_averages());
    let ScratchCampaign {
        scratch,
        tiles,
        written,
    } = args.campaign.write("lod-build-resume")?;
    println!(
        "{} points in {} LAZ files; load average {}",
        written.points,
        written.laz.len(),
        load_averages()
    );

    let uninterrupted = scratch.path().join("uninterrupted");
    println!("uninterrupted build:");
    let whole = run_build(args, &tiles, &uninterrupted, None);
    println!(
        "  ran {:.2} s, CPU {:.2} s; load average {}",
        whole.wall_s,
        whole.cpu_s,
        load_averages()
    );

    // The kill moments: `kills` random points of the uninterrupted build's time, in order;
    // each run is killed once it has run from the previous moment to its own.
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(args.seed);
    let mut moments: Vec<f64> = (0..args.kills)
        .map(|_| rng.random_range(0.02..0.98))
        .collect();
    moments.sort_by(f64::total_cmp);
    let resumed = scratch.path().join("resumed");
    let (mut wall_s, mut cpu_s) = (0.0, 0.0);
    let mut previous = 0.0;
    let mut finished = false;
    for moment in &moments {
        let after = Duration::from_secs_f64((moment - previous) * whole.wall_s);
        let run = run_build(args, &tiles, &resumed, Some(after));
        let before_kill = run
            .cpu_before_kill_s
            .map_or_else(|| "-".into(), |s| format!("{s:.2} s"));
        println!(
            "killed at {:.0}% of the build: ran {:.2} s, CPU {:.2} s ({before_kill} read \
             before the kill)",
            100.0 * moment,
            run.wall_s,
            run.cpu_s
        );
        wall_s += run.wall_s;
        cpu_s += run.cpu_s;
        previous = *moment;
        if run.finished {
            finished = true;
            break;
        }
    }
    if !finished {
        println!("resumed to the end:");
        let run = run_build(args, &tiles, &resumed, None);
        println!("  ran {:.2} s, CPU {:.2} s", run.wall_s, run.cpu_s);
        wall_s += run.wall_s;
        cpu_s += run.cpu_s;
    }
    println!("load average at the end: {}", load_averages());
    let same = same_store(&uninterrupted, &resumed)?;
    println!(
        "uninterrupted {:.2} s wall, {:.2} s CPU; killed {} times and resumed: {wall_s:.2} s \
         wall in all ({:.3}x), {cpu_s:.2} s CPU in all ({:.3}x); the same store node for node: \
         {same}",
        whole.wall_s,
        whole.cpu_s,
        moments.len(),
        wall_s / whole.wall_s,
        cpu_s / whole.cpu_s
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

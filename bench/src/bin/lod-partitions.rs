//! The partitions stage's parallelism: a campaign's store built from LAZ at each of several
//! memory budgets and pool sizes, one row a build: how many partitions and how large, how
//! many were in memory at once (most and time-weighted mean), the largest one's CPU, the
//! stage's wall and CPU time (the kernel's part of it, and the pages first touched: minor
//! faults) and the least wall time its units' CPU allows on 16 threads. A
//! pool larger than the host's cores shows what the memory meter admits at once for that many
//! threads, the cores oversubscribed. The tiles are written once into `--tiles` and kept, so
//! that two binaries can be run alternately on the same files; the store digest compares
//! their stores. docs/perf/lod-partitions-parallelism.md has its figures.
//!
//! ```text
//! lod-partitions --tiles DIR [--points N] [--files N] [--budgets-mib 256,1024,4096]
//!                [--threads 2,16] [--journal on|off] [--dir DIR]
//! ```
//!
//! `--journal off` builds without the build's journal (as from a source without a
//! fingerprint): no unit's output is synced before it is recorded.

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::{Duration, Instant};

use pointfarm_bench::campaign::write_campaign;
use pointfarm_bench::cli::{exit_code, laz_files, parse_flags};
use pointfarm_bench::serve::load;
use pointfarm_render::cloud::WorldBounds;
use pointfarm_render::ingest::DatasetSource;
use pointfarm_render::lod::digest::store_digest;
use pointfarm_render::lod::partition_figures::PartitionsFigures;
use pointfarm_render::lod::{
    build_lod, AttributeSchema, BatchVisitor, LodBuildOptions, LodError, LodStore, PointSource,
    PositionGrid,
};

const USAGE: &str = "usage: lod-partitions --tiles DIR [--points N] [--files N] \
                     [--budgets-mib 256,1024,4096] [--threads 2,16] [--journal on|off] [--dir DIR]";

/// The seed of the campaign's terrain, the campaign bench's.
const SEED: u64 = 11;
/// The pool the ceiling is stated for: the 16-core host's.
const CEILING_THREADS: usize = 16;

struct Args {
    tiles: Option<PathBuf>,
    points: u64,
    files: usize,
    budgets_mib: Vec<u64>,
    threads: Vec<usize>,
    dir: Option<PathBuf>,
    journal: bool,
}

fn main() -> ExitCode {
    let args: Vec<String> = std::env::args().skip(1).collect();
    exit_code(
        "lod-partitions",
        parse(&args).and_then(|args| measure(&args)),
    )
}

fn parse(args: &[String]) -> Result<Args, String> {
    let mut parsed = Args {
        tiles: None,
        points: 20_000_000,
        files: 20,
        budgets_mib: vec![256, 1024, 4096],
        threads: vec![2, 16],
        dir: None,
        journal: true,
    };
    parse_flags(args, USAGE, |flag, value| {
        match flag {
            "--tiles" => parsed.tiles = Some(value.path()),
            "--points" => parsed.points = value.number()?,
            "--files" => parsed.files = value.number()? as usize,
            "--budgets-mib" => parsed.budgets_mib = value.numbers()?,
            "--threads" => {
                parsed.threads = value.numbers()?.into_iter().map(|t| t as usize).collect()
            }
            "--dir" => parsed.dir = Some(value.path()),
            "--journal" => {
                parsed.journal = match value.path().to_str() {
                    Some("on") => true,
                    Some("off") => false,
                    _ => return Err(format!("--journal is on or off\n{USAGE}")),
                }
            }
            _ => return Ok(false),
        }
        Ok(true)
    })?;
    if parsed.tiles.is_none() {
        return Err(format!("--tiles is needed\n{USAGE}"));
    }
    Ok(parsed)
}

fn measure(args: &Args) -> Result<(), String> {
    let tiles = args.tiles.as_deref().unwrap_or(Path::new("."));
    let files = tile_files(tiles, args)?;
    let scratch = tempfile::Builder::new()
        .prefix("lod-partitions-")
        .tempdir_in(args.dir.clone().unwrap_or_else(std::env::temp_dir))
        .map_err(|e| e.to_string())?;
    println!(
        "| threads | budget MiB | load | partitions (split) | points min / median / max | \
         in flight most / mean | largest CPU s | units CPU s | stage wall s | stage CPU s | \
         stage sys s | stage faults | ceiling on {CEILING_THREADS} s | store s | digest |"
    );
    println!("|---:|---:|---:|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---|");
    for &threads in &args.threads {
        for &budget in &args.budgets_mib {
            let load = load();
            let folder = scratch.path().join(format!("t{threads}-b{budget}"));
            let (figures, digest, build_s) = build(&files, &folder, threads, budget, args.journal)?;
            println!(
                "{}",
                row(threads, budget, &load, &figures, &digest, build_s)
            );
            std::fs::remove_dir_all(&folder).map_err(|e| e.to_string())?;
        }
    }
    Ok(())
}

/// The LAZ tiles in `dir`, written there first when it holds none.
fn tile_files(dir: &Path, args: &Args) -> Result<Vec<PathBuf>, String> {
    std::fs::create_dir_all(dir).map_err(|e| format!("{}: {e}", dir.display()))?;
    let files = laz_files(dir)?;
    if !files.is_empty() {
        return Ok(files);
    }
    let started = Instant::now();
    write_campaign(dir, args.points, args.files, SEED, false).map_err(|e| e.to_string())?;
    eprintln!(
        "wrote {} points in {} files in {:.1} s",
        args.points,
        args.files,
        started.elapsed().as_secs_f64()
    );
    laz_files(dir)
}

/// Builds the store of `files` into `folder` on `threads` threads within `budget_mib`: the
/// partitions stage's figures, the store's digest and the build's wall time.
fn build(
    files: &[PathBuf],
    folder: &Path,
    threads: usize,
    budget_mib: u64,
    journal: bool,
) -> Result<(PartitionsFigures, String, f64), String> {
    let db = sled::Config::new()
        .path(folder.join("index"))
        .cache_capacity(64 << 20)
        .open()
        .map_err(|e| e.to_string())?;
    let tree = db.open_tree("lod").map_err(|e| e.to_string())?;
    let store = LodStore::open(tree, folder.join("nodes.bin")).map_err(|e| e.to_string())?;
    let source = DatasetSource::open(files).map_err(|e| e.to_string())?;
    let mut options = LodBuildOptions::new(folder.join("spill"));
    options.memory_budget_bytes = budget_mib << 20;
    options.threads = Some(threads);
    let started = Instant::now();
    let report = match journal {
        true => build_lod(&source, &store, &options),
        false => build_lod(&Unjournaled(&source), &store, &options),
    }
    .map_err(|e| e.to_string())?;
    let build_s = started.elapsed().as_secs_f64();
    let digest = format!("{:016x}", store_digest(&store).map_err(|e| e.to_string())?);
    Ok((report.partitions_figures, digest, build_s))
}

fn row(
    threads: usize,
    budget_mib: u64,
    load: &str,
    figures: &PartitionsFigures,
    digest: &str,
    build_s: f64,
) -> String {
    let mut sizes: Vec<u64> = figures.built().map(|s| s.points).collect();
    sizes.sort_unstable();
    let size = |at: usize| sizes.get(at).copied().unwrap_or(0);
    let splits = figures.spans.iter().filter(|s| s.split).count();
    let (most, mean) = figures.in_flight();
    let secs = |d: Duration| d.as_secs_f64();
    let store: Duration = figures.spans.iter().map(|s| s.store).sum();
    format!(
        "| {threads} | {budget_mib} | {} | {} ({splits}) | {} / {} / {} | {most} / {mean:.2} | \
         {:.2} | {:.2} | {:.2} | {} | {} | {} | {:.2} | {:.2} | {digest} |  (build {build_s:.1} s)",
        load.split_whitespace().next().unwrap_or("?"),
        sizes.len(),
        size(0),
        size(sizes.len() / 2),
        sizes.last().copied().unwrap_or(0),
        figures.largest().map_or(0.0, |s| secs(s.cpu)),
        secs(figures.units_cpu()),
        secs(figures.wall),
        figures
            .process_cpu
            .map_or("?".into(), |c| format!("{:.2}", secs(c))),
        figures
            .process_system_cpu
            .map_or("?".into(), |c| format!("{:.2}", secs(c))),
        figures
            .process_minor_faults
            .map_or("?".into(), |f| f.to_string()),
        secs(figures.ceiling(CEILING_THREADS)),
        secs(store),
    )
}

/// A source read as another, without its fingerprint: its build keeps no journal.
struct Unjournaled<'s>(&'s DatasetSource);

impl PointSource for Unjournaled<'_> {
    fn bounds(&self) -> WorldBounds {
        self.0.bounds()
    }

    fn point_count(&self) -> u64 {
        self.0.point_count()
    }

    fn for_each_batch(&self, visit: &mut BatchVisitor<'_>) -> Result<(), LodError> {
        self.0.for_each_batch(visit)
    }

    fn position_grid(&self) -> Option<PositionGrid> {
        self.0.position_grid()
    }

    fn attributes(&self) -> Option<AttributeSchema> {
        self.0.attributes()
    }
}

//! What updating a level-of-detail store costs against building it: a campaign of `--files`
//! LAZ tiles whose inner tile changes (`--change`): `add`, a store built from all but that
//! tile, then updated with it; `remove`, a store of every tile updated without it; `replace`,
//! a store of every tile updated with the tile processed again (the same tile of a campaign of
//! another seed) in its place ([`update_store`]). Each against a full build of the tiles after
//! the change; each step timed `--rounds` times, the fastest kept. Both stores are checked to
//! hold every point once (their point counts, and a checksum of every point's position on the
//! millimetre grid and attributes). docs/perf/lod-store-update.md has its figures.
//!
//! ```text
//! lod-store-update [--change add|remove|replace] [--points N] [--files N] [--rounds N]
//!                  [--budget-mib N] [--dir DIR]
//! ```

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

use pointfarm_bench::campaign::store_points::points_checksum;
use pointfarm_bench::campaign::{grid, write_campaign, CampaignFlags, ScratchCampaign};
use pointfarm_bench::cli::{exit_code, parse_flags};
use pointfarm_render::ingest::DatasetSource;
use pointfarm_render::lod::{
    build_lod, update_store, LodBuildOptions, LodError, LodStore, PointSource, StoreChange,
};

const USAGE: &str = "usage: lod-store-update [--change add|remove|replace] [--points N] \
                     [--files N] [--rounds N] [--budget-mib N] [--dir DIR]";

/// What happens to the inner tile.
#[derive(Clone, Copy, PartialEq)]
enum Change {
    Add,
    Remove,
    Replace,
}

struct Args {
    campaign: CampaignFlags,
    rounds: usize,
    change: Change,
}

fn main() -> ExitCode {
    let args: Vec<String> = std::env::args().skip(1).collect();
    exit_code(
        "lod-store-update",
        parse(&args).and_then(|args| measure(&args)),
    )
}

fn parse(args: &[String]) -> Result<Args, String> {
    let mut parsed = Args {
        campaign: CampaignFlags::new(21_000_000, 21),
        rounds: 2,
        change: Change::Add,
    };
    parse_flags(args, USAGE, |flag, value| {
        match flag {
            "--rounds" => parsed.rounds = value.number()?.max(1) as usize,
            "--change" => {
                parsed.change = match value.path().to_str() {
                    Some("add") => Change::Add,
                    Some("remove") => Change::Remove,
                    Some("replace") => Change::Replace,
                    _ => return Err(format!("--change is add, remove or replace\n{USAGE}")),
                }
            }
            _ => return parsed.campaign.apply(flag, &value),
        }
        Ok(true)
    })?;
    parsed.campaign.check_inner_tile()?;
    Ok(parsed)
}

/// A store in `folder`: its sled database (kept open while the store is) and payload file.
fn open_store(folder: &Path) -> Result<(sled::Db, LodStore), String> {
    std::fs::create_dir_all(folder).map_err(|e| e.to_string())?;
    let db = sled::open(folder.join("index")).map_err(|e| e.to_string())?;
    let tree = db.open_tree("lod").map_err(|e| e.to_string())?;
    let store = LodStore::open(tree, folder.join("nodes.bin")).map_err(|e| e.to_string())?;
    Ok((db, store))
}

fn options(folder: &Path, budget_mib: u64) -> LodBuildOptions {
    let mut options = LodBuildOptions::new(folder.join("spill"));
    options.memory_budget_bytes = (budget_mib << 20).max(options.min_memory_budget_bytes());
    options
}

/// Seconds `files` take to build into a fresh store in `folder`, which is left built.
fn build(files: &[PathBuf], folder: &Path, budget_mib: u64) -> Result<(f64, LodStore), String> {
    let _ = std::fs::remove_dir_all(folder);
    let (db, store) = open_store(folder)?;
    let source = DatasetSource::open(files).map_err(|e| e.to_string())?;
    let started = Instant::now();
    let report =
        build_lod(&source, &store, &options(folder, budget_mib)).map_err(|e| e.to_string())?;
    let seconds = started.elapsed().as_secs_f64();
    let regions = store
        .read_regions()
        .map_err(|e| e.to_string())?
        .ok_or("the build kept no regions")?;
    let kept: u64 = regions
        .regions
        .iter()
        .filter_map(|r| r.root.map(|n| n.stored_bytes()))
        .sum();
    println!(
        "    built {} points of {} files in {seconds:.2} s: {} partitions, {} regions; \
         {:.1} MB stored, {:.1} MB of it the regions' kept roots",
        report.hierarchy.point_count,
        files.len(),
        report.partitions,
        regions.regions.len(),
        report.stored_bytes as f64 / 1e6,
        kept as f64 / 1e6
    );
    drop(db);
    Ok((seconds, store))
}

/// The count and an order-free checksum of every point the store holds.
fn points_of(store: &LodStore) -> Result<(u64, u64), String> {
    let hierarchy = store.read_hierarchy().map_err(|e| e.to_string())?;
    points_checksum(store, &hierarchy)
}

fn measure(args: &Args) -> Result<(), String> {
    let ScratchCampaign {
        scratch, written, ..
    } = args.campaign.write("lod-store-update")?;
    let (rows, cols) = grid(args.campaign.files);
    // A tile of the middle row, away from the edges: within the other tiles' cube.
    let inner = (rows / 2) * cols + cols / 2;
    let others: Vec<PathBuf> = (0..written.laz.len())
        .filter(|&i| i != inner)
        .map(|i| written.laz[i].clone())
        .collect();
    // The files before and after the change, and the change as places in the store's order.
    let (before, after, removed, added) = match args.change {
        Change::Add => {
            let mut after = others.clone();
            after.push(written.laz[inner].clone());
            (others, after, vec![], vec![written.laz[inner].clone()])
        }
        Change::Remove => (written.laz.clone(), others, vec![inner], vec![]),
        Change::Replace => {
            let again = scratch.path().join("again");
            std::fs::create_dir_all(&again).map_err(|e| e.to_string())?;
            let other =
                write_campaign(&again, args.campaign.points, args.campaign.files, 12, false)
                    .map_err(|e| e.to_string())?;
            let processed = scratch.path().join("processed.laz");
            std::fs::copy(&other.laz[inner], &processed).map_err(|e| e.to_string())?;
            let mut after = others.clone();
            after.push(processed.clone());
            (written.laz.clone(), after, vec![inner], vec![processed])
        }
    };
    let what = match args.change {
        Change::Add => "added to",
        Change::Remove => "removed from",
        Change::Replace => "replaced in",
    };
    println!(
        "{} points in {} LAZ tiles ({rows} x {cols}); tile {inner} {what} the others",
        written.points,
        written.laz.len()
    );

    let (mut full, mut update) = (f64::INFINITY, f64::INFINITY);
    let mut last = None;
    for round in 0..args.rounds {
        println!("round {}:", round + 1);
        let folder = scratch.path().join("full");
        let (seconds, store) = build(&after, &folder, args.campaign.budget_mib)?;
        full = full.min(seconds);
        let fresh = points_of(&store)?;
        drop(store);

        let folder = scratch.path().join("updated");
        build(&before, &folder, args.campaign.budget_mib)?;
        let (db, store) = open_store(&folder)?;
        let source = match added.is_empty() {
            true => None,
            false => Some(DatasetSource::open(&added).map_err(|e| e.to_string())?),
        };
        let reopen = |places: &[usize]| -> Result<Box<dyn PointSource>, LodError> {
            let paths: Vec<PathBuf> = places.iter().map(|&i| before[i].clone()).collect();
            let source =
                DatasetSource::open(&paths).map_err(|e| LodError::Source(e.to_string()))?;
            Ok(Box::new(source))
        };
        let change = StoreChange {
            added: source.as_ref().map(|s| s as &dyn PointSource),
            removed: removed.clone(),
            reopen: &reopen,
            files: Vec::new(),
        };
        let started = Instant::now();
        let report = update_store(&store, &change, &options(&folder, args.campaign.budget_mib))
            .map_err(|e| e.to_string())?;
        let seconds = started.elapsed().as_secs_f64();
        update = update.min(seconds);
        println!(
            "    updated in {seconds:.2} s: {} points added, {} removed, {} files read again; \
             {} regions rebuilt, {} added, {} kept; {} points decoded; {:.1} MB appended, \
             {:.1} MB dead",
            report.points_added,
            report.points_removed,
            report.files_reread,
            report.regions_rebuilt,
            report.regions_added,
            report.regions_kept,
            report.points_decoded,
            report.stored_bytes as f64 / 1e6,
            report.dead_bytes as f64 / 1e6
        );
        let updated = points_of(&store)?;
        if updated != fresh {
            return Err(format!(
                "the updated store holds {updated:?} (count, checksum), a fresh build {fresh:?}"
            ));
        }
        drop((store, db));
        last = Some(report);
    }
    let report = last.expect("one round");
    println!(
        "full build of {} tiles {full:.2} s; one tile {what} the store {update:.2} s: {:.1}% of \
         the full build ({} regions rebuilt of {}); every point once in both",
        after.len(),
        100.0 * update / full,
        report.regions_rebuilt + report.regions_added,
        report.regions_rebuilt + report.regions_added + report.regions_kept
    );
    Ok(())
}

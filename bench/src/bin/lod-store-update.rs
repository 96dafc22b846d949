//! What updating a level-of-detail store costs against building it: a campaign of `--files`
//! LAZ tiles, a store built from all but an inner tile, then updated with that tile
//! (`update_lod`), against a full build of every tile; each step timed `--rounds` times, the
//! fastest kept. Both stores are checked to hold every point once (their point counts, and a
//! checksum of every point's position on the millimetre grid and attributes).
//! docs/perf/lod-store-update.md has its figures.
//!
//! ```text
//! lod-store-update [--points N] [--files N] [--rounds N] [--budget-mib N] [--dir DIR]
//! ```

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

use pointfarm_bench::campaign::{grid, CampaignFlags, ScratchCampaign};
use pointfarm_bench::cli::{exit_code, parse_flags};
use pointfarm_render::ingest::DatasetSource;
use pointfarm_render::lod::{
    build_lod, read_nodes, update_lod, LodBuildOptions, LodStore, NodeKey,
};

const USAGE: &str =
    "usage: lod-store-update [--points N] [--files N] [--rounds N] [--budget-mib N] [--dir DIR]";

struct Args {
    campaign: CampaignFlags,
    rounds: usize,
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
    };
    parse_flags(args, USAGE, |flag, value| {
        match flag {
            "--rounds" => parsed.rounds = value.number()?.max(1) as usize,
            _ => return parsed.campaign.apply(flag, &value),
        }
        Ok(true)
    })?;
    if grid(parsed.campaign.files).0 < 3 {
        return Err(format!(
            "{} files make no inner tile: give a count of at least three rows",
            parsed.campaign.files
        ));
    }
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
    let keys: Vec<NodeKey> = hierarchy.stored_nodes().map(|n| n.key).collect();
    let (mut count, mut sum) = (0u64, 0u64);
    for chunk in keys.chunks(512) {
        for node in read_nodes(store, &hierarchy, chunk).map_err(|e| e.to_string())? {
            let rgb = node.rgb.clone().unwrap_or_else(|| vec![[0; 3]; node.len()]);
            for (i, p) in node.world_positions().into_iter().enumerate() {
                let mm = (p * 1000.0).round();
                let text = format!(
                    "{} {} {} {:?} {} {} {}",
                    mm.x,
                    mm.y,
                    mm.z,
                    rgb[i],
                    node.intensity[i],
                    node.classification[i],
                    node.return_number[i]
                );
                sum = sum.wrapping_add(fnv(text.as_bytes()));
                count += 1;
            }
        }
    }
    Ok((count, sum))
}

fn fnv(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325, |h, &b| {
        (h ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3)
    })
}

fn measure(args: &Args) -> Result<(), String> {
    let ScratchCampaign {
        scratch, written, ..
    } = args.campaign.write("lod-store-update")?;
    let (rows, cols) = grid(args.campaign.files);
    // A tile of the middle row, away from the edges: within the other tiles' cube.
    let inner = (rows / 2) * cols + cols / 2;
    let before: Vec<PathBuf> = (0..written.laz.len())
        .filter(|&i| i != inner)
        .map(|i| written.laz[i].clone())
        .collect();
    let added = [written.laz[inner].clone()];
    println!(
        "{} points in {} LAZ tiles ({rows} x {cols}); tile {inner} added to the others",
        written.points,
        written.laz.len()
    );

    let (mut full, mut update) = (f64::INFINITY, f64::INFINITY);
    let mut last = None;
    for round in 0..args.rounds {
        println!("round {}:", round + 1);
        let folder = scratch.path().join("full");
        let (seconds, store) = build(&written.laz, &folder, args.campaign.budget_mib)?;
        full = full.min(seconds);
        let fresh = points_of(&store)?;
        drop(store);

        let folder = scratch.path().join("updated");
        build(&before, &folder, args.campaign.budget_mib)?;
        let (db, store) = open_store(&folder)?;
        let source = DatasetSource::open(&added).map_err(|e| e.to_string())?;
        let started = Instant::now();
        let report = update_lod(
            &store,
            &source,
            Vec::new(),
            &options(&folder, args.campaign.budget_mib),
        )
        .map_err(|e| e.to_string())?;
        let seconds = started.elapsed().as_secs_f64();
        update = update.min(seconds);
        println!(
            "    updated with {} points in {seconds:.2} s: {} regions rebuilt, {} added, {} kept; \
             {} points decoded; {:.1} MB appended, {:.1} MB dead",
            report.points_added,
            report.regions_rebuilt,
            report.regions_added,
            report.regions_kept,
            report.points_decoded,
            report.stored_bytes as f64 / 1e6,
            report.dead_bytes as f64 / 1e6
        );
        let updated = points_of(&store)?;
        if updated != fresh || updated.0 != written.points {
            return Err(format!(
                "the updated store holds {updated:?} (count, checksum), a fresh build {fresh:?}"
            ));
        }
        drop((store, db));
        last = Some(report);
    }
    let report = last.expect("one round");
    println!(
        "full build of {} tiles {full:.2} s; one tile added {update:.2} s: {:.1}% of the full \
         build ({} regions rebuilt of {}); every point once in both",
        written.laz.len(),
        100.0 * update / full,
        report.regions_rebuilt + report.regions_added,
        report.regions_rebuilt + report.regions_added + report.regions_kept
    );
    Ok(())
}

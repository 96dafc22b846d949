//! A campaign that grows through a real `pointfarm serve`: what making the store of a dataset
//! of `--files` LAZ tiles costs when the daemon grows it from the store of the same tiles less
//! the inner one, against the daemon building it whole. A daemon renders the tiles but the
//! inner one (`pointfarm render --server`: the files uploaded, the store built whole), then all
//! of them (the inner tile uploaded, the dataset composed, its store grown); a second daemon,
//! fresh, renders all of them (built whole). The times are the daemons' own log lines: `levels
//! of detail built` (a whole build) and `updated the store of` (the copy, the update and the
//! checks; its `update_seconds` is the update alone), so what the client and the upload take
//! is left out. docs/perf/lod-store-update.md has its figures.
//!
//! ```text
//! lod-store-growth --pointfarm PATH [--points N] [--files N] [--rounds N] [--budget-mib N]
//!                  [--dir DIR]
//! ```

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use pointfarm_bench::campaign::{grid, CampaignFlags, ScratchCampaign, ServeCampaignFlags};
use pointfarm_bench::cli::run_program;
use pointfarm_bench::serve::{load, Serve};

const USAGE: &str = "usage: lod-store-growth --pointfarm PATH [--points N] [--files N] \
                     [--rounds N] [--budget-mib N] [--dir DIR]";

/// How each render is drawn: from levels of detail.
const LEVELS: &[&str] = &["--size=200x150", "--lod-error=0"];

fn main() -> ExitCode {
    run_program("lod-store-growth", parse, measure)
}

fn parse(args: &[String]) -> Result<ServeCampaignFlags, String> {
    let campaign = CampaignFlags::new(21_000_000, 21);
    ServeCampaignFlags::parse(args, USAGE, campaign, |_, _| Ok(false))
}

/// A folder of hard links to `tiles`.
fn day(folder: &Path, tiles: &[&PathBuf]) -> Result<PathBuf, String> {
    std::fs::create_dir_all(folder).map_err(|e| e.to_string())?;
    for tile in tiles {
        let name = tile.file_name().ok_or("a tile without a name")?;
        std::fs::hard_link(tile, folder.join(name)).map_err(|e| e.to_string())?;
    }
    Ok(folder.to_owned())
}

fn measure(flags: &ServeCampaignFlags) -> Result<(), String> {
    let ServeCampaignFlags {
        campaign,
        rounds,
        pointfarm,
    } = flags;
    let ScratchCampaign {
        scratch, written, ..
    } = campaign.write("lod-store-growth")?;
    let (rows, cols) = grid(campaign.files);
    let inner = (rows / 2) * cols + cols / 2;
    let all: Vec<&PathBuf> = written.laz.iter().collect();
    let before: Vec<&PathBuf> = (0..all.len())
        .filter(|&i| i != inner)
        .map(|i| all[i])
        .collect();
    let dir = scratch.path();
    let (day1, day2) = (
        day(&dir.join("day1"), &before)?,
        day(&dir.join("day2"), &all)?,
    );
    println!(
        "{} points in {} LAZ tiles ({rows} x {cols}); tile {inner} added; daemon {}",
        written.points,
        all.len(),
        pointfarm.display()
    );
    let budget = campaign.budget_mib;
    for round in 1..=*rounds {
        let data = dir.join(format!("grown-{round}"));
        let serve = Serve::start(pointfarm, &data, budget)?;
        serve.render(pointfarm, &day1, &dir.join("day1.png"), LEVELS)?;
        let [before_whole] = serve.said("levels of detail built", ["seconds"])?;
        let load_before = load();
        serve.render(pointfarm, &day2, &dir.join("day2.png"), LEVELS)?;
        let fields = [
            "seconds",
            "update_seconds",
            "regions_rebuilt",
            "regions_kept",
        ];
        let [grown, update, rebuilt, kept] = serve.said("updated the store of", fields)?;
        let [copy] = serve.said("copied the earlier store to update", ["seconds"])?;
        let load_grown = load();
        drop(serve);
        let _ = std::fs::remove_dir_all(&data);

        let data = dir.join(format!("whole-{round}"));
        let serve = Serve::start(pointfarm, &data, budget)?;
        serve.render(pointfarm, &day2, &dir.join("whole.png"), LEVELS)?;
        let [whole] = serve.said("levels of detail built", ["seconds"])?;
        let load_whole = load();
        drop(serve);
        let _ = std::fs::remove_dir_all(&data);
        println!(
            "round {round}: whole build of {} tiles {before_whole:.2} s; of {} tiles \
             {whole:.2} s (load {load_whole}); store of {} tiles grown {grown:.2} s (copy \
             {copy:.2} s, update alone {update:.2} s, {rebuilt} regions rebuilt, {kept} kept; load {load_before} \
             before, {load_grown} after): {:.1}% of the whole build",
            before.len(),
            all.len(),
            all.len(),
            100.0 * grown / whole
        );
    }
    Ok(())
}

//! How soon a flythrough's first final frame comes through a real `pointfarm serve` when the
//! daemon builds the store of the tiles its frames see first (`daemon/src/stores/camera_first.rs`),
//! against the daemon building the whole store first. A campaign of `--files` LAZ tiles and a
//! low keyframed flight over the middle of one inner tile, drawn from levels of detail at the
//! default pixel error: a fresh daemon renders the flight
//! (the part's store built, every frame leased against it, the whole store grown after); a
//! second fresh daemon renders a still view of the same tiles (the whole store built first).
//! The tiles are registered where they lie (`serve --data-root`), not uploaded, so a campaign
//! of a billion points takes its disk once. The times are the daemons' own log lines: from
//! `job submitted` to the first `frame handed in`, and the whole build's `levels of detail
//! built`.
//! docs/perf/lod-camera-first.md has its figures.
//!
//! ```text
//! lod-camera-first-daemon --pointfarm PATH [--points N] [--files N] [--frames N]
//!                         [--size WxH] [--rounds N] [--budget-mib N] [--dir DIR]
//! ```

use std::process::ExitCode;

use pointfarm_bench::campaign::{grid, CampaignFlags, ScratchCampaign, ServeCampaignFlags};
use pointfarm_bench::cli::run_program;
use pointfarm_bench::flight::{camera_path_file, inner_tile_keyframes};
use pointfarm_bench::serve::{load, Serve};
use pointfarm_render::cut::DEFAULT_LOD_ERROR_PX;
use pointfarm_render::ingest::DatasetSource;
use pointfarm_render::lod::PointSource;

const USAGE: &str = "usage: lod-camera-first-daemon --pointfarm PATH [--points N] [--files N] \
                     [--frames N] [--size WxH] [--rounds N] [--budget-mib N] [--dir DIR]";

struct Args {
    flags: ServeCampaignFlags,
    frames: u64,
    size: String,
}

fn main() -> ExitCode {
    run_program("lod-camera-first-daemon", parse, measure)
}

fn parse(args: &[String]) -> Result<Args, String> {
    let (mut frames, mut size) = (10, "1280x720".to_owned());
    let campaign = CampaignFlags::new(10_000_000, 20);
    let flags = ServeCampaignFlags::parse(args, USAGE, campaign, |flag, value| {
        match flag {
            "--frames" => frames = value.number()?.clamp(1, 10_000),
            "--size" => size = value.path().to_string_lossy().into_owned(),
            _ => return Ok(false),
        }
        Ok(true)
    })?;
    Ok(Args {
        flags,
        frames,
        size,
    })
}

fn measure(args: &Args) -> Result<(), String> {
    let ServeCampaignFlags {
        campaign,
        rounds,
        pointfarm,
    } = &args.flags;
    let ScratchCampaign {
        scratch,
        tiles,
        written,
    } = campaign.write("lod-camera-first-daemon")?;
    let dir = scratch.path();
    let bounds = DatasetSource::open(&written.laz)
        .map_err(|e| e.to_string())?
        .bounds();
    let (rows, columns) = grid(campaign.files);
    let flight = dir.join("flight.toml");
    let keyframes = inner_tile_keyframes(&bounds, (rows, columns));
    std::fs::write(&flight, camera_path_file(&keyframes, args.frames))
        .map_err(|e| e.to_string())?;
    let flight_arg = format!("--camera-path={}", flight.display());
    let size = format!("--size={}", args.size);
    // Levels of detail asked for, at the default pixel error: 10M points would be resident.
    let levels = format!("--lod-error={DEFAULT_LOD_ERROR_PX}");
    let options = [size.as_str(), "--point-size=2", levels.as_str()];
    let flight_options = [options[0], options[1], options[2], flight_arg.as_str()];
    println!(
        "{} points in {} LAZ tiles ({rows} x {columns}), a flight of {} frames at {} over \
         the inner tile; daemon {}",
        written.points,
        written.laz.len(),
        args.frames,
        args.size,
        pointfarm.display()
    );
    let budget = campaign.budget_mib;
    for round in 1..=*rounds {
        let data = dir.join(format!("camera-first-{round}"));
        let serve = Serve::start_in_place(pointfarm, &data, budget, &tiles)?;
        serve.render(pointfarm, &tiles, &dir.join("flight"), &flight_options)?;
        let first = serve.seconds_between("job submitted", "frame handed in")?;
        let [part] = serve.said("levels of detail built", ["seconds"])?;
        let load_first = load();
        let log = serve.log_text();
        let seen = log
            .lines()
            .find(|l| l.contains("camera first: the store of the"))
            .and_then(|l| l.split_once(" files_seen="))
            .and_then(|(_, rest)| rest.split_whitespace().next().map(str::to_owned))
            .ok_or_else(|| format!("the daemon did not build camera first:\n{log}"))?;
        drop(serve);
        let _ = std::fs::remove_dir_all(&data);

        let data = dir.join(format!("whole-{round}"));
        let serve = Serve::start_in_place(pointfarm, &data, budget, &tiles)?;
        serve.render(pointfarm, &tiles, &dir.join("still.png"), &options)?;
        let [whole] = serve.said("levels of detail built", ["seconds"])?;
        let still = serve.seconds_between("job submitted", "frame handed in")?;
        let load_whole = load();
        drop(serve);
        let _ = std::fs::remove_dir_all(&data);
        println!(
            "round {round}: camera first, {seen} of {} tiles seen: first final frame {first:.2} s \
             after submission (the part's store {part:.2} s; load {load_first}); whole build \
             {whole:.2} s, a still view's first frame {still:.2} s after submission (load \
             {load_whole}): {:.1}% of the whole build",
            written.laz.len(),
            100.0 * first / whole
        );
    }
    Ok(())
}

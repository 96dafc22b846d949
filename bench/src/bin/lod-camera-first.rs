//! How soon a flythrough's first final frame comes when its store is built camera first: a
//! campaign of `--files` LAZ tiles and a low keyframed flight over one inner tile. Built whole
//! first, the first frame waits for the whole build; built camera first
//! (`source::camera_first`), for the files the first frame sees. Each is timed from the files
//! to frame 0 drawn; then the camera-first store is finished (the path's files, then the
//! unseen ones, by updates) and checked to hold every point once, as the whole build does
//! (point counts, and a checksum of every point's position on the millimetre grid and
//! attributes). docs/perf/lod-camera-first.md has its figures.
//!
//! ```text
//! lod-camera-first [--points N] [--files N] [--frames N] [--size WxH] [--budget-mib N]
//!                  [--dir DIR]
//! ```

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::Arc;
use std::time::Instant;

use pointfarm_bench::campaign::store_points::points_checksum;
use pointfarm_bench::campaign::{grid, CampaignFlags, ScratchCampaign};
use pointfarm_bench::cli::{exit_code, parse_flags};
use pointfarm_bench::flight::inner_tile_keyframes;
use pointfarm_render::cloud::WorldBounds;
use pointfarm_render::cut::{CutOptions, StoredLod};
use pointfarm_render::gpu::{AdapterChoice, GpuContext};
use pointfarm_render::ingest::DatasetSource;
use pointfarm_render::lod::PointSource;
use pointfarm_render::raster::Renderer;
use pointfarm_render::request::{
    CameraPath, Interpolation, Lens, PointSize, RenderOptions, RenderRequest,
};
use pointfarm_render::source::{
    file_boxes, quiet, FileOrder, FrameSource, Levels, LocalStore, Opening, StagedStore,
};

const USAGE: &str = "usage: lod-camera-first [--points N] [--files N] [--frames N] \
                     [--size WxH] [--budget-mib N] [--dir DIR]";

struct Args {
    campaign: CampaignFlags,
    frames: u32,
    size: (u32, u32),
}

fn main() -> ExitCode {
    exit_code("lod-camera-first", run())
}

fn run() -> Result<(), String> {
    let args = parse(&std::env::args().skip(1).collect::<Vec<_>>())?;
    measure(&args)
}

fn parse(args: &[String]) -> Result<Args, String> {
    let mut parsed = Args {
        campaign: CampaignFlags::new(10_000_000, 20),
        frames: 10,
        size: (1280, 720),
    };
    parse_flags(args, USAGE, |flag, value| {
        match flag {
            "--frames" => parsed.frames = value.number()?.clamp(1, 10_000) as u32,
            "--size" => {
                let text = value.path().to_string_lossy().into_owned();
                let size = text
                    .split_once('x')
                    .and_then(|(w, h)| Some((w.parse().ok()?, h.parse().ok()?)))
                    .filter(|&(w, h): &(u32, u32)| w > 0 && h > 0)
                    .ok_or_else(|| format!("--size is WxH\n{USAGE}"))?;
                parsed.size = size;
            }
            _ => return parsed.campaign.apply(flag, &value),
        }
        Ok(true)
    })?;
    parsed.campaign.check_inner_tile()?;
    Ok(parsed)
}

/// A low flight looking down over the middle of the inner tile of a grid of `rows` x
/// `columns` tiles over `bounds`.
fn flight(args: &Args, bounds: &WorldBounds, grid: (usize, usize)) -> RenderRequest {
    RenderRequest {
        width: args.size.0,
        height: args.size.1,
        camera_path: CameraPath::Keyframes {
            keyframes: inner_tile_keyframes(bounds, grid),
            frames: args.frames,
            interpolation: Interpolation::Linear,
        },
        lens: Lens::default(),
        render: RenderOptions {
            point_size: PointSize::Fixed(2),
            ..RenderOptions::default()
        },
    }
}

/// Renders frame 0 of `request` from `store`; the seconds it took.
fn first_frame(
    gpu: &Arc<GpuContext>,
    store: LocalStore,
    request: &RenderRequest,
) -> Result<f64, String> {
    let started = Instant::now();
    let opening = Opening::Levels {
        levels: Levels::Store(Box::new(store)),
        cut_options: CutOptions::default(),
    };
    let renderer = Renderer::new(Arc::clone(gpu));
    let mut source =
        FrameSource::open(renderer, opening, &request.render, &quiet).map_err(|e| e.to_string())?;
    let settings = source.frame_settings(request, 0);
    source
        .render(&settings, &quiet)
        .map_err(|e| e.to_string())?;
    Ok(started.elapsed().as_secs_f64())
}

/// The count and an order-free checksum of every point the finished store in `folder` holds.
fn points_of(folder: &Path) -> Result<(u64, u64), String> {
    let stored = StoredLod::open_or_build(&[], folder, 64 << 20, None, &mut |_| {})
        .map_err(|e| e.to_string())?;
    points_checksum(
        stored.dataset.records().as_ref(),
        stored.dataset.hierarchy(),
    )
}

fn measure(args: &Args) -> Result<(), String> {
    let ScratchCampaign {
        scratch, written, ..
    } = args.campaign.write("lod-camera-first")?;
    let files: Vec<PathBuf> = written.laz.clone();
    let bounds = DatasetSource::open(&files)
        .map_err(|e| e.to_string())?
        .bounds();
    let request = flight(args, &bounds, grid(files.len()));
    let gpu = Arc::new(GpuContext::new(AdapterChoice::Auto).map_err(|e| e.to_string())?);
    let budget = (args.campaign.budget_mib << 20).max(64 << 20);
    println!(
        "{} points in {} LAZ tiles; {} frames of {}x{} over the inner tile; {}",
        written.points,
        files.len(),
        args.frames,
        args.size.0,
        args.size.1,
        gpu.describe()
    );

    // Whole first: the build of every tile, then frame 0.
    let whole = scratch.path().join("whole");
    let started = Instant::now();
    let stored = StoredLod::open_or_build(&files, &whole, budget, None, &mut |_| {})
        .map_err(|e| e.to_string())?;
    let build = started.elapsed().as_secs_f64();
    let store = LocalStore::of_built(stored, &files, budget, None, &quiet);
    let frame = first_frame(&gpu, store, &request)?;
    println!(
        "whole first: build {build:.2} s, frame 0 {frame:.2} s: first final frame at {:.2} s",
        build + frame
    );

    // Camera first: the files frame 0 sees, frame 0, then the rest by updates.
    let folder = scratch.path().join("camera-first");
    let started = Instant::now();
    let boxes = file_boxes(&files).map_err(|e| e.to_string())?;
    let order = FileOrder::of(&request, &boxes).ok_or("the flight sees every tile")?;
    let staged = StagedStore::new(&files, &folder, budget, None).map_err(|e| e.to_string())?;
    let stages = order.stages(Default::default());
    let (stage, places) = &stages[0];
    let store = staged
        .open_stage(*stage, places, places, &quiet)
        .map_err(|e| e.to_string())?;
    let chosen = started.elapsed().as_secs_f64();
    let frame = first_frame(&gpu, store, &request)?;
    let first = started.elapsed().as_secs_f64();
    let seen_points: u64 =
        DatasetSource::open(&places.iter().map(|&i| files[i].clone()).collect::<Vec<_>>())
            .map_err(|e| e.to_string())?
            .point_count();
    println!(
        "camera first: {} tiles seen by frame 0 ({:.1}% of the points), {} more by the path, \
         {} unseen; store of frame 0's tiles in {chosen:.2} s, frame 0 {frame:.2} s: first \
         final frame at {first:.2} s, {:.1}% of the whole build",
        order.first.len(),
        100.0 * seen_points as f64 / written.points as f64,
        order.path.len(),
        order.unseen.len(),
        100.0 * first / build
    );
    let mut built = places.len();
    for (stage, places) in &stages[1..] {
        let step = Instant::now();
        let store = staged
            .open_stage(*stage, places, &places[built..], &quiet)
            .map_err(|e| e.to_string())?;
        built = places.len();
        drop(store);
        println!(
            "  then {}: {} files in {:.2} s",
            stage.describe(),
            places.len(),
            step.elapsed().as_secs_f64()
        );
    }
    let total = started.elapsed().as_secs_f64();
    println!(
        "camera first, finished: {total:.2} s in all ({:.2}x the whole build)",
        total / build
    );
    let (ours, theirs) = (points_of(&folder)?, points_of(&whole)?);
    if ours != theirs || ours.0 != written.points {
        return Err(format!(
            "the camera-first store holds {ours:?} (count, checksum), the whole build {theirs:?}"
        ));
    }
    println!("both stores hold the {} points once each", ours.0);
    Ok(())
}

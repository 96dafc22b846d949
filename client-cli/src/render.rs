//! `pointfarm render`: the request the arguments describe, rendered here frame by frame, or
//! handed to a server (`remote_render`).

use std::path::Path;
use std::sync::Arc;
use std::time::Instant;

use anyhow::{bail, Context, Result};
use indicatif::{ProgressBar, ProgressStyle};
use pointfarm_render::color::point_colors;
use pointfarm_render::encode;
use pointfarm_render::gpu::GpuContext;
use pointfarm_render::ingest::{dataset_files, load_dataset};
use pointfarm_render::raster::{FrameSettings, Renderer, Stage, StageTimings};

pub use crate::render_args::RenderArgs;

pub fn run(args: RenderArgs) -> Result<()> {
    // Refuse bad options before anything is read, with the field at fault.
    let request = args.request()?;
    if let Some(server) = args.server.clone() {
        return crate::remote_render::run(&server, &args, &request);
    }

    let started = Instant::now();
    let files = dataset_files(&args.inputs)?;
    let spinner = spinner(match files.as_slice() {
        [one] => format!("reading {}", one.display()),
        many => format!("reading {} files", many.len()),
    });
    let cloud = load_dataset(&files);
    spinner.finish_and_clear();
    let mut cloud = cloud?;
    cloud.colors = point_colors(&cloud, request.render.color_mode);
    println!(
        "{}: {} points in {} file{}, colour from {:?}, read in {:.0} ms",
        args.inputs_label(),
        cloud.len(),
        files.len(),
        if files.len() == 1 { "" } else { "s" },
        cloud.color_source,
        started.elapsed().as_secs_f64() * 1e3
    );

    let gpu = Arc::new(GpuContext::new(args.adapter)?);
    println!("adapter: {}", gpu.describe());
    let mut renderer = Renderer::new(gpu);
    let settings = |index: u32| FrameSettings {
        atomics: args.atomics(),
        ..request.frame_settings(index, &cloud.bounds)
    };
    // Refuse sizes this adapter cannot hold, or cameras the cloud makes invalid, before the
    // upload.
    renderer.validate(&settings(0))?;
    let resident = renderer.upload(&cloud)?;

    if args.turntable.is_none() {
        if args.out.is_dir() {
            bail!(
                "{} is a directory; give a .png file (or use --turntable N)",
                args.out.display()
            );
        }
        let base = settings(0);
        let mut frame = renderer.render(&resident, &base)?;
        encode::save_png(&mut frame, &args.out)
            .with_context(|| format!("writing {}", args.out.display()))?;
        if request.render.depth {
            save_depth(&frame, &args.out.with_extension("depth.png"), &base)?;
        }
        println!("{}  {}", args.out.display(), frame.timings);
        return Ok(());
    }
    let frames = request.frames();
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    let progress = ProgressBar::new(frames as u64).with_style(
        ProgressStyle::with_template("{bar:40} {pos}/{len} frames, {eta} left")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    let mut all = Vec::with_capacity(frames as usize);
    for i in 0..frames {
        let frame_settings = settings(i);
        let mut frame = renderer.render(&resident, &frame_settings)?;
        let path = args.out.join(format!("frame_{i:05}.png"));
        encode::save_png(&mut frame, &path)
            .with_context(|| format!("writing {}", path.display()))?;
        if request.render.depth {
            let depth = args.out.join(format!("depth_{i:05}.png"));
            save_depth(&frame, &depth, &frame_settings)?;
        }
        let line = format!("{}  {}", path.display(), frame.timings);
        if progress.is_hidden() {
            println!("{line}"); // not a terminal: plain lines for logs and scripts
        } else {
            progress.println(line);
        }
        all.push(frame.timings);
        progress.inc(1);
    }
    progress.finish_and_clear();
    print_summary(&args.out, &all);
    if let Some(video) = &args.video {
        crate::video::assemble(&args.out, video, args.fps)?;
    }
    Ok(())
}

fn save_depth(
    frame: &pointfarm_render::raster::Frame,
    path: &Path,
    settings: &FrameSettings,
) -> Result<()> {
    encode::save_depth_png16(frame, path, settings.camera.near, settings.camera.far)
        .with_context(|| format!("writing {}", path.display()))
}

fn print_summary(dir: &Path, frames: &[StageTimings]) {
    println!(
        "{} frames in {}; median per stage:",
        frames.len(),
        dir.display()
    );
    for stage in [
        Stage::Upload,
        Stage::Cull,
        Stage::Rasterize,
        Stage::Resolve,
        Stage::Shade,
        Stage::Downsample,
        Stage::Readback,
        Stage::Encode,
    ] {
        let mut ms: Vec<f64> = frames.iter().filter_map(|t| t.get(stage)).collect();
        if ms.is_empty() {
            continue;
        }
        ms.sort_by(f64::total_cmp);
        println!("  {:<10} {:>9.2} ms", stage.name(), ms[ms.len() / 2]);
    }
}

fn spinner(message: String) -> ProgressBar {
    let spinner = ProgressBar::new_spinner().with_message(message);
    spinner.enable_steady_tick(std::time::Duration::from_millis(100));
    spinner
}

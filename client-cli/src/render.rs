//! `pointfarm render`: the request the arguments describe, rendered here frame by frame, or
//! handed to a server (`remote_render`).

use std::path::Path;
use std::sync::Arc;

use anyhow::{bail, Context, Result};
use indicatif::{ProgressBar, ProgressStyle};
use pointfarm_render::encode;
use pointfarm_render::gpu::GpuContext;
use pointfarm_render::ingest::{dataset_files, dataset_point_count};
use pointfarm_render::raster::{FrameSettings, Stage, StageTimings};

use crate::frame_source::{FrameSource, RenderedFrame};
use crate::lod_store::{default_cache_dir, StoreCache};

pub use crate::render_args::RenderArgs;

pub fn run(args: RenderArgs) -> Result<()> {
    // Refuse bad options before anything is read, with the field at fault.
    let request = args.request()?;
    if let Some(server) = args.server.clone().filter(|_| !args.local) {
        return crate::remote_render::run(&server, &args, &request);
    }

    let files = dataset_files(&args.inputs)?;
    // With --json, standard output carries only the frames' objects.
    let say = |line: String| {
        if args.json {
            eprintln!("{line}");
        } else {
            outln!("{line}");
        }
    };
    let points = dataset_point_count(&files)?;
    let label = args.inputs_label();
    let say_input = |line: String| say(format!("{label}: {line}"));
    let gpu = Arc::new(GpuContext::new(args.adapter)?);
    let color_mode = request.render.color_mode;
    let mut source = match args.cut_options(points)? {
        None => FrameSource::resident(Arc::clone(&gpu), &files, color_mode, &say_input)?,
        Some(options) => {
            let cache = StoreCache {
                dir: args.cache_dir.clone().unwrap_or_else(default_cache_dir),
                size_bytes: args.cache_size,
            };
            FrameSource::cut(
                Arc::clone(&gpu),
                &files,
                &cache,
                options,
                color_mode,
                &say_input,
            )?
        }
    };
    say(format!("adapter: {}", gpu.describe()));
    let bounds = source.bounds();
    let settings = |index: u32| FrameSettings {
        atomics: args.atomics(),
        ..request.frame_settings(index, &bounds)
    };
    // Refuse sizes this adapter cannot hold, or cameras the cloud makes invalid, before the
    // first frame.
    source.renderer().validate(&settings(0))?;

    if args.turntable.is_none() {
        if args.out.is_dir() {
            bail!(
                "{} is a directory; give a .png file (or use --turntable N)",
                args.out.display()
            );
        }
        let base = settings(0);
        let mut rendered = source.render(&base)?;
        encode::save_png(&mut rendered.frame, &args.out)
            .with_context(|| format!("writing {}", args.out.display()))?;
        if request.render.depth {
            save_depth(
                &rendered.frame,
                &args.out.with_extension("depth.png"),
                &base,
            )?;
        }
        report_frame(&args, 0, &args.out, &base, &rendered, None);
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
        let mut rendered = source.render(&frame_settings)?;
        // The next frame's nodes load while this one is encoded and written.
        if i + 1 < frames {
            source.read_ahead(&settings(i + 1));
        }
        let path = args.out.join(format!("frame_{i:05}.png"));
        encode::save_png(&mut rendered.frame, &path)
            .with_context(|| format!("writing {}", path.display()))?;
        if request.render.depth {
            let depth = args.out.join(format!("depth_{i:05}.png"));
            save_depth(&rendered.frame, &depth, &frame_settings)?;
        }
        report_frame(&args, i, &path, &frame_settings, &rendered, Some(&progress));
        all.push(rendered.frame.timings);
        progress.inc(1);
    }
    progress.finish_and_clear();
    if !args.json {
        print_summary(&args.out, &all);
    }
    if let Some(video) = &args.video {
        crate::video::assemble(&args.out, video, args.fps)?;
        say(format!("video: {}", video.display()));
    }
    Ok(())
}

/// A frame's line (or its JSON object with --json), above the progress bar if there is one.
fn report_frame(
    args: &RenderArgs,
    index: u32,
    path: &Path,
    settings: &FrameSettings,
    rendered: &RenderedFrame,
    progress: Option<&ProgressBar>,
) {
    let line = if args.json {
        frame_json(index, path, settings, rendered).to_string()
    } else {
        let mut line = format!("{}  {}", path.display(), rendered.frame.timings);
        if let Some(cut) = rendered.cut.as_ref().map(|c| &c.counts) {
            line.push_str(&format!(
                "  | cut {} nodes, {} points; read {} nodes ({:.1} MiB), host hits {}, GPU hits {}",
                cut.nodes,
                cut.points_rendered,
                cut.nodes_read,
                cut.bytes_read as f64 / f64::from(1 << 20),
                cut.host_hits,
                cut.gpu_hits
            ));
        }
        line
    };
    match progress {
        // Not a terminal: plain lines for logs and scripts.
        Some(progress) if !progress.is_hidden() => progress.println(line),
        _ => outln!("{line}"),
    }
}

/// One frame as `render --json` reports it.
fn frame_json(
    index: u32,
    path: &Path,
    settings: &FrameSettings,
    rendered: &RenderedFrame,
) -> serde_json::Value {
    let timings: serde_json::Map<String, serde_json::Value> = rendered
        .frame
        .timings
        .stages
        .iter()
        .map(|t| (t.stage.name().to_string(), serde_json::json!(t.ms)))
        .collect();
    let mut object = serde_json::json!({
        "frame": index,
        "path": path.display().to_string(),
        "width": settings.width,
        "height": settings.height,
        "points_total": rendered.points_total,
        "points_rendered": rendered.points_rendered,
        "timings_ms": timings,
    });
    if let Some(cut) = &rendered.cut {
        object["cut"] = serde_json::to_value(cut).unwrap_or_default();
    }
    object
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
    outln!(
        "{} frames in {}; median per stage:",
        frames.len(),
        dir.display()
    );
    for stage in [
        Stage::Select,
        Stage::Load,
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
        outln!("  {:<10} {:>9.2} ms", stage.name(), ms[ms.len() / 2]);
    }
}

//! `pointfarm render`: the request the arguments describe, rendered here frame by frame, or
//! handed to a server (`remote_render`).

use std::path::Path;
use std::sync::Arc;

use anyhow::{Context, Result};
use glam::DVec3;
use indicatif::{ProgressBar, ProgressStyle};
use pointfarm_render::camera::{Camera, Projection};
use pointfarm_render::cloud::WorldBounds;
use pointfarm_render::copc::is_copc;
use pointfarm_render::encode;
use pointfarm_render::gpu::GpuContext;
use pointfarm_render::ingest::{dataset_files, dataset_point_count};
use pointfarm_render::legend::Legend;
use pointfarm_render::raster::{FrameSettings, Stage, StageTimings};

use crate::frame_files::save_depth;
use crate::frame_source::{FrameSource, RenderedFrame};
use crate::lod_store::StoreCache;
use crate::paths::user_cache_dir;
use crate::render_json::FrameJson;
use crate::render_outputs::{write_legend, Outputs};

pub use crate::render_args::RenderArgs;

pub fn run(args: RenderArgs) -> Result<()> {
    // Refuse bad options before anything is read, with the field at fault: the request, where
    // the frames go, and the video.
    let request = args.request()?;
    let outputs = Outputs::check(&args, &request)?;
    if let Some(server) = args.server.clone().filter(|_| !args.local) {
        return crate::remote_render::run(&server, &args, &request, &outputs);
    }
    if !args.require_tags.is_empty() || args.require_gpu {
        anyhow::bail!(
            "--require-tag and --require-gpu choose a server's workers for the job; they need \
             --server (this render runs here)"
        );
    }

    let files = dataset_files(&args.inputs)?;
    let say = |line: String| crate::output::say(args.json, line);
    let points = dataset_point_count(&files)?;
    let label = args.inputs_label();
    let say_input = |line: String| say(format!("{label}: {line}"));
    let gpu = Arc::new(GpuContext::new(args.adapter)?);
    let coloring = request.render.coloring();
    let copc = match files.as_slice() {
        [one] if is_copc(one)? => Some(one),
        _ => None,
    };
    let mut source = match (copc, args.cut_options(points)?) {
        (Some(file), _) => FrameSource::copc(
            Arc::clone(&gpu),
            file,
            args.lod_options()?,
            &request.render,
            &say_input,
        )?,
        (None, None) => {
            FrameSource::resident(Arc::clone(&gpu), &files, &request.render, &say_input)?
        }
        (None, Some(options)) => {
            let cache = StoreCache {
                dir: args.cache_dir.clone().unwrap_or_else(user_cache_dir),
                size_bytes: args.cache_size,
            };
            FrameSource::cut(
                Arc::clone(&gpu),
                &files,
                &cache,
                options,
                &request.render,
                &say_input,
            )?
        }
    };
    if let Some(path) = &outputs.legend {
        say(write_legend(
            path,
            Legend::of(coloring, source.ramp_range()),
        )?);
    }
    say(format!("adapter: {}", gpu.describe()));
    let bounds = source.bounds();
    let spacing = source.spacing();
    let settings = |index: u32| FrameSettings {
        atomics: args.atomics(),
        ..request.frame_settings(index, &bounds, spacing)
    };
    // Refuse sizes this adapter cannot hold, or cameras the cloud makes invalid, before the
    // first frame.
    source.renderer().validate(&settings(0))?;
    say(format!("bounds: {}", bounds_text(&bounds)));
    say(format!("camera: {}", camera_flags(&settings(0).camera)));
    say(point_size_text(&settings(0), spacing));

    let files = &outputs.files;
    let frames = request.frames();
    files.create_dir()?;
    let progress = if args.is_sequence() {
        ProgressBar::new(u64::from(frames)).with_style(
            ProgressStyle::with_template("{bar:40} {pos}/{len} frames, {eta} left")
                .unwrap_or_else(|_| ProgressStyle::default_bar()),
        )
    } else {
        ProgressBar::hidden()
    };
    let mut written = Vec::with_capacity(frames as usize);
    let mut all = Vec::with_capacity(frames as usize);
    for i in 0..frames {
        let frame_settings = settings(i);
        let mut rendered = source.render(&frame_settings)?;
        // The next frame's nodes load while this one is encoded and written.
        if i + 1 < frames {
            source.read_ahead(&settings(i + 1));
        }
        let path = files.frame(i);
        encode::save_frame(&mut rendered.frame, &path, files.format())
            .with_context(|| format!("writing {}", path.display()))?;
        if request.render.depth {
            save_depth(files, i, &rendered.frame, &frame_settings)?;
        }
        report_frame(
            &args,
            i,
            &path,
            &frame_settings,
            &bounds,
            &rendered,
            &progress,
        );
        all.push(rendered.frame.timings);
        written.push(path);
        progress.inc(1);
    }
    progress.finish_and_clear();
    if args.is_sequence() && !args.json {
        print_summary(files.dir(), &all);
    }
    if let Some(video) = &outputs.video {
        video.assemble(&written)?;
        say(format!("video: {}", video.path().display()));
    }
    Ok(())
}

/// A frame's line (or its JSON object with --json), above the progress bar if there is one.
fn report_frame(
    args: &RenderArgs,
    index: u32,
    path: &Path,
    settings: &FrameSettings,
    bounds: &WorldBounds,
    rendered: &RenderedFrame,
    progress: &ProgressBar,
) {
    let line = if args.json {
        serde_json::to_string(&FrameJson::new(index, path, settings, bounds, rendered))
            .unwrap_or_default()
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
    if progress.is_hidden() {
        // Not a terminal, or a still: plain lines for logs and scripts.
        outln!("{line}");
    } else {
        progress.println(line);
    }
}

/// The bounds in the file's coordinates, to 3 decimals.
/// The first frame's point size, and for an adaptive one the spacing it came from.
fn point_size_text(settings: &FrameSettings, spacing: Option<f64>) -> String {
    let side = settings.point_size;
    let unit = if side == 1 { "pixel" } else { "pixels" };
    match (settings.adaptive_size, spacing) {
        (Some(_), Some(spacing)) if side > 1 => {
            format!("point size: 1 to {side} {unit} by depth (points about {spacing:.3} apart)")
        }
        _ => format!("point size: {side} {unit}"),
    }
}

fn bounds_text(bounds: &WorldBounds) -> String {
    let axis = |name: &str, min: f64, max: f64| format!("{name} {min:.3} .. {max:.3}");
    [
        axis("x", bounds.min.x, bounds.max.x),
        axis("y", bounds.min.y, bounds.max.y),
        axis("z", bounds.min.z, bounds.max.z),
    ]
    .join(", ")
}

/// The camera as the flags that give it, to adjust from (`--flag=value`, as a value may
/// start with a minus sign).
fn camera_flags(camera: &Camera) -> String {
    // `+ 0.0` turns -0 into 0, which reads better.
    let vector = |v: DVec3| format!("{:.3},{:.3},{:.3}", v.x + 0.0, v.y + 0.0, v.z + 0.0);
    let lens = match camera.projection {
        Projection::Perspective { fov_y_deg } => format!("--fov={fov_y_deg}"),
        Projection::Orthographic { height } => format!("--ortho --ortho-height={height:.3}"),
    };
    format!(
        "--camera-pos={} --camera-target={} --camera-up={} {lens} --near={:.3} --far={:.3}",
        vector(camera.position),
        vector(camera.target),
        vector(camera.up),
        camera.near,
        camera.far
    )
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

//! `pointfarm render`: the request the arguments describe, rendered here frame by frame, or
//! handed to a server (`remote_render`).

use std::path::{Path, PathBuf};
use std::sync::{mpsc, Arc};

use anyhow::Result;
use glam::DVec3;
use indicatif::{ProgressBar, ProgressStyle};
use pointfarm_render::camera::{Camera, Projection};
use pointfarm_render::cloud::WorldBounds;
use pointfarm_render::copc::is_copc;
use pointfarm_render::cut::{CutOptions, StoredLod, PREVIEW_LOD_ERROR_PX};
use pointfarm_render::gpu::GpuContext;
use pointfarm_render::ingest::{dataset_files, dataset_point_count};
use pointfarm_render::legend::Legend;
use pointfarm_render::lod::{BuildProgress, PREVIEW_REDRAW_SHARE, PREVIEW_STORED_POINTS};
use pointfarm_render::raster::{FrameSettings, Renderer, Stage, StageTimings};
use pointfarm_render::remote::{FetchCounts, ObjectUrl, RemoteClient};
use pointfarm_render::request::RenderRequest;
use pointfarm_render::source::{
    frame_points, ChunkStarts, FramePoints, FrameSource, Levels, LocalStore, PointSourceFacts,
    SourceEvent, SourceFrame, StoreCache,
};

use crate::paths::store_cache;
use crate::render_json::FrameJson;
use crate::render_outputs::{write_legend, Outputs};
use crate::source_words::SourceWords;
use crate::url_input::{self, Inputs, UrlDataset};

pub use crate::render_args::RenderArgs;

pub fn run(args: RenderArgs) -> Result<()> {
    // Refuse bad options before anything is read, with the field at fault: the request, where
    // the frames go, and the video.
    let request = args.request()?;
    let outputs = Outputs::check(&args, &request)?;
    if let Some(server) = args.server.clone().filter(|_| !args.local) {
        if let Some(url) = args
            .inputs
            .iter()
            .find(|input| url_input::looks_like_url(input))
        {
            anyhow::bail!(
                "{}: a URL renders here (--local), or on the server once registered there \
                 (pointfarm dataset register URL, then render --dataset ID)",
                url.display()
            );
        }
        return crate::remote_render::run(&server, &args, &request, &outputs);
    }
    if let Some(id) = &args.dataset {
        anyhow::bail!("--dataset {id} names a server's dataset; it needs --server URL");
    }
    if !args.require_tags.is_empty() || args.require_gpu {
        anyhow::bail!(
            "--require-tag and --require-gpu choose a server's workers for the job; they need \
             --server (this render runs here)"
        );
    }
    if !args.after.is_empty() || args.detach {
        anyhow::bail!(
            "--after and --detach are for a server's jobs; they need --server (this render \
             runs here)"
        );
    }

    let files = match url_input::classify(&args.inputs)? {
        Inputs::Url(url) => return render_url(&args, &request, &outputs, &url),
        Inputs::Paths(paths) => dataset_files(&paths)?,
    };
    let say = |line: String| crate::output::say(args.json, line);
    let points = dataset_point_count(&files)?;
    let words = SourceWords::new(args.json, args.inputs_label());
    let events = |event: SourceEvent<'_>| words.tell(event);
    let gpu = Arc::new(GpuContext::new(args.adapter)?);
    let renderer = Renderer::new(Arc::clone(&gpu));
    let copc = match files.as_slice() {
        [one] if is_copc(one)? => Some(one),
        _ => None,
    };
    let stores = store_cache(args.cache_dir.as_ref(), args.cache_size);
    // A store already built in the cache is cut, as a server cuts it, whatever the size.
    let store_folder = match copc {
        Some(_) => None,
        None => Some(stores.folder_of_files(&files)?),
    };
    let facts = PointSourceFacts {
        points: Some(points),
        one_copc_file: copc.is_some(),
        store_built: store_folder.as_deref().is_some_and(StoredLod::is_built),
        levels_of_detail_asked: args.levels_of_detail_asked(),
    };
    let frame_points = frame_points(&facts);
    let target = FrameTarget {
        args: &args,
        request: &request,
        outputs: &outputs,
        gpu: &gpu,
        words: &words,
        fetched: None,
    };
    if args.preview {
        match (copc, frame_points, &store_folder) {
            (Some(file), _, _) => {
                let options = args.lod_options()?;
                if options.lod_error < PREVIEW_LOD_ERROR_PX {
                    let render = &request.render;
                    let source = FrameSource::copc(renderer, file, options, render, &events)?;
                    return copc_preview_then_final(&target, source, options);
                }
                say(format!(
                    "--preview: the pixel error ({}) is a preview's already; {FINAL_AT_ONCE}",
                    options.lod_error
                ));
            }
            (None, FramePoints::Resident, _) => say(format!(
                "--preview: {points} points render resident, nothing to build; {FINAL_AT_ONCE}"
            )),
            (None, _, Some(folder)) if !facts.store_built => {
                let build = Build {
                    files: &files,
                    folder: folder.clone(),
                    stores: &stores,
                    options: args.lod_options()?,
                    points,
                };
                return preview_then_final(&target, renderer, build);
            }
            (None, _, _) => say(format!("--preview: {BUILT_ALREADY}; {FINAL_AT_ONCE}")),
        }
    }
    let render = &request.render;
    let mut source = match (copc, frame_points, store_folder) {
        (Some(file), _, _) => {
            FrameSource::copc(renderer, file, args.lod_options()?, render, &events)?
        }
        (None, FramePoints::Resident, _) | (None, _, None) => {
            FrameSource::resident(renderer, &files, None, render, &events)?
        }
        (None, _, Some(folder)) => FrameSource::local_store(
            renderer,
            &files,
            &folder,
            stores.disk_budget,
            args.lod_options()?,
            render,
            &events,
        )?,
    };
    target.render(&mut source, &|| true)
}

const BUILT_ALREADY: &str = "the levels of detail are built already";
const FINAL_AT_ONCE: &str = "rendering the final frames";

/// Renders the COPC file at `url` as a file here is rendered, cut by cut, its header,
/// hierarchy pages and nodes read by range as the frames reach them; or, with `--preview`,
/// LAS/LAZ tiles by URL from their chunk starts read by range. Says what was fetched.
fn render_url(
    args: &RenderArgs,
    request: &RenderRequest,
    outputs: &Outputs,
    url: &ObjectUrl,
) -> Result<()> {
    let client = url_input::client()?;
    let words = SourceWords::new(args.json, args.inputs_label());
    let events = |event: SourceEvent<'_>| words.tell(event);
    let say = |line: String| crate::output::say(args.json, line);
    let dataset = url_input::open(&client, url)?;
    if matches!(dataset, UrlDataset::Tiles(_)) && !args.preview {
        anyhow::bail!("{url}: {}", url_input::TILES_FINAL);
    }
    let gpu = Arc::new(GpuContext::new(args.adapter)?);
    let renderer = Renderer::new(Arc::clone(&gpu));
    let target = FrameTarget {
        args,
        request,
        outputs,
        gpu: &gpu,
        words: &words,
        fetched: Some(&client),
    };
    let options = args.lod_options()?;
    match dataset {
        UrlDataset::Tiles(tiles) => {
            let chunk_starts = ChunkStarts::read_urls(&client, &tiles)?;
            let points = chunk_starts.with_nodes(&[]);
            let mut preview = FrameSource::preview(renderer, points, &request.render, &events)?;
            target.render(&mut preview, &|| true)?;
            say(format!("final frames: {}", url_input::TILES_FINAL));
        }
        UrlDataset::Copc(copc) => {
            let levels = Levels::Copc(copc);
            let mut source =
                FrameSource::levels(renderer, levels, options, &request.render, &events)?;
            match (args.preview, options.lod_error < PREVIEW_LOD_ERROR_PX) {
                (true, true) => copc_preview_then_final(&target, source, options)?,
                (preview, _) => {
                    if preview {
                        say(format!(
                            "--preview: the pixel error ({}) is a preview's already; \
                             {FINAL_AT_ONCE}",
                            options.lod_error
                        ));
                    }
                    target.render(&mut source, &|| true)?;
                }
            }
        }
    }
    let counts = client.counts();
    say(format!(
        "fetched {} bytes in {} requests from {url}",
        counts.bytes, counts.requests
    ));
    Ok(())
}

/// What frames are rendered for, where they go, and who tells their source's steps.
struct FrameTarget<'a> {
    args: &'a RenderArgs,
    request: &'a RenderRequest,
    outputs: &'a Outputs,
    gpu: &'a Arc<GpuContext>,
    words: &'a SourceWords,
    /// The client frames are read through by URL, whose counts each frame's JSON reports.
    fetched: Option<&'a RemoteClient>,
}

impl FrameTarget<'_> {
    fn render(&self, source: &mut FrameSource, keep_going: &dyn Fn() -> bool) -> Result<()> {
        render_frames(self, source, keep_going)
    }

    /// Renders every final frame from `source` over the previews, and says where they are.
    fn render_final(&self, source: &mut FrameSource) -> Result<()> {
        self.render(source, &|| true)?;
        crate::output::say(
            self.args.json,
            format!(
                "final frames: {} (over the previews)",
                self.outputs.files.dir().display()
            ),
        );
        Ok(())
    }

    fn events(&self) -> impl Fn(SourceEvent<'_>) + '_ {
        |event| self.words.tell(event)
    }
}

/// The store a preview is drawn in front of: of `files`, built in `folder`.
struct Build<'a> {
    files: &'a [PathBuf],
    folder: PathBuf,
    stores: &'a StoreCache,
    options: CutOptions,
    points: u64,
}

/// Renders the frames from the files' chunk starts while their store builds on another
/// thread, again with the nodes stored so far each time another tenth of the points is
/// stored, then the final frames from the store over them.
fn preview_then_final(
    target: &FrameTarget<'_>,
    renderer: Renderer,
    build: Build<'_>,
) -> Result<()> {
    let Build {
        files,
        folder,
        stores,
        options,
        points,
    } = build;
    let events = target.events();
    target.words.say(&format!(
        "building levels of detail of {points} points in the background (once; kept in {})",
        folder.display()
    ));
    // The build waits for the first preview frame, whose time to screen it would otherwise
    // share the cores with (docs/perf/preview-first-frame.md).
    let (start_build, build_gate) = mpsc::channel();
    let progress = Arc::new(BuildProgress::new());
    let build = LocalStore::build_in_background(
        files.to_vec(),
        folder,
        options.memory_budget_bytes,
        stores.disk_budget,
        build_gate,
        Arc::clone(&progress),
    )?;
    let chunk_starts = ChunkStarts::read(files)?;
    let render = &target.request.render;
    let mut preview =
        FrameSource::preview(renderer, chunk_starts.with_nodes(&[]), render, &events)?;
    let building = || !build.is_finished();
    target.render(&mut preview, &|| {
        let _ = start_build.send(());
        building()
    })?;
    drop(start_build);
    // The preview's GPU memory is the final frames' node cache's: let go of before them.
    let renderer = redraw_while_building(target, &chunk_starts, &progress, &building, preview)?;
    let built = build.join();
    let stored = built.map_err(|_| anyhow::anyhow!("the levels of detail's build panicked"))??;
    let store = LocalStore::of_built(
        stored,
        files,
        options.memory_budget_bytes,
        stores.disk_budget,
        &events,
    );
    let mut source = FrameSource::levels(
        renderer,
        Levels::Store(Box::new(store)),
        options,
        render,
        &events,
    )?;
    target.render_final(&mut source)
}

/// Renders a COPC file's frames (`source`, opened at `options`) from coarse cuts at
/// [`PREVIEW_LOD_ERROR_PX`], then the final frames at `options`' pixel error over them, into
/// the same files, with the nodes the previews read still cached.
fn copc_preview_then_final(
    target: &FrameTarget<'_>,
    mut source: FrameSource,
    options: CutOptions,
) -> Result<()> {
    source.preview_cuts(true)?;
    target.render(&mut source, &|| true)?;
    source.preview_cuts(false)?;
    target.words.say(&format!(
        "final frames at a pixel error of {}",
        options.lod_error
    ));
    target.render_final(&mut source)
}

/// Draws the preview frames again, each time the build has stored another tenth of the
/// points, from the chunk starts and the nodes stored so far, until `building` says it is
/// done; gives back the renderer.
fn redraw_while_building(
    target: &FrameTarget<'_>,
    chunk_starts: &ChunkStarts,
    progress: &BuildProgress,
    building: &dyn Fn() -> bool,
    mut preview: FrameSource,
) -> Result<Renderer> {
    let mut drawn = 0;
    loop {
        let spinner = crate::progress::spinner("waiting for the levels of detail".into());
        let stored = loop {
            let (stored, total) = progress.points();
            let step = (PREVIEW_REDRAW_SHARE * total as f64).max(1.0);
            if !building() || (total > 0 && stored as f64 >= drawn as f64 + step) {
                break stored;
            }
            std::thread::sleep(std::time::Duration::from_millis(200));
        };
        spinner.finish_and_clear();
        if !building() {
            return Ok(preview.into_renderer());
        }
        drawn = stored;
        // The preview's GPU memory is the next one's.
        let renderer = preview.into_renderer();
        let reading = std::time::Instant::now();
        let nodes = progress.read_points(PREVIEW_STORED_POINTS)?;
        tracing::info!(
            stored,
            nodes = nodes.len(),
            read_ms = format!("{:.0}", reading.elapsed().as_secs_f64() * 1e3),
            "preview redrawn with the nodes stored so far"
        );
        let points = chunk_starts.with_nodes(&nodes);
        drop(nodes);
        preview = FrameSource::preview(renderer, points, &target.request.render, &target.events())?;
        target.render(&mut preview, building)?;
    }
}

/// Renders the request's frames from `source` into the outputs, while `keep_going` says so
/// after the first; a preview's frames are followed by final ones, so only final frames
/// write the legend, the summary and the video.
fn render_frames(
    target: &FrameTarget<'_>,
    source: &mut FrameSource,
    keep_going: &dyn Fn() -> bool,
) -> Result<()> {
    let FrameTarget {
        args,
        request,
        outputs,
        gpu,
        ..
    } = *target;
    let events = target.events();
    let say = |line: String| crate::output::say(args.json, line);
    let is_preview = source.is_preview();
    if let (Some(path), false) = (&outputs.legend, is_preview) {
        say(write_legend(
            path,
            Legend::of(request.render.coloring(), source.ramp_range()),
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
        let what = if is_preview {
            "preview frames"
        } else {
            "frames"
        };
        ProgressBar::new(u64::from(frames)).with_style(
            ProgressStyle::with_template(&format!(
                "{{bar:40}} {{pos}}/{{len}} {what}, {{eta}} left"
            ))
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
        )
    } else {
        ProgressBar::hidden()
    };
    let mut written = Vec::with_capacity(frames as usize);
    let mut all = Vec::with_capacity(frames as usize);
    for i in 0..frames {
        if i > 0 && !keep_going() {
            break;
        }
        let frame_settings = settings(i);
        let mut rendered = source.render(&frame_settings, &events)?;
        // The next frame's nodes load while this one is encoded and written.
        if i + 1 < frames {
            source.read_ahead(&settings(i + 1));
        }
        let path = files.frame(i);
        outputs.save_frame(&mut rendered.frame, &path, &frame_settings.camera)?;
        if request.render.depth {
            outputs.save_depth(i, &rendered.frame, &frame_settings)?;
        }
        let fetched = target.fetched.map(RemoteClient::counts);
        let frame = ReportedFrame {
            index: i,
            path: &path,
            settings: &frame_settings,
            rendered: &rendered,
            fetched,
        };
        report_frame(args, &frame, &bounds, &progress);
        all.push(rendered.frame.timings);
        written.push(path);
        progress.inc(1);
    }
    progress.finish_and_clear();
    if is_preview {
        say(format!(
            "preview: {} of {frames} frame{} in {}",
            written.len(),
            if frames == 1 { "" } else { "s" },
            files.dir().display()
        ));
        return Ok(());
    }
    if args.is_sequence() && !args.json {
        print_summary(files.dir(), &all);
    }
    if let Some(video) = &outputs.video {
        video.assemble(&written)?;
        say(format!("video: {}", video.path().display()));
    }
    Ok(())
}

/// A frame rendered, as its line reports it.
struct ReportedFrame<'a> {
    index: u32,
    path: &'a Path,
    settings: &'a FrameSettings,
    rendered: &'a SourceFrame,
    /// What reading by URL has fetched so far, where the frames are read by URL.
    fetched: Option<FetchCounts>,
}

/// A frame's line (or its JSON object with --json), above the progress bar if there is one.
fn report_frame(
    args: &RenderArgs,
    frame: &ReportedFrame<'_>,
    bounds: &WorldBounds,
    progress: &ProgressBar,
) {
    let ReportedFrame {
        index,
        path,
        settings,
        rendered,
        fetched,
    } = *frame;
    let line = if args.json {
        let json = FrameJson::new(index, path, settings, bounds, rendered);
        let mut value = serde_json::to_value(json).unwrap_or_default();
        if let (Some(counts), Some(object)) = (fetched, value.as_object_mut()) {
            // So far, over every frame: opening the file's reads included.
            object.insert(
                "fetched".into(),
                serde_json::json!({ "requests": counts.requests, "bytes": counts.bytes }),
            );
        }
        value.to_string()
    } else {
        let mut line = format!("{}  {}", path.display(), rendered.frame.timings);
        if rendered.preview.is_some() {
            line.push_str(&format!(
                "  | preview of {} of {} points ({:.3}%)",
                rendered.points_rendered,
                rendered.points_total,
                rendered.points_rendered as f64 * 100.0 / rendered.points_total.max(1) as f64
            ));
        }
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
    for (name, ms) in summary_rows(frames) {
        outln!("  {name:<10} {ms:>9.2} ms");
    }
}

/// The median milliseconds of every stage the frames report, in the order they first ran,
/// then of the frames' totals.
fn summary_rows(frames: &[StageTimings]) -> Vec<(&'static str, f64)> {
    let mut stages: Vec<Stage> = Vec::new();
    for timing in frames.iter().flat_map(|t| &t.stages) {
        if !stages.contains(&timing.stage) {
            stages.push(timing.stage);
        }
    }
    let mut rows: Vec<(&'static str, f64)> = stages
        .into_iter()
        .map(|stage| {
            let ms = frames.iter().filter_map(|t| t.get(stage)).collect();
            (stage.name(), median(ms))
        })
        .collect();
    if !frames.is_empty() {
        rows.push((
            "total",
            median(frames.iter().map(StageTimings::total_ms).collect()),
        ));
    }
    rows
}

fn median(mut ms: Vec<f64>) -> f64 {
    ms.sort_by(f64::total_cmp);
    ms.get(ms.len() / 2).copied().unwrap_or(0.0)
}

#[cfg(test)]
mod tests {
    use super::*;
    use pointfarm_render::raster::Clock;

    #[test]
    fn the_summary_lists_every_stage_the_frames_report_and_a_total() {
        let frame = |fill: f64| {
            let mut timings = StageTimings::default();
            timings.push(Stage::Rasterize, 2.0, Clock::Gpu);
            timings.push(Stage::Accumulate, 1.0, Clock::Gpu);
            timings.push(Stage::Visibility, 0.5, Clock::Gpu);
            timings.push(Stage::Fill, fill, Clock::Gpu);
            timings.push(Stage::Encode, 3.0, Clock::Host);
            timings
        };
        let rows = summary_rows(&[frame(1.0), frame(2.0), frame(4.0)]);
        let names: Vec<&str> = rows.iter().map(|(name, _)| *name).collect();
        assert_eq!(
            names,
            [
                "rasterize",
                "accumulate",
                "visibility",
                "fill",
                "encode",
                "total"
            ]
        );
        assert_eq!(rows[3].1, 2.0);
        assert_eq!(rows[5].1, 8.5);
        assert!(summary_rows(&[]).is_empty());
    }
}

//! `pointfarm render`: the request the arguments describe, rendered here frame by frame, or
//! handed to a server (`remote_render`).

use std::path::PathBuf;
use std::sync::{mpsc, Arc};

use anyhow::Result;
use indicatif::{ProgressBar, ProgressStyle};
use pointfarm_render::copc::is_copc;
use pointfarm_render::cut::{CutOptions, StoredLod, PREVIEW_LOD_ERROR_PX};
use pointfarm_render::gpu::GpuContext;
use pointfarm_render::ingest::{dataset_files, dataset_point_count};
use pointfarm_render::lod::{BuildProgress, PREVIEW_REDRAW_SHARE, PREVIEW_STORED_POINTS};
use pointfarm_render::raster::{FrameSettings, Renderer};
use pointfarm_render::remote::{ListedObject, ObjectUrl, RemoteClient};
use pointfarm_render::request::RenderRequest;
use pointfarm_render::source::{
    file_boxes, frame_points, BuildStage, ChunkStarts, FileOrder, FramePoints, FrameSource,
    HeldExposure, Levels, LocalStore, Opening, PointSourceFacts, SourceEvent, StagedStore,
    StoreCache, StoreInput,
};

use crate::frame_lines;
use crate::output::Reporter;
use crate::paths::store_cache;
use crate::render_outputs::Outputs;
use crate::source_words::SourceWords;
use crate::url_input::{self, Inputs, UrlDataset};

pub use crate::render_args::RenderArgs;

pub fn run(args: RenderArgs) -> Result<()> {
    let reporter = Reporter::new(args.json);
    // Refuse bad options before anything is read, with the field at fault: the request, where
    // the frames go, and the video.
    let request = args.request()?;
    let outputs = Outputs::check(&args, &request, reporter)?;
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
    let inputs = url_input::classify(&args.inputs)?;
    let words = SourceWords::new(args.json, args.inputs_label());
    let asked = Asked {
        args: &args,
        request: &request,
        outputs: &outputs,
        words: &words,
        reporter,
    };
    match inputs {
        Inputs::Url(url) => render_url(asked, &url),
        Inputs::Paths(paths) => render_files(asked, &paths),
    }
}

const BUILT_ALREADY: &str = "the levels of detail are built already";
const FINAL_AT_ONCE: &str = "rendering the final frames";

/// What a local render is asked for, and who says its steps.
#[derive(Clone, Copy)]
struct Asked<'a> {
    args: &'a RenderArgs,
    request: &'a RenderRequest,
    outputs: &'a Outputs,
    words: &'a SourceWords,
    reporter: Reporter,
}

/// Renders the files `paths` name, here: resident, cut by cut from their store (built
/// first, or, with `--preview`, previewed while it builds), or from a COPC file's own
/// hierarchy.
fn render_files(asked: Asked<'_>, paths: &[PathBuf]) -> Result<()> {
    let args = asked.args;
    let files = dataset_files(paths)?;
    let points = dataset_point_count(&files)?;
    let target = FrameTarget::new(asked, None)?;
    if let [one] = files.as_slice() {
        if is_copc(one)? {
            let cut_options = args.lod_options()?;
            let opening = Opening::Copc {
                file: one.as_path(),
                cut_options,
            };
            return target.render_plan(target.copc_plan(opening, cut_options));
        }
    }
    let stores = store_cache(args.cache_dir.as_ref(), args.cache_size);
    let folder = stores.folder_of_files(&files)?;
    // A store already built in the cache is cut, as a server cuts it, whatever the size.
    let store_built = StoredLod::is_built(&folder);
    let facts = PointSourceFacts {
        points: Some(points),
        one_copc_file: false,
        store_built,
        levels_of_detail_asked: args.levels_of_detail_asked(),
    };
    let plan = match frame_points(&facts) {
        FramePoints::Resident => {
            if args.preview {
                asked.reporter.say(format_args!(
                    "--preview: {points} points render resident, nothing to build; \
                     {FINAL_AT_ONCE}"
                ));
            }
            Plan::Frames(Opening::Resident {
                files: &files,
                cache: None,
            })
        }
        _ if args.preview && !store_built => Plan::WhileBuilding(Build {
            input: BuildInput::Files(&files, points),
            folder: folder.clone(),
            stores: &stores,
            options: args.lod_options()?,
        }),
        _ => {
            if args.preview {
                asked
                    .reporter
                    .say(format_args!("--preview: {BUILT_ALREADY}; {FINAL_AT_ONCE}"));
            }
            let cut_options = args.lod_options()?;
            if !store_built && FileOrder::applies(asked.request) {
                let boxes = file_boxes(&files)?;
                if let Some(order) = FileOrder::of(asked.request, &boxes) {
                    let memory = cut_options.memory_budget_bytes;
                    let staged = StagedStore::new(&files, &folder, memory, stores.disk_budget)?;
                    return camera_first(&target, &staged, &order, cut_options);
                }
            }
            Plan::Frames(Opening::Store {
                files: &files,
                folder: folder.as_path(),
                disk_budget: stores.disk_budget,
                cut_options,
            })
        }
    };
    target.render_plan(plan)
}

/// Renders the frames cut by cut from a store built camera first (`source::camera_first`):
/// the first frame once the files it sees are in, the others once the path's are, then adds
/// the files no frame sees (unless `--build-unseen never`).
fn camera_first(
    target: &FrameTarget<'_>,
    staged: &StagedStore<'_>,
    order: &FileOrder,
    options: CutOptions,
) -> Result<()> {
    let frames = target.asked.request.frames();
    let events = target.events();
    let mut renderer = Some(Renderer::new(Arc::clone(&target.gpu)));
    let (mut drawn, mut held, mut built) = (Drawn::default(), HeldExposure::default(), 0);
    for (stage, places) in order.stages(target.asked.args.build_unseen) {
        let store = staged.open_stage(stage, &places, &places[built..], &events)?;
        built = places.len();
        let range = match stage {
            BuildStage::FirstFrame if !order.path.is_empty() => 0..1,
            BuildStage::FirstFrame => 0..frames,
            BuildStage::Path => 1..frames,
            BuildStage::Unseen => continue,
        };
        let Some(drawing) = renderer.take() else {
            anyhow::bail!("the renderer was not given back");
        };
        let opening = Opening::Levels {
            levels: Levels::Store(Box::new(store)),
            cut_options: options,
        };
        let mut source = target.open(drawing, opening)?;
        source.hold_exposure_of(held);
        render_range(target, &mut source, range, &|| true, &mut drawn)?;
        held = source.held_exposure();
        renderer = Some(source.into_renderer());
    }
    finish_frames(target, false, drawn)
}

/// Renders the COPC file at `url` as a file here is rendered, cut by cut, its header,
/// hierarchy pages and nodes read by range as the frames reach them; or LAS/LAZ tiles by URL
/// from the store built here by streaming them (with `--preview`, previewed from their chunk
/// starts read by range while it builds). Says what was fetched.
fn render_url(asked: Asked<'_>, url: &ObjectUrl) -> Result<()> {
    let args = asked.args;
    let client = url_input::client()?;
    let dataset = url_input::open(&client, url)?;
    let target = FrameTarget::new(asked, Some(&client))?;
    let cut_options = args.lod_options()?;
    match dataset {
        UrlDataset::Tiles(tiles) => render_tiles(&target, &client, &tiles)?,
        UrlDataset::Copc(copc) => {
            let opening = Opening::Levels {
                levels: Levels::Copc(copc),
                cut_options,
            };
            target.render_plan(target.copc_plan(opening, cut_options))?;
        }
    }
    let counts = client.counts();
    asked.reporter.say(format_args!(
        "fetched {} bytes in {} requests from {url}",
        counts.bytes, counts.requests
    ));
    Ok(())
}

/// Renders LAS/LAZ tiles by URL cut by cut from their store here, kept under their URLs and
/// versions: built first by streaming them, or, with `--preview`, previewed from their chunk
/// starts while it builds.
fn render_tiles(
    target: &FrameTarget<'_>,
    client: &RemoteClient,
    tiles: &[ListedObject],
) -> Result<()> {
    let args = target.asked.args;
    let stores = store_cache(args.cache_dir.as_ref(), args.cache_size);
    let folder = stores.folder_of_objects(tiles);
    let options = args.lod_options()?;
    if args.preview && !StoredLod::is_built(&folder) {
        return target.render_plan(Plan::WhileBuilding(Build {
            input: BuildInput::Tiles(client, tiles),
            folder,
            stores: &stores,
            options,
        }));
    }
    if args.preview {
        target
            .asked
            .reporter
            .say(format_args!("--preview: {BUILT_ALREADY}; {FINAL_AT_ONCE}"));
    }
    let store = LocalStore::open_or_build_tiles(
        client,
        tiles,
        &folder,
        options.memory_budget_bytes,
        stores.disk_budget,
        &target.events(),
    )?;
    target.render_plan(Plan::Frames(Opening::Levels {
        levels: Levels::Store(Box::new(store)),
        cut_options: options,
    }))
}

/// How a render's frames are drawn.
enum Plan<'a> {
    /// The frames from one source: final frames, or a preview's alone.
    Frames(Opening<'a>),
    /// A COPC source's coarse cuts at [`PREVIEW_LOD_ERROR_PX`], then the final frames at the
    /// options' pixel error over them, from the same source.
    CoarseFirst(Opening<'a>, CutOptions),
    /// Preview frames from the files' chunk starts while their store builds, then the final
    /// frames from it.
    WhileBuilding(Build<'a>),
}

/// What frames are rendered for, where they go, who tells their source's steps, and the
/// adapter that draws them.
struct FrameTarget<'a> {
    asked: Asked<'a>,
    gpu: Arc<GpuContext>,
    /// The client frames are read through by URL, whose counts each frame's JSON reports.
    fetched: Option<&'a RemoteClient>,
}

impl<'a> FrameTarget<'a> {
    /// The target of `asked`, on the adapter it asks for.
    fn new(asked: Asked<'a>, fetched: Option<&'a RemoteClient>) -> Result<Self> {
        Ok(Self {
            gpu: Arc::new(GpuContext::new(asked.args.adapter)?),
            asked,
            fetched,
        })
    }

    /// A COPC source's plan: with `--preview`, its coarse cuts first, unless its pixel error
    /// is a preview's already.
    fn copc_plan<'o>(&self, opening: Opening<'o>, options: CutOptions) -> Plan<'o> {
        if self.asked.args.preview {
            if options.lod_error < PREVIEW_LOD_ERROR_PX {
                return Plan::CoarseFirst(opening, options);
            }
            self.asked.reporter.say(format_args!(
                "--preview: the pixel error ({}) is a preview's already; {FINAL_AT_ONCE}",
                options.lod_error
            ));
        }
        Plan::Frames(opening)
    }

    /// Renders every frame as `plan` says.
    fn render_plan(&self, plan: Plan<'_>) -> Result<()> {
        let renderer = Renderer::new(Arc::clone(&self.gpu));
        match plan {
            Plan::Frames(opening) => {
                let mut source = self.open(renderer, opening)?;
                self.render(&mut source, &|| true)
            }
            Plan::CoarseFirst(opening, options) => {
                let source = self.open(renderer, opening)?;
                copc_preview_then_final(self, source, options)
            }
            Plan::WhileBuilding(build) => preview_then_final(self, renderer, build),
        }
    }

    /// The source `opening` names, drawn by `renderer` as the request asks.
    fn open(&self, renderer: Renderer, opening: Opening<'_>) -> Result<FrameSource> {
        let render = &self.asked.request.render;
        Ok(FrameSource::open(
            renderer,
            opening,
            render,
            &self.events(),
        )?)
    }

    fn render(&self, source: &mut FrameSource, keep_going: &dyn Fn() -> bool) -> Result<()> {
        render_frames(self, source, keep_going)
    }

    /// Renders every final frame from `source` over the previews, and says where they are.
    fn render_final(&self, source: &mut FrameSource) -> Result<()> {
        self.render(source, &|| true)?;
        self.asked.reporter.say(format_args!(
            "final frames: {} (over the previews)",
            self.asked.outputs.files.dir().display()
        ));
        Ok(())
    }

    fn events(&self) -> impl Fn(SourceEvent<'_>) + '_ {
        |event| self.asked.words.tell(event)
    }
}

/// The store a preview is drawn in front of: of `input`, built in `folder`.
struct Build<'a> {
    input: BuildInput<'a>,
    folder: PathBuf,
    stores: &'a StoreCache,
    options: CutOptions,
}

/// What a store is built from: files here (of so many points), or tiles by URL, streamed.
enum BuildInput<'a> {
    Files(&'a [PathBuf], u64),
    Tiles(&'a RemoteClient, &'a [ListedObject]),
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
        input,
        folder,
        stores,
        options,
    } = build;
    let what = match input {
        BuildInput::Files(_, points) => format!("{points} points"),
        BuildInput::Tiles(_, tiles) => format!("{} tiles by URL", tiles.len()),
    };
    target.asked.words.say(&format!(
        "building levels of detail of {what} in the background (once; kept in {})",
        folder.display()
    ));
    // The build waits for the first preview frame, whose time to screen it would otherwise
    // share the cores with (docs/perf/preview-first-frame.md).
    let (start_build, build_gate) = mpsc::channel();
    let progress = Arc::new(BuildProgress::new());
    let (memory, disk) = (options.memory_budget_bytes, stores.disk_budget);
    let (gate, watch) = (build_gate, Arc::clone(&progress));
    let (store_input, chunk_starts, files) = match input {
        BuildInput::Files(files, _) => {
            let chunk_starts = ChunkStarts::read(files)?;
            (StoreInput::Files(files.to_vec()), chunk_starts, files)
        }
        BuildInput::Tiles(client, tiles) => {
            let urls: Vec<ObjectUrl> = tiles.iter().map(|tile| tile.url.clone()).collect();
            let chunk_starts = ChunkStarts::read_urls(client, &urls)?;
            // A store of tiles is opened without them: damaged, it is removed, for the next
            // render to build.
            let input = StoreInput::Tiles(client.clone(), tiles.to_vec());
            (input, chunk_starts, &[][..])
        }
    };
    let build = LocalStore::build_in_background(store_input, folder, memory, disk, gate, watch)?;
    let first = Box::new(chunk_starts.with_nodes(&[]));
    let mut preview = target.open(renderer, Opening::Preview(first))?;
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
    let events = target.events();
    let store = LocalStore::of_built(stored, files, memory, disk, &events);
    let levels = Levels::Store(Box::new(store));
    let opening = Opening::Levels {
        levels,
        cut_options: options,
    };
    let mut source = target.open(renderer, opening)?;
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
    target.asked.words.say(&format!(
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
        let points = Box::new(chunk_starts.with_nodes(&nodes));
        drop(nodes);
        preview = target.open(renderer, Opening::Preview(points))?;
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
    let frames = target.asked.request.frames();
    let mut drawn = Drawn::default();
    render_range(target, source, 0..frames, keep_going, &mut drawn)?;
    finish_frames(target, source.is_preview(), drawn)
}

/// The frames written so far, and their timings.
#[derive(Default)]
struct Drawn {
    written: Vec<PathBuf>,
    timings: Vec<pointfarm_render::raster::StageTimings>,
}

/// Renders the frames of `range` from `source` into the outputs, while `keep_going` says so
/// after the first; the first of the request (frame 0) says the legend and framing first.
fn render_range(
    target: &FrameTarget<'_>,
    source: &mut FrameSource,
    range: std::ops::Range<u32>,
    keep_going: &dyn Fn() -> bool,
    drawn: &mut Drawn,
) -> Result<()> {
    let Asked {
        args,
        request,
        outputs,
        reporter,
        ..
    } = target.asked;
    let events = target.events();
    let is_preview = source.is_preview();
    let bounds = source.bounds();
    let spacing = source.spacing();
    let settings = |index: u32| FrameSettings {
        atomics: args.atomics(),
        ..request.frame_settings(index, &bounds, spacing)
    };
    if range.start == 0 {
        if !is_preview {
            let coloring = request.render.coloring();
            if let Some(line) = outputs.write_legend(coloring, || source.ramp_range())? {
                reporter.say(line);
            }
        }
        reporter.say(format_args!("adapter: {}", target.gpu.describe()));
        // Refuse sizes this adapter cannot hold, or cameras the cloud makes invalid, before
        // the first frame.
        source.renderer().validate(&settings(0))?;
        for line in frame_lines::framing_lines(&bounds, &settings(0), spacing) {
            reporter.say(line);
        }
    }

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
    progress.set_position(u64::from(range.start));
    let first = range.start;
    for i in range.clone() {
        if i > first && !keep_going() {
            break;
        }
        let frame_settings = settings(i);
        let mut rendered = source.render(&frame_settings, &events)?;
        // The next frame's nodes load while this one is encoded and written.
        if i + 1 < range.end {
            source.read_ahead(&settings(i + 1));
        }
        let path = outputs.save(i, &mut rendered.frame, &frame_settings)?;
        let fetched = target.fetched.map(RemoteClient::counts);
        let frame = frame_lines::ReportedFrame {
            index: i,
            path: &path,
            settings: &frame_settings,
            rendered: &rendered,
            fetched,
        };
        frame_lines::report_frame(reporter, &frame, &bounds, &progress);
        drawn.timings.push(rendered.frame.timings);
        drawn.written.push(path);
        progress.inc(1);
    }
    progress.finish_and_clear();
    Ok(())
}

/// Says what the frames drawn came to: a preview's count, or the final frames' summary and
/// video.
fn finish_frames(target: &FrameTarget<'_>, is_preview: bool, drawn: Drawn) -> Result<()> {
    let (outputs, reporter) = (target.asked.outputs, target.asked.reporter);
    let files = &outputs.files;
    let frames = target.asked.request.frames();
    if is_preview {
        reporter.say(format_args!(
            "preview: {} of {frames} frame{} in {}",
            drawn.written.len(),
            if frames == 1 { "" } else { "s" },
            files.dir().display()
        ));
        return Ok(());
    }
    if target.asked.args.is_sequence() && !reporter.is_json() {
        frame_lines::print_summary(files.dir(), &drawn.timings);
    }
    if let Some(video) = &outputs.video {
        video.assemble(&drawn.written)?;
        reporter.say(format_args!("video: {}", video.path().display()));
    }
    Ok(())
}

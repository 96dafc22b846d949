//! What local frames are rendered from: the whole dataset resident on the GPU, or cuts of
//! levels of detail through bounded node caches: the dataset's store, or a COPC file's own
//! hierarchy read node by node. Both give a frame and what it drew.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

use anyhow::Result;
use pointfarm_render::cloud::PointCloud;
use pointfarm_render::cloud::WorldBounds;
use pointfarm_render::color::{point_colors, ramp_range, ColorRange, Coloring};
use pointfarm_render::cut::{CutOptions, CutRenderer, CutReport, PREVIEW_LOD_ERROR_PX};
use pointfarm_render::filter::PointFilter;
use pointfarm_render::gpu::GpuContext;
use pointfarm_render::ingest::{load_dataset, sample_chunk_starts, DatasetSource, PreviewSample};
use pointfarm_render::lod::{NodePoints, PointSource};
use pointfarm_render::raster::{Frame, FrameSettings, GpuPointCloud, Renderer};
use pointfarm_render::request::RenderOptions;

use crate::lod_store::{open_or_build, LocalStore, StoreCache};
use pointfarm_render::copc::{open_copc, CopcDataset};
use pointfarm_render::cut::LodDataset;

/// A frame and what it drew.
pub struct RenderedFrame {
    pub frame: Frame,
    /// The points of the dataset's files (of the cloud, for a resident one).
    pub points_total: u64,
    pub points_rendered: u64,
    /// Whether the frame is a preview: drawn from the files' chunk starts (and the nodes
    /// stored so far), or a COPC file's coarse cut.
    pub preview: bool,
    /// The cut's nodes, caches and loads, when the frame came from a store.
    pub cut: Option<CutReport>,
}

/// What a preview is drawn from besides the stored nodes: the first point of every LAZ chunk
/// (every 50,000th record of a LAS file), read once without decompressing, and the files'
/// header bounds.
pub struct PreviewData {
    sample: PreviewSample,
    framed: WorldBounds,
    files: usize,
    read_ms: f64,
}

impl PreviewData {
    pub fn read(files: &[PathBuf], options: &RenderOptions) -> Result<Self> {
        let started = Instant::now();
        let sample = sample_chunk_starts(files)?;
        let framed = options
            .filter
            .framing_bounds(&DatasetSource::open(files)?.bounds())?;
        Ok(Self {
            sample,
            framed,
            files: files.len(),
            read_ms: started.elapsed().as_secs_f64() * 1e3,
        })
    }
}

pub enum FrameSource {
    Resident {
        renderer: Renderer,
        cloud: GpuPointCloud,
        bounds: WorldBounds,
        spacing: Option<f64>,
        ramp_range: Option<ColorRange>,
        /// For a preview of the files' chunk starts, the points of the files.
        preview_of: Option<u64>,
    },
    Cut {
        renderer: Renderer,
        cut: Box<CutRenderer>,
        lod: Levels,
        coloring: Coloring,
        filter: PointFilter,
        /// What the automatic camera frames: the store's bounds within the filter's box.
        bounds: WorldBounds,
        /// Whether the cuts are a preview's, at a coarser pixel error than the final frames'.
        preview: bool,
    },
}

/// Where a cut's levels of detail come from.
pub enum Levels {
    /// The dataset's store in the cache folder, built again once if its bytes fail their
    /// checks.
    Store(Box<LocalStore>),
    /// A COPC file's own hierarchy, its nodes read from the file.
    Copc(Box<CopcDataset>),
}

impl Levels {
    pub fn dataset(&self) -> &LodDataset {
        match self {
            Self::Store(store) => &store.stored.dataset,
            Self::Copc(copc) => &copc.dataset,
        }
    }
}

impl FrameSource {
    /// The dataset read whole, coloured, filtered and uploaded.
    pub fn resident(
        gpu: Arc<GpuContext>,
        files: &[PathBuf],
        options: &RenderOptions,
        say: &dyn Fn(String),
    ) -> Result<Self> {
        let started = Instant::now();
        let spinner = crate::progress::spinner(match files {
            [one] => format!("reading {}", one.display()),
            many => format!("reading {} files", many.len()),
        });
        let cloud = load_dataset(files);
        spinner.finish_and_clear();
        let cloud = cloud?;
        let points = cloud.len();
        let about = format!(
            "{points} points in {} file{}, {}, read in {:.0} ms",
            files.len(),
            plural(files.len()),
            cloud.color_source.describe(),
            started.elapsed().as_secs_f64() * 1e3
        );
        Self::of_cloud(gpu, cloud, options, None, &about, say)
    }

    /// A preview: `data`'s chunk starts and `stored`, the nodes a build has stored so far,
    /// resident, framed by the files' header bounds as the store built from them will be.
    pub fn preview(
        gpu: Arc<GpuContext>,
        data: &PreviewData,
        stored: &[NodePoints],
        options: &RenderOptions,
        say: &dyn Fn(String),
    ) -> Result<Self> {
        let cloud = data.sample.cloud_with_nodes(stored);
        let stored_points: usize = stored.iter().map(NodePoints::len).sum();
        let what = if stored.is_empty() {
            format!("chunk starts, read in {:.0} ms", data.read_ms)
        } else {
            format!(
                "{} chunk starts and {stored_points} points of {} stored nodes",
                data.sample.cloud.len(),
                stored.len()
            )
        };
        let about = format!(
            "preview: {} of the {} points in {} file{} ({what}), {}",
            cloud.len(),
            data.sample.points_in_files,
            data.files,
            plural(data.files),
            cloud.color_source.describe(),
        );
        let mut source = Self::of_cloud(gpu, cloud, options, Some(data.framed), &about, say)?;
        if let Self::Resident { preview_of, .. } = &mut source {
            *preview_of = Some(data.sample.points_in_files);
        }
        Ok(source)
    }

    /// `cloud` coloured, filtered and uploaded, once `about` it is said; framed by its own
    /// bounds unless `framed` says otherwise.
    fn of_cloud(
        gpu: Arc<GpuContext>,
        mut cloud: PointCloud,
        options: &RenderOptions,
        framed: Option<WorldBounds>,
        about: &str,
        say: &dyn Fn(String),
    ) -> Result<Self> {
        let coloring = options.coloring();
        cloud.colors = point_colors(&cloud, coloring);
        let ramp_range = ramp_range(&cloud, coloring);
        let points = cloud.len();
        say(about.to_string());
        if !options.filter.keeps_everything() {
            let kept = options.filter.apply(&mut cloud)?;
            say(filtered_words(kept, points));
        }
        let renderer = Renderer::new(gpu);
        let bounds = framed.unwrap_or(cloud.bounds);
        let spacing = cloud.spacing();
        let resident = renderer.upload(&cloud)?;
        Ok(Self::Resident {
            renderer,
            cloud: resident,
            bounds,
            spacing,
            ramp_range,
            preview_of: None,
        })
    }

    /// The dataset's store, built first if the cache folder has none, rendered cut by cut.
    pub fn cut(
        gpu: Arc<GpuContext>,
        files: &[PathBuf],
        cache: &StoreCache,
        options: CutOptions,
        render: &RenderOptions,
        say: &dyn Fn(String),
    ) -> Result<Self> {
        let lod = open_or_build(files, cache, options.memory_budget_bytes, say)?;
        Self::stored(gpu, lod, files.len(), options, render, say)
    }

    /// An opened store of a dataset of `file_count` files, rendered cut by cut.
    pub fn stored(
        gpu: Arc<GpuContext>,
        lod: LocalStore,
        file_count: usize,
        options: CutOptions,
        render: &RenderOptions,
        say: &dyn Fn(String),
    ) -> Result<Self> {
        let about = format!(
            "{} points in {file_count} file{}, levels of detail from {}",
            lod.stored.dataset.point_count(),
            plural(file_count),
            lod.stored.folder.display(),
        );
        Self::of_levels(
            gpu,
            Levels::Store(Box::new(lod)),
            options,
            render,
            &about,
            say,
        )
    }

    /// A COPC file rendered cut by cut from its own hierarchy: no store is built, only the
    /// nodes a frame's cut needs are read from the file.
    pub fn copc(
        gpu: Arc<GpuContext>,
        file: &Path,
        options: CutOptions,
        render: &RenderOptions,
        say: &dyn Fn(String),
    ) -> Result<Self> {
        let started = Instant::now();
        let copc = open_copc(file)?;
        let plural = |n: usize| if n == 1 { "" } else { "s" };
        let unread = match copc.unread_pages {
            0 => String::new(),
            n => format!(", {n} more page{} read as frames reach them", plural(n)),
        };
        let about = format!(
            "{} points, COPC: reading its hierarchy node by node ({} nodes in the {} page{} read{unread}; {} nodes read for the colour ranges, {:.0} ms)",
            copc.dataset.point_count(),
            copc.nodes,
            copc.pages,
            plural(copc.pages),
            copc.sample_nodes,
            started.elapsed().as_secs_f64() * 1e3,
        );
        Self::of_levels(
            gpu,
            Levels::Copc(Box::new(copc)),
            options,
            render,
            &about,
            say,
        )
    }

    /// `levels` rendered cut by cut, once `about` them and their node caches is said.
    fn of_levels(
        gpu: Arc<GpuContext>,
        levels: Levels,
        options: CutOptions,
        render: &RenderOptions,
        about: &str,
        say: &dyn Fn(String),
    ) -> Result<Self> {
        let renderer = Renderer::new(gpu);
        let bounds = render.filter.framing_bounds(&levels.dataset().bounds())?;
        let cut = CutRenderer::new(&renderer, levels.dataset(), options)?;
        let budgets = cut.budgets();
        say(format!(
            "{about}; node caches: host {} MiB, GPU {} MiB; pixel error {}",
            budgets.host_bytes >> 20,
            budgets.gpu_bytes >> 20,
            options.lod_error,
        ));
        Ok(Self::Cut {
            renderer,
            cut: Box::new(cut),
            lod: levels,
            coloring: render.coloring(),
            filter: render.filter,
            bounds,
            preview: false,
        })
    }

    /// A COPC file's preview: [`FrameSource::copc`] drawing its cuts at
    /// [`PREVIEW_LOD_ERROR_PX`] until [`FrameSource::finish_preview`].
    pub fn copc_preview(
        gpu: Arc<GpuContext>,
        file: &Path,
        options: CutOptions,
        render: &RenderOptions,
        say: &dyn Fn(String),
    ) -> Result<Self> {
        let preview_options = CutOptions {
            lod_error: PREVIEW_LOD_ERROR_PX,
            ..options
        };
        let mut source = Self::copc(gpu, file, preview_options, render, say)?;
        if let Self::Cut { preview, .. } = &mut source {
            *preview = true;
        }
        Ok(source)
    }

    /// The final frames after a preview's, at `lod_error` pixels, with the nodes the preview
    /// cached.
    pub fn finish_preview(&mut self, lod_error: f64) -> Result<()> {
        if let Self::Cut { cut, preview, .. } = self {
            cut.set_lod_error(lod_error)?;
            *preview = false;
        }
        Ok(())
    }

    /// Whether the frames are previews: of the files' chunk starts, or a COPC file's coarse
    /// cuts.
    pub fn is_preview(&self) -> bool {
        match self {
            Self::Resident { preview_of, .. } => preview_of.is_some(),
            Self::Cut { preview, .. } => *preview,
        }
    }

    /// The bounds the automatic camera frames.
    pub fn bounds(&self) -> WorldBounds {
        match self {
            Self::Resident { bounds, .. } | Self::Cut { bounds, .. } => *bounds,
        }
    }

    /// The typical distance between the points drawn, which sizes adaptive points: the
    /// filtered cloud's, or the store's original points'.
    pub fn spacing(&self) -> Option<f64> {
        match self {
            Self::Resident { spacing, .. } => *spacing,
            Self::Cut { lod, .. } => lod.dataset().point_spacing(),
        }
    }

    /// The range elevation or intensity is drawn over (the request's, or the data's robust
    /// one); `None` for the other modes.
    pub fn ramp_range(&self) -> Option<ColorRange> {
        match self {
            Self::Resident { ramp_range, .. } => *ramp_range,
            Self::Cut { lod, coloring, .. } => lod.dataset().ramp_range(*coloring),
        }
    }

    pub fn renderer(&self) -> &Renderer {
        match self {
            Self::Resident { renderer, .. } | Self::Cut { renderer, .. } => renderer,
        }
    }

    /// Renders the frame of `settings`. A store whose bytes fail their checks is built again
    /// (once, `say`ing so) and the frame rendered from the new one.
    pub fn render(
        &mut self,
        settings: &FrameSettings,
        say: &dyn Fn(String),
    ) -> Result<RenderedFrame> {
        match self {
            Self::Resident {
                renderer,
                cloud,
                preview_of,
                ..
            } => {
                let frame = renderer.render(cloud, settings)?;
                Ok(RenderedFrame {
                    frame,
                    points_total: preview_of.unwrap_or(cloud.len() as u64),
                    points_rendered: renderer.listed_points(),
                    preview: preview_of.is_some(),
                    cut: None,
                })
            }
            Self::Cut {
                renderer,
                cut,
                lod,
                coloring,
                filter,
                preview,
                ..
            } => {
                let (frame, report) = loop {
                    let error =
                        match cut.render(renderer, lod.dataset(), settings, *coloring, filter) {
                            Ok(rendered) => break rendered,
                            Err(error) => error,
                        };
                    let Levels::Store(store) = lod else {
                        return Err(error.into());
                    };
                    if !error.is_store_damage() {
                        return Err(error.into());
                    }
                    store.rebuild_after(&error, say)?;
                    // The caches hold the old store's nodes: a new renderer starts empty.
                    **cut = CutRenderer::new(renderer, &store.stored.dataset, *cut.options())?;
                };
                Ok(RenderedFrame {
                    frame,
                    points_total: report.counts.points_total,
                    points_rendered: report.counts.points_rendered,
                    preview: *preview,
                    cut: Some(report),
                })
            }
        }
    }

    /// Starts loading the nodes of the next frame while this one is written.
    pub fn read_ahead(&mut self, settings: &FrameSettings) {
        if let Self::Cut {
            cut, lod, filter, ..
        } = self
        {
            cut.read_ahead(lod.dataset(), settings, filter);
        }
    }
}

fn plural(count: usize) -> &'static str {
    if count == 1 {
        ""
    } else {
        "s"
    }
}

/// What a filter kept of a dataset's points, in words; a warning when it kept none.
fn filtered_words(kept: usize, points: usize) -> String {
    if kept == 0 {
        format!("the filter keeps none of the {points} points: the frames show only the background")
    } else {
        let percent = kept as f64 * 100.0 / points.max(1) as f64;
        format!("the filter keeps {kept} of {points} points ({percent:.1}%)")
    }
}

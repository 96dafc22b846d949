//! What local frames are rendered from: the whole dataset resident on the GPU, or cuts of
//! levels of detail through bounded node caches: the dataset's store, or a COPC file's own
//! hierarchy read node by node. Both give a frame and what it drew.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

use anyhow::Result;
use pointfarm_render::cloud::WorldBounds;
use pointfarm_render::color::{point_colors, ramp_range, ColorRange, Coloring};
use pointfarm_render::cut::{CutOptions, CutRenderer, CutReport};
use pointfarm_render::filter::PointFilter;
use pointfarm_render::gpu::GpuContext;
use pointfarm_render::ingest::load_dataset;
use pointfarm_render::raster::{Frame, FrameSettings, GpuPointCloud, Renderer};
use pointfarm_render::request::RenderOptions;

use crate::lod_store::{open_or_build, StoreCache};
use pointfarm_render::copc::{open_copc, CopcDataset};
use pointfarm_render::cut::{LodDataset, StoredLod};

/// A frame and what it drew.
pub struct RenderedFrame {
    pub frame: Frame,
    pub points_total: u64,
    pub points_rendered: u64,
    /// The cut's nodes, caches and loads, when the frame came from a store.
    pub cut: Option<CutReport>,
}

pub enum FrameSource {
    Resident {
        renderer: Renderer,
        cloud: GpuPointCloud,
        bounds: WorldBounds,
        spacing: Option<f64>,
        ramp_range: Option<ColorRange>,
    },
    Cut {
        renderer: Renderer,
        cut: Box<CutRenderer>,
        lod: Levels,
        coloring: Coloring,
        filter: PointFilter,
        /// What the automatic camera frames: the store's bounds within the filter's box.
        bounds: WorldBounds,
    },
}

/// Where a cut's levels of detail come from.
pub enum Levels {
    /// The dataset's store in the cache folder.
    Store(Box<StoredLod>),
    /// A COPC file's own hierarchy, its nodes read from the file.
    Copc(Box<CopcDataset>),
}

impl Levels {
    pub fn dataset(&self) -> &LodDataset {
        match self {
            Self::Store(stored) => &stored.dataset,
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
        let mut cloud = cloud?;
        let coloring = options.coloring();
        cloud.colors = point_colors(&cloud, coloring);
        let ramp_range = ramp_range(&cloud, coloring);
        let points = cloud.len();
        say(format!(
            "{points} points in {} file{}, {}, read in {:.0} ms",
            files.len(),
            if files.len() == 1 { "" } else { "s" },
            cloud.color_source.describe(),
            started.elapsed().as_secs_f64() * 1e3
        ));
        if !options.filter.keeps_everything() {
            let kept = options.filter.apply(&mut cloud)?;
            say(filtered_words(kept, points));
        }
        let renderer = Renderer::new(gpu);
        let bounds = cloud.bounds;
        let spacing = cloud.spacing();
        let resident = renderer.upload(&cloud)?;
        Ok(Self::Resident {
            renderer,
            cloud: resident,
            bounds,
            spacing,
            ramp_range,
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
        let about = format!(
            "{} points in {} file{}, levels of detail from {}",
            lod.dataset.point_count(),
            files.len(),
            if files.len() == 1 { "" } else { "s" },
            lod.folder.display(),
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
        let about = format!(
            "{} points, COPC: reading its hierarchy node by node ({} nodes in {} page{}, {} nodes read for the colour ranges, {:.0} ms)",
            copc.dataset.point_count(),
            copc.nodes,
            copc.pages,
            if copc.pages == 1 { "" } else { "s" },
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
        })
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

    pub fn render(&mut self, settings: &FrameSettings) -> Result<RenderedFrame> {
        match self {
            Self::Resident {
                renderer, cloud, ..
            } => {
                let frame = renderer.render(cloud, settings)?;
                Ok(RenderedFrame {
                    frame,
                    points_total: cloud.len() as u64,
                    points_rendered: renderer.listed_points(),
                    cut: None,
                })
            }
            Self::Cut {
                renderer,
                cut,
                lod,
                coloring,
                filter,
                ..
            } => {
                let (frame, report) =
                    cut.render(renderer, lod.dataset(), settings, *coloring, filter)?;
                Ok(RenderedFrame {
                    frame,
                    points_total: report.counts.points_total,
                    points_rendered: report.counts.points_rendered,
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

/// What a filter kept of a dataset's points, in words; a warning when it kept none.
fn filtered_words(kept: usize, points: usize) -> String {
    if kept == 0 {
        format!("the filter keeps none of the {points} points: the frames show only the background")
    } else {
        let percent = kept as f64 * 100.0 / points.max(1) as f64;
        format!("the filter keeps {kept} of {points} points ({percent:.1}%)")
    }
}

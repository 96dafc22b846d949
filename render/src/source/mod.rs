//! Where a frame's points come from, and the frames drawn from them: the one assembly that a
//! local render and a worker share, so a dataset renders the same way here and through a
//! server.
//!
//! [`frame_points`] decides from a dataset's facts and the request whether its frames are
//! drawn from the whole dataset resident on the GPU, from cuts through its level-of-detail
//! store, or from cuts through a COPC file's own hierarchy. A [`FrameSource`] is opened from
//! local files (through a dataset cache or not), a store of this machine, a COPC file, node
//! records a daemon serves, or a preview's points, each an [`Opening`] that
//! [`FrameSource::open`] takes; it renders each frame and reports what it drew. What happens
//! on the way (files read, a store built or built again, a filter's share) goes out as
//! [`SourceEvent`]s: the command line says them, a worker logs them.
//!
//! - `camera_first`: a store built first from the files a camera path sees.
//! - `choice`: the rule, resident or a cut.
//! - `error`: why a source could not open or render.
//! - `events`: what a source tells as it opens and renders.
//! - `exposure`: one gain after Eye-Dome Lighting for all of a job's frames.
//! - `extent`: where the points lie, and the robust box the automatic camera frames.
//! - `local_store`: stores in folders of this machine, built again once when damaged.
//! - `preview`: what a preview draws while a store builds.
//! - `published_store`: a store published to object storage, read by range.
//! - `url_tiles`: LAS/LAZ tiles by URL, described and sampled for a preview by range.
//! - `tile_store`: stores of LAS/LAZ tiles by URL, built by streaming the tiles.

mod camera_first;
mod choice;
mod error;
mod events;
mod exposure;
mod local_store;
mod preview;
mod published_store;
mod tile_store;
mod url_tiles;

use std::path::{Path, PathBuf};
use std::time::Instant;

use crate::cache::{CacheOutcome, DatasetCache};
use crate::cloud::{PointCloud, WorldBounds};
use crate::color::{point_colors, ramp_range, ColorRange, Coloring};
use crate::copc::{open_copc, CopcDataset};
use crate::cut::{
    completeness, CutError, CutOptions, CutRenderer, CutReport, LodDataset, PREVIEW_LOD_ERROR_PX,
};
use crate::filter::PointFilter;
use crate::ingest::load_dataset;
use crate::lod::for_each_coarse_node_up_to;
use crate::raster::{Frame, FrameSettings, GpuPointCloud, Renderer};
use crate::request::{RenderOptions, RenderRequest};

pub use crate::extent::{Extent, Framed};
pub use camera_first::{file_boxes, frame_sees, BuildUnseen, FileOrder, StagedStore, WithinBounds};
pub use choice::{frame_points, FramePoints, PointSourceFacts};
pub use error::SourceError;
pub use events::{quiet, BuildStage, LevelsFrom, SourceEvent};
pub use exposure::HeldExposure;
pub use local_store::{LocalStore, StoreCache};
pub use preview::{ChunkStarts, PreviewPoints};
pub use published_store::{open_published_store, PublishedObjects, PublishedStoreError};
pub use tile_store::{listed_tiles, open_or_build_tiles, open_tile_source, StoreInput};
pub use url_tiles::{describe_tile, describe_tile_url};

/// A frame and what it drew.
pub struct SourceFrame {
    pub frame: Frame,
    /// The dataset's points (a resident cloud's after the filter; a preview's dataset's).
    pub points_total: u64,
    pub points_rendered: u64,
    /// For a preview, the share of the dataset's points it drew ([`completeness`]).
    pub preview: Option<f64>,
    /// The cut's nodes, caches and loads, for a frame of levels of detail.
    pub cut: Option<CutReport>,
    /// What opening the source took, with its first frame.
    pub opened: Option<Opened>,
}

/// What opening a source took, reported with its first frame.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Opened {
    /// Reading the dataset's points (a preview's: preparing them), in ms, and whether a
    /// dataset cache held them.
    pub load_ms: Option<f64>,
    pub cache: Option<CacheOutcome>,
    /// Building the store, in ms, when this opening built it (or the daemon did for it).
    pub build_ms: Option<f64>,
}

/// Where a cut's levels of detail come from.
pub enum Levels {
    /// A store of this machine.
    Store(Box<LocalStore>),
    /// A COPC file, here or by URL (`copc::open_copc_url`), its nodes read from it by range.
    Copc(Box<CopcDataset>),
    /// Node records another machine serves (a daemon's store, or its COPC file's chunks).
    Served {
        dataset: Box<LodDataset>,
        /// How long the daemon took to build the store, when it built it for this opening.
        build_ms: Option<f64>,
    },
}

impl Levels {
    pub fn dataset(&self) -> &LodDataset {
        match self {
            Self::Store(store) => &store.stored.dataset,
            Self::Copc(copc) => &copc.dataset,
            Self::Served { dataset, .. } => dataset,
        }
    }
}

/// How a source's points are on the GPU.
enum Points {
    /// One cloud drawn whole every frame.
    Resident {
        cloud: GpuPointCloud,
        spacing: Option<f64>,
        ramp_range: Option<ColorRange>,
        /// For a preview, the points of the dataset it previews.
        preview_of: Option<u64>,
    },
    /// Cuts of levels of detail through bounded node caches.
    Cut {
        cut: Box<CutRenderer>,
        levels: Levels,
        /// The dataset's extent before a clip box, from its coarsest nodes.
        unclipped: Extent,
        /// The pixel error of the final frames.
        lod_error: f64,
        /// Whether the cuts are a preview's, at [`PREVIEW_LOD_ERROR_PX`].
        preview: bool,
    },
}

/// What a [`FrameSource`] is opened from, with what each kind needs.
pub enum Opening<'a> {
    /// The dataset of `files` read whole (from `cache`, under its content hash, when there is
    /// one).
    Resident {
        files: &'a [PathBuf],
        cache: Option<(&'a DatasetCache, &'a str)>,
    },
    /// The store of `files` in `folder`, built first when there is none.
    Store {
        files: &'a [PathBuf],
        folder: &'a Path,
        disk_budget: Option<u64>,
        cut_options: CutOptions,
    },
    /// A COPC file here, read node by node from its own hierarchy.
    Copc {
        file: &'a Path,
        cut_options: CutOptions,
    },
    /// Levels of detail opened already: a store built, a COPC file by URL, served records.
    Levels {
        levels: Levels,
        cut_options: CutOptions,
    },
    /// A preview's points, drawn resident.
    Preview(Box<PreviewPoints>),
}

/// A dataset's points ready to render, and the renderer that draws them.
pub struct FrameSource {
    renderer: Renderer,
    coloring: Coloring,
    filter: PointFilter,
    /// Where the points lie: what the automatic camera frames, and what explicit cameras'
    /// clip planes enclose.
    extent: Extent,
    points: Points,
    /// How the source was opened, until the first frame reports it.
    unreported: Option<Opened>,
    /// The gain after Eye-Dome Lighting held for the frames of the view it renders.
    exposure: exposure::HeldExposure,
}

impl FrameSource {
    /// The source `opening` names, colored and filtered as `options` ask; what happens on the
    /// way goes to `events`.
    pub fn open(
        renderer: Renderer,
        opening: Opening<'_>,
        options: &RenderOptions,
        events: &dyn Fn(SourceEvent<'_>),
    ) -> Result<Self, SourceError> {
        let (levels, cut_options) = match opening {
            Opening::Resident { files, cache } => {
                return Self::resident(renderer, files, cache, options, events);
            }
            Opening::Preview(points) => return Self::preview(renderer, *points, options, events),
            Opening::Store {
                files,
                folder,
                disk_budget,
                cut_options,
            } => {
                let memory_budget = cut_options.memory_budget_bytes;
                let store =
                    LocalStore::open_or_build(files, folder, memory_budget, disk_budget, events)?;
                (Levels::Store(Box::new(store)), cut_options)
            }
            Opening::Copc { file, cut_options } => {
                (Levels::Copc(Box::new(open_copc(file)?)), cut_options)
            }
            Opening::Levels {
                levels,
                cut_options,
            } => (levels, cut_options),
        };
        Self::levels(renderer, levels, cut_options, options, events)
    }

    /// The dataset of `files` read whole (from `cache`, under its content hash, when there is
    /// one), colored, filtered and uploaded.
    pub fn resident(
        renderer: Renderer,
        files: &[PathBuf],
        cache: Option<(&DatasetCache, &str)>,
        options: &RenderOptions,
        events: &dyn Fn(SourceEvent<'_>),
    ) -> Result<Self, SourceError> {
        let started = Instant::now();
        events(SourceEvent::Reading { files });
        let (cloud, outcome) = match cache {
            Some((cache, sha256)) => {
                let (cloud, outcome) = cache.load(sha256, files)?;
                (cloud, Some(outcome))
            }
            None => (load_dataset(files)?, None),
        };
        let load_ms = started.elapsed().as_secs_f64() * 1e3;
        events(SourceEvent::Read {
            points: cloud.len(),
            files: files.len(),
            colors: cloud.color_source.describe(),
            ms: load_ms,
            cache: outcome,
        });
        let mut source = Self::of_cloud(renderer, cloud, options, None, events)?;
        source.unreported = Some(Opened {
            load_ms: Some(load_ms),
            cache: outcome,
            build_ms: None,
        });
        Ok(source)
    }

    /// A preview of `points`, resident, framed by the dataset files' header bounds: its few
    /// points cannot say where the dataset's lie, so it frames the box its store's frames lie
    /// in, seen from where they are; each frame says how complete it is.
    pub fn preview(
        renderer: Renderer,
        points: PreviewPoints,
        options: &RenderOptions,
        events: &dyn Fn(SourceEvent<'_>),
    ) -> Result<Self, SourceError> {
        let started = Instant::now();
        events(SourceEvent::Preview {
            points: points.cloud.len(),
            points_in_files: points.points_in_files,
            stored_nodes: points.stored_nodes,
            stored_points: points.stored_points,
            colors: points.cloud.color_source.describe(),
        });
        let framed = options.filter.framing_bounds(&points.files_bounds)?;
        let mut source = Self::of_cloud(renderer, points.cloud, options, Some(framed), events)?;
        if let Points::Resident { preview_of, .. } = &mut source.points {
            *preview_of = Some(points.points_in_files);
        }
        source.unreported = Some(Opened {
            load_ms: Some(started.elapsed().as_secs_f64() * 1e3),
            ..Opened::default()
        });
        Ok(source)
    }

    /// `cloud` colored, filtered and uploaded; framed by the robust box of its points unless
    /// `framed` gives the box to frame.
    fn of_cloud(
        renderer: Renderer,
        mut cloud: PointCloud,
        options: &RenderOptions,
        framed: Option<WorldBounds>,
        events: &dyn Fn(SourceEvent<'_>),
    ) -> Result<Self, SourceError> {
        let coloring = options.coloring();
        cloud.colors = point_colors(&cloud, coloring);
        let ramp_range = ramp_range(&cloud, coloring);
        let points = cloud.len();
        // Framed by the points a clip box keeps, all of them else: a render filtered by class
        // or return lines up with the whole one.
        let clip = PointFilter {
            clip: options.filter.clip,
            ..PointFilter::default()
        };
        clip.apply(&mut cloud)?;
        let extent = match framed {
            Some(bounds) => Extent::whole(bounds),
            None => {
                let sample = crate::spacing::sample_of(&cloud.positions);
                Extent::of_points(cloud.bounds, cloud.origin, &sample, &cloud.positions)
            }
        };
        let kept = options.filter.apply(&mut cloud)?;
        if !options.filter.keeps_everything() || kept == 0 {
            events(SourceEvent::Filtered { kept, points });
        }
        let cloud_on_gpu = renderer.upload(&cloud)?;
        // The spacing of the points drawn sizes them.
        let sample = crate::spacing::sample_of(&cloud.positions);
        let spacing = crate::spacing::of_sample(&sample, cloud.len() as u64);
        Ok(Self {
            renderer,
            coloring,
            filter: options.filter,
            extent,
            points: Points::Resident {
                cloud: cloud_on_gpu,
                spacing,
                ramp_range,
                preview_of: None,
            },
            unreported: None,
            exposure: Default::default(),
        })
    }

    /// The store of `files` in `folder` (built first when there is none, or opened without
    /// `files` when it is built), rendered cut by cut.
    pub fn local_store(
        renderer: Renderer,
        files: &[PathBuf],
        folder: &Path,
        disk_budget: Option<u64>,
        cut_options: CutOptions,
        options: &RenderOptions,
        events: &dyn Fn(SourceEvent<'_>),
    ) -> Result<Self, SourceError> {
        let opening = Opening::Store {
            files,
            folder,
            disk_budget,
            cut_options,
        };
        Self::open(renderer, opening, options, events)
    }

    /// A COPC file rendered cut by cut from its own hierarchy: no store is built, only the
    /// nodes a frame's cut needs are read from the file.
    pub fn copc(
        renderer: Renderer,
        file: &Path,
        cut_options: CutOptions,
        options: &RenderOptions,
        events: &dyn Fn(SourceEvent<'_>),
    ) -> Result<Self, SourceError> {
        let opening = Opening::Copc { file, cut_options };
        Self::open(renderer, opening, options, events)
    }

    /// `levels` rendered cut by cut with `cut_options`, colored and filtered as `options`
    /// ask.
    pub fn levels(
        renderer: Renderer,
        levels: Levels,
        cut_options: CutOptions,
        options: &RenderOptions,
        events: &dyn Fn(SourceEvent<'_>),
    ) -> Result<Self, SourceError> {
        let dataset = levels.dataset();
        let unclipped = coarse_extent(dataset)?;
        let extent = unclipped.clipped(&options.filter)?;
        let cut = CutRenderer::new(&renderer, dataset, cut_options)?;
        let budgets = cut.budgets();
        let from = match &levels {
            Levels::Store(store) => LevelsFrom::Store {
                folder: store.folder(),
                files: store.file_count(),
            },
            Levels::Copc(copc) => LevelsFrom::Copc {
                nodes: copc.nodes,
                pages: copc.pages,
                unread_pages: copc.unread_pages,
                sample_nodes: copc.sample_nodes,
            },
            Levels::Served { .. } => LevelsFrom::Served,
        };
        events(SourceEvent::Levels {
            points: dataset.point_count(),
            from,
            host_cache_bytes: budgets.host_bytes,
            gpu_cache_bytes: budgets.gpu_bytes,
            lod_error: cut_options.lod_error,
        });
        let build_ms = match &levels {
            Levels::Store(store) => store.stored.built.as_ref().map(|(_, s)| s * 1e3),
            Levels::Copc(_) => None,
            Levels::Served { build_ms, .. } => *build_ms,
        };
        Ok(Self {
            renderer,
            coloring: options.coloring(),
            filter: options.filter,
            extent,
            points: Points::Cut {
                cut: Box::new(cut),
                levels,
                unclipped,
                lod_error: cut_options.lod_error,
                preview: false,
            },
            unreported: build_ms.map(|ms| Opened {
                build_ms: Some(ms),
                ..Opened::default()
            }),
            exposure: Default::default(),
        })
    }

    /// Draws the cuts that follow at [`PREVIEW_LOD_ERROR_PX`] (a preview, when that is
    /// coarser than the final frames' error) or at the final frames' error, with the nodes
    /// cached so far. Returns whether the frames are now previews; a resident source's are
    /// what they are.
    pub fn preview_cuts(&mut self, on: bool) -> Result<bool, SourceError> {
        match &mut self.points {
            Points::Resident { preview_of, .. } => Ok(preview_of.is_some()),
            Points::Cut {
                cut,
                lod_error,
                preview,
                ..
            } => {
                let coarser = on && *lod_error < PREVIEW_LOD_ERROR_PX;
                if coarser != *preview {
                    cut.set_lod_error(if coarser {
                        PREVIEW_LOD_ERROR_PX
                    } else {
                        *lod_error
                    })?;
                    *preview = coarser;
                }
                Ok(coarser)
            }
        }
    }

    /// Takes `options`' colors, filter and pixel error for the frames that follow, when this
    /// source can draw them as a source opened anew would; otherwise `false`, and the caller
    /// opens one anew. A resident cloud was colored and filtered as it was uploaded; a cut
    /// colors and filters each node as it loads, and changes its pixel error in place.
    pub fn reuse_for(&mut self, options: &RenderOptions, lod_error: Option<f64>) -> bool {
        match &mut self.points {
            Points::Resident { .. } => {
                self.coloring == options.coloring() && self.filter == options.filter
            }
            Points::Cut {
                cut,
                unclipped,
                lod_error: current,
                preview,
                ..
            } => {
                let Ok(extent) = unclipped.clipped(&options.filter) else {
                    return false;
                };
                let wanted = lod_error.unwrap_or(*current);
                if wanted != *current {
                    let error = if *preview {
                        PREVIEW_LOD_ERROR_PX
                    } else {
                        wanted
                    };
                    if cut.set_lod_error(error).is_err() {
                        return false;
                    }
                    *current = wanted;
                }
                self.coloring = options.coloring();
                self.filter = options.filter;
                self.extent = extent;
                true
            }
        }
    }

    /// How this source's frames get their points.
    pub fn frame_points(&self) -> FramePoints {
        match &self.points {
            Points::Resident { .. } => FramePoints::Resident,
            Points::Cut {
                levels: Levels::Copc(_),
                ..
            } => FramePoints::CopcCut,
            Points::Cut { .. } => FramePoints::StoreCut,
        }
    }

    /// The final frames' pixel error, for cuts.
    pub fn lod_error(&self) -> Option<f64> {
        match &self.points {
            Points::Resident { .. } => None,
            Points::Cut { lod_error, .. } => Some(*lod_error),
        }
    }

    /// Whether the frames are previews: of a few of the dataset's points, or coarse cuts.
    pub fn is_preview(&self) -> bool {
        match &self.points {
            Points::Resident { preview_of, .. } => preview_of.is_some(),
            Points::Cut { preview, .. } => *preview,
        }
    }

    /// Where the points lie: the robust box the automatic camera frames, and the box of every
    /// point that explicit cameras' clip planes enclose.
    pub fn bounds(&self) -> Extent {
        self.extent.clone()
    }

    /// The typical distance between the points drawn, which sizes adaptive points: the
    /// filtered cloud's, or the levels of detail's original points'.
    pub fn spacing(&self) -> Option<f64> {
        match &self.points {
            Points::Resident { spacing, .. } => *spacing,
            Points::Cut { levels, .. } => levels.dataset().point_spacing(),
        }
    }

    /// The range elevation or intensity is drawn over (the request's, or the data's robust
    /// one); `None` for the other modes.
    pub fn ramp_range(&self) -> Option<ColorRange> {
        match &self.points {
            Points::Resident { ramp_range, .. } => *ramp_range,
            Points::Cut { levels, .. } => levels.dataset().ramp_range(self.coloring),
        }
    }

    pub fn renderer(&self) -> &Renderer {
        &self.renderer
    }

    /// The renderer, for the next source: its pipelines are made once.
    pub fn into_renderer(self) -> Renderer {
        self.renderer
    }

    /// The settings of `request`'s frame `index`, framed and sized for these points.
    pub fn frame_settings(&self, request: &RenderRequest, index: u32) -> FrameSettings {
        request.frame_settings(index, &self.extent, self.spacing())
    }

    /// Renders the frame of `settings`; a final frame shaded with Eye-Dome Lighting is
    /// exposed with the gain of the first this source rendered of its view (`exposure`).
    pub fn render(
        &mut self,
        settings: &FrameSettings,
        events: &dyn Fn(SourceEvent<'_>),
    ) -> Result<SourceFrame, SourceError> {
        let settings = self.with_held_exposure(settings);
        let rendered = self.draw(&settings, events)?;
        self.hold_exposure(&settings, &rendered);
        Ok(rendered)
    }

    /// Renders the frame of `settings` as they are. A store of this machine whose bytes fail
    /// their checks is built again (once) and the frame rendered from the new one.
    fn draw(
        &mut self,
        settings: &FrameSettings,
        events: &dyn Fn(SourceEvent<'_>),
    ) -> Result<SourceFrame, SourceError> {
        let opened = self.unreported.take();
        let renderer = &mut self.renderer;
        match &mut self.points {
            Points::Resident {
                cloud, preview_of, ..
            } => {
                let frame = renderer.render(cloud, settings)?;
                let points_total = preview_of.unwrap_or(cloud.len() as u64);
                let points_rendered = renderer.listed_points();
                Ok(SourceFrame {
                    frame,
                    points_total,
                    points_rendered,
                    preview: preview_of.map(|_| completeness(points_rendered, points_total)),
                    cut: None,
                    opened,
                })
            }
            Points::Cut {
                cut,
                levels,
                preview,
                ..
            } => {
                let (frame, report) = loop {
                    let rendered = cut.render(
                        renderer,
                        levels.dataset(),
                        settings,
                        self.coloring,
                        &self.filter,
                    );
                    let damage = match rendered {
                        Ok(rendered) => break rendered,
                        Err(error) if error.is_store_damage() => error,
                        Err(error) => return Err(error.into()),
                    };
                    let Levels::Store(store) = levels else {
                        return Err(damage.into());
                    };
                    store.rebuild_after(damage, events)?;
                    // The caches hold the old store's nodes: a new cut renderer starts empty.
                    **cut = CutRenderer::new(renderer, &store.stored.dataset, *cut.options())?;
                };
                let counts = &report.counts;
                Ok(SourceFrame {
                    frame,
                    points_total: counts.points_total,
                    points_rendered: counts.points_rendered,
                    preview: preview
                        .then(|| completeness(counts.points_rendered, counts.points_total)),
                    cut: Some(report),
                    opened,
                })
            }
        }
    }

    /// Starts loading the nodes of the frame of `settings` (the next one) while this one is
    /// written.
    pub fn read_ahead(&mut self, settings: &FrameSettings) {
        if let Points::Cut { cut, levels, .. } = &mut self.points {
            cut.read_ahead(levels.dataset(), settings, &self.filter);
        }
    }
}

/// Points of a level-of-detail dataset's coarsest nodes its robust box is taken from: an even
/// sample, as the spacing's is, small enough to read in milliseconds.
const EXTENT_SAMPLE_POINTS: u64 = 1 << 16;

/// The extent of `dataset`: its bounds, and the robust box of its coarsest nodes' points.
fn coarse_extent(dataset: &LodDataset) -> Result<Extent, SourceError> {
    let origin = dataset.origin();
    let mut sample = Vec::new();
    for_each_coarse_node_up_to(
        dataset.records().as_ref(),
        dataset.hierarchy(),
        EXTENT_SAMPLE_POINTS,
        |points| sample.extend(points.positions_relative_to(origin)),
    )
    .map_err(CutError::from)?;
    Ok(Extent::of_sample(dataset.bounds(), origin, &sample))
}

#[cfg(test)]
mod tests;

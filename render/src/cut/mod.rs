//! Rendering a level-of-detail store out of core: per frame a cut of its nodes, loaded through
//! a host and a GPU node cache, each bounded, then drawn by the same renderer as any cloud.
//!
//! A frame (Kanzok et al.'s out-of-core renderer on Scheiblauer's and Potree's octree of
//! original points):
//! 1. **select** (`select.rs`): the nodes in view whose parent's spacing on screen exceeds the
//!    pixel error, largest on screen first, as many as the GPU node cache holds;
//! 2. **load**: the cut's nodes the GPU cache lacks are taken from the host cache
//!    (`host_cache.rs`) or read from the store, in the cut's order (the load queue, by
//!    priority) a window at a time and by where they lie within it (`read_order.rs`), a wave
//!    at a time so the transient memory stays small (`load.rs`): the next wave's records
//!    read while this one's are decoded, and the one before prepared and uploaded;
//! 3. **upload**: each is colored for the frame's color mode with the dataset's ranges
//!    (`lod/colors.rs`), put in Morton order, batched and quantised as any cloud, and written into
//!    free batch slots of the GPU cache's pages (`gpu_cache.rs`), the least recently used nodes
//!    outside the cut evicted;
//! 4. **draw**: the pages' batch tables are set to the cut's batches, each with its point
//!    size where the size is adaptive (`point_sizes.rs`), and the renderer draws them with
//!    every mode it has.
//!
//! A frame renders only once its whole cut is resident, so the same request gives the same
//! image from a cold or a warm cache. `read_ahead` loads the next frame's nodes into the host
//! cache on another thread while the caller encodes this one.

mod dataset;
mod gpu_cache;
mod host_cache;
mod load;
mod options;
mod point_sizes;
mod read_order;
mod report;
mod select;
mod store_space;
mod stored;

#[cfg(test)]
mod tests;

use std::collections::HashSet;
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::Instant;

use rayon::prelude::*;
use thiserror::Error;

use crate::color::{ColorMode, Coloring};
use crate::filter::PointFilter;
use crate::lod::codec::Detail;
use crate::lod::{LodError, LodHierarchy, NodeKey, NodePoints, LOAD_WAVE_NODES};
use crate::raster::gpu_data::GpuBatch;
use crate::raster::morton::morton_order_of_cells;
use crate::raster::points::SegmentData;
use crate::raster::{Clock, Frame, FrameSettings, RenderError, Renderer, Stage, StageTiming};

// The dataset a cut reads lives in lod/; re-exported for the daemon, the CLI, the bench and the
// tests that name them from here.
pub use crate::lod::{LodDataset, ELEVATION_SAMPLE_POINTS};
pub use gpu_cache::SLOT_BYTES;
pub use host_cache::node_heap_bytes;
pub use options::{
    CacheBudgets, CutOptions, CutOptionsError, DEFAULT_GPU_BUDGET_BYTES, DEFAULT_LOD_ERROR_PX,
    DEFAULT_MEMORY_BUDGET_BYTES, MAX_CUT_POINTS_PER_PIXEL, MAX_LOD_ERROR_PX, MIN_BUDGET_BYTES,
    PREVIEW_LOD_ERROR_PX, RESIDENT_MAX_POINTS,
};
pub use report::{completeness, CutCounts, CutReport};
pub use select::{select_cut, Cut, CutNode, CutView};
pub use stored::{StoreBuild, StoredLod, PAYLOAD_FILE};

use dataset::Selected;
use gpu_cache::{GpuNodeCache, SizeFactors};
use host_cache::HostNodeCache;
use load::{fetch_at_details, fetch_wave, FrameDetails};
use point_sizes::CutPointSizes;
use read_order::in_read_order;
use select::NodesInView;

/// The most points of a page of the GPU node cache: few pages keep a frame's dispatches few,
/// small ones keep a small dataset's cache small.
const MAX_PAGE_POINTS: usize = 1 << 22;

#[derive(Debug, Error)]
pub enum CutError {
    #[error(transparent)]
    Options(#[from] CutOptionsError),
    #[error(transparent)]
    Ingest(#[from] crate::ingest::IngestError),
    #[error(transparent)]
    Store(#[from] LodError),
    #[error(transparent)]
    Render(#[from] RenderError),
    #[error("{0}")]
    Cache(String),
    #[error(
        "building the levels of detail of {points} points needs about {needed_mib} MiB of disk \
         in {folder}, {limit}"
    )]
    DiskTooSmall {
        points: u64,
        needed_mib: u64,
        folder: std::path::PathBuf,
        /// What is short: the free space, or the budget.
        limit: String,
    },
}

impl CutError {
    /// Whether a store's own bytes failed their checks ([`LodError::is_damage`]): the store
    /// is built again from its dataset's files, once.
    pub fn is_store_damage(&self) -> bool {
        matches!(self, Self::Store(error) if error.is_damage())
    }
}

/// The nodes a read-ahead is fetching, and the thread doing it.
struct ReadAhead {
    thread: JoinHandle<Result<u64, LodError>>,
}

/// Renders frames of one [`LodDataset`], keeping its nodes cached between them.
pub struct CutRenderer {
    options: CutOptions,
    budgets: CacheBudgets,
    host: Arc<Mutex<HostNodeCache>>,
    gpu_cache: GpuNodeCache,
    read_ahead: Option<ReadAhead>,
    /// Bytes read by a read-ahead, reported by the next frame.
    read_ahead_bytes: u64,
    /// How the last frame was colored: a read-ahead reads the next frame's nodes at the
    /// detail it will draw them at.
    last_coloring: Option<Coloring>,
}

impl CutRenderer {
    pub fn new(
        renderer: &Renderer,
        dataset: &LodDataset,
        options: CutOptions,
    ) -> Result<Self, CutError> {
        let cpu = renderer.gpu().adapter_info.device_type == wgpu::DeviceType::Cpu;
        let budgets = options.budgets(cpu)?;
        Ok(Self::with_budgets(renderer, dataset, options, budgets))
    }

    /// A renderer with budgets of any size (the tests' small ones below the minimum).
    pub(crate) fn with_budgets(
        renderer: &Renderer,
        dataset: &LodDataset,
        options: CutOptions,
        budgets: CacheBudgets,
    ) -> Self {
        Self {
            options,
            budgets,
            host: Arc::new(Mutex::new(HostNodeCache::new(budgets.host_bytes))),
            gpu_cache: GpuNodeCache::new(
                dataset.origin,
                budgets.gpu_bytes,
                renderer.max_segment_points().min(MAX_PAGE_POINTS),
            ),
            read_ahead: None,
            read_ahead_bytes: 0,
            last_coloring: None,
        }
    }

    pub fn options(&self) -> &CutOptions {
        &self.options
    }

    /// Draws the next frames at `lod_error` pixels (checked as [`CutOptions`] are), with the
    /// nodes cached so far: a COPC file's final frames after its previews.
    pub fn set_lod_error(&mut self, lod_error: f64) -> Result<(), CutError> {
        let options = CutOptions {
            lod_error,
            ..self.options
        };
        options.validate()?;
        self.options = options;
        Ok(())
    }

    pub fn budgets(&self) -> CacheBudgets {
        self.budgets
    }

    /// Whether high quality weighs each point by the original points it stands for (the
    /// default); without, every point counts once, as cuts drew it before points had weights
    /// (docs/perf/hq-band-on-cuts.md compares the two).
    pub fn set_weighted_high_quality(&mut self, weighted: bool) {
        self.gpu_cache.weighted = weighted;
    }

    /// Bytes of the GPU node cache's pages so far.
    pub fn gpu_bytes(&self) -> u64 {
        self.gpu_cache.gpu_bytes()
    }

    /// Bytes of the nodes in the host cache.
    pub fn host_bytes(&self) -> u64 {
        self.host.lock().map(|h| h.bytes()).unwrap_or(0)
    }

    /// The cut a frame of `settings` draws.
    pub fn cut(
        &self,
        dataset: &LodDataset,
        settings: &FrameSettings,
        filter: &PointFilter,
    ) -> Result<Cut, LodError> {
        dataset.select_cut(&self.cut_view(dataset, settings, filter))
    }

    /// What the selection of a frame of `settings` needs, in the supersampled frame's pixels.
    fn cut_view<'a>(
        &self,
        dataset: &LodDataset,
        settings: &'a FrameSettings,
        filter: &PointFilter,
    ) -> CutView<'a> {
        let k = settings.supersample.max(1);
        let (width, height) = (
            settings.width.saturating_mul(k),
            settings.height.saturating_mul(k),
        );
        let pixels = u64::from(width) * u64::from(height);
        CutView {
            camera: &settings.camera,
            origin: dataset.origin,
            width,
            height,
            point_size: settings.point_size.saturating_mul(k),
            lod_error: self.options.lod_error * f64::from(k),
            max_batches: self.gpu_cache.capacity_batches(),
            max_points: (self.options.lod_error > 0.0)
                .then(|| pixels.saturating_mul(MAX_CUT_POINTS_PER_PIXEL)),
            clip: filter.clip,
        }
    }

    /// The point sizes of the cut of a frame of `settings`: with an adaptive size, each batch
    /// sized by the spacing of the deepest nodes drawn where it lies (`point_sizes.rs`).
    fn point_sizes<'a>(
        &self,
        dataset: &LodDataset,
        hierarchy: &'a LodHierarchy,
        settings: &FrameSettings,
        filter: &PointFilter,
        cut: &Cut,
    ) -> Option<CutPointSizes<'a>> {
        let scale = settings.adaptive_size?;
        let reference = dataset.point_spacing?;
        let view = self.cut_view(dataset, settings, filter);
        // In the frame's own pixels: the renderer scales the sizes for supersampling.
        let transform = settings
            .camera
            .transform(dataset.origin, settings.width, settings.height);
        Some(CutPointSizes::new(
            hierarchy,
            cut,
            NodesInView::new(hierarchy, &view, &transform),
            &transform,
            dataset.origin,
            reference,
            scale,
        ))
    }

    /// A frame in the points' own colors, every point kept: the frame cuts are measured and
    /// compared by.
    pub fn render_rgb(
        &mut self,
        renderer: &mut Renderer,
        dataset: &LodDataset,
        settings: &FrameSettings,
    ) -> Result<(Frame, CutReport), CutError> {
        let every_point = PointFilter::default();
        self.render(renderer, dataset, settings, ColorMode::Rgb, &every_point)
    }

    /// Renders one frame: its cut made resident, its points colored in `color_mode` and
    /// passed through `filter`, then drawn.
    pub fn render(
        &mut self,
        renderer: &mut Renderer,
        dataset: &LodDataset,
        settings: &FrameSettings,
        coloring: impl Into<Coloring>,
        filter: &PointFilter,
    ) -> Result<(Frame, CutReport), CutError> {
        let coloring = coloring.into();
        renderer.validate(settings)?;
        let started = Instant::now();
        let Selected {
            cut,
            hierarchy,
            pages_read,
        } = dataset.select(&self.cut_view(dataset, settings, filter))?;
        let select_ms = ms_since(started);
        let mut report = CutReport::of_cut(&cut, dataset.point_count());
        report.select_ms = select_ms;
        report.hierarchy_pages_read = pages_read.pages;
        report.hierarchy_page_bytes = pages_read.bytes;

        let started = Instant::now();
        if let Some(ahead) = self.read_ahead.take() {
            match ahead.thread.join() {
                Ok(Ok(bytes)) => self.read_ahead_bytes += bytes,
                // A failed read-ahead only loses time: the frame reads what it needs itself
                // and reports a damaged node from there.
                Ok(Err(error)) => tracing::debug!(%error, "read-ahead stopped"),
                Err(_) => tracing::warn!("read-ahead thread panicked"),
            }
        }
        report.counts.read_ahead_bytes = std::mem::take(&mut self.read_ahead_bytes);
        report.wait_ms = ms_since(started);

        self.gpu_cache.prepare_for(coloring, *filter);
        let keys: Vec<NodeKey> = cut.nodes.iter().map(|n| n.key).collect();
        let keep: HashSet<NodeKey> = keys.iter().copied().collect();
        let details = FrameDetails::new(&self.options, dataset, coloring, filter);
        self.last_coloring = Some(coloring);
        let missing: Vec<&CutNode> = cut
            .nodes
            .iter()
            .filter(|n| !self.gpu_cache.touch(n.key, details.of(n)))
            .collect();
        report.counts.gpu_hits = (cut.nodes.len() - missing.len()) as u64;
        let missing = in_read_order(missing, &hierarchy);
        let mut upload_ms = 0.0;
        let host = &self.host;
        let gpu_cache = &mut self.gpu_cache;
        std::thread::scope(|scope| -> Result<(), CutError> {
            // Four stages run at once, a wave apart: one thread reads waves' records,
            // another decodes them (on all cores), a third prepares them (on all cores), and
            // this one uploads, so the disk or the daemon, the cores and the transfers overlap
            // (docs/perf/cold-first-frame.md, docs/perf/prepare-pipeline.md,
            // docs/perf/fetch-decode-stages.md).
            let (fetched_sender, fetched_receiver) = std::sync::mpsc::sync_channel(1);
            let (read_sender, read_receiver) = std::sync::mpsc::sync_channel(1);
            let (prepared_sender, prepared_receiver) = std::sync::mpsc::sync_channel(1);
            let (missing, hierarchy, details) = (&missing, &hierarchy, &details);
            scope.spawn(move || {
                for wave in missing.chunks(LOAD_WAVE_NODES) {
                    let fetched = fetch_wave(host, dataset, hierarchy, details, wave);
                    let failed = fetched.is_err();
                    // A closed channel: a later stage stopped on an error.
                    if fetched_sender.send(fetched).is_err() || failed {
                        break;
                    }
                }
            });
            scope.spawn(move || {
                for fetched in fetched_receiver {
                    let loaded = fetched.and_then(|wave| wave.decode(host, dataset, hierarchy));
                    let failed = loaded.is_err();
                    if read_sender.send(loaded).is_err() || failed {
                        break;
                    }
                }
            });
            scope.spawn(move || {
                for loaded in read_receiver {
                    let prepared = loaded.map(|wave| {
                        let started = Instant::now();
                        let data: Vec<SegmentData> = wave
                            .nodes
                            .par_iter()
                            .zip(&wave.details)
                            .map(|(node, &detail)| prepare(dataset, node, detail, coloring, filter))
                            .collect();
                        (wave, data, ms_since(started))
                    });
                    let failed = prepared.is_err();
                    if prepared_sender.send(prepared).is_err() || failed {
                        break;
                    }
                }
            });
            loop {
                let started = Instant::now();
                let Ok(prepared) = prepared_receiver.recv() else {
                    return Ok(());
                };
                report.load_ms += ms_since(started);
                let (loaded, prepared, prepare_ms) = prepared?;
                report.counts.host_hits += loaded.host_hits;
                report.counts.nodes_read += loaded.nodes_read;
                report.counts.bytes_read += loaded.bytes_read;
                report.prepare_ms += prepare_ms;

                let started = Instant::now();
                for ((node, &detail), data) in
                    loaded.nodes.iter().zip(&loaded.details).zip(&prepared)
                {
                    report.counts.gpu_evicted += gpu_cache
                        .insert(renderer.gpu(), node.key, detail, data, &keep)
                        .map_err(CutError::Cache)?;
                    report.counts.gpu_uploaded += 1;
                }
                upload_ms += ms_since(started);
            }
        })?;
        let mut sizes = self.point_sizes(dataset, &hierarchy, settings, filter, &cut);
        let mut size_factor = sizes
            .as_mut()
            .map(|sizes| move |key: NodeKey, batch: &GpuBatch| sizes.factor(key, batch));
        let cloud = self.gpu_cache.frame_cloud(
            renderer.gpu(),
            &keys,
            upload_ms,
            size_factor.as_mut().map(|f| f as SizeFactors<'_>),
        );
        let settings = &FrameSettings {
            point_size: sizes.map_or(settings.point_size, |s| s.largest_side()),
            ..*settings
        };
        // What the filter kept of the cut's points.
        report.counts.points_rendered = cloud.len() as u64;
        let mut frame = renderer.render(cloud, settings)?;
        // Preparing overlapped the waits and the uploads: the waits are what it did not hide.
        let load_ms = report.wait_ms + report.load_ms;
        let mut stages = vec![
            StageTiming {
                stage: Stage::Select,
                ms: report.select_ms,
                clock: Clock::Host,
            },
            StageTiming {
                stage: Stage::Load,
                ms: load_ms,
                clock: Clock::Host,
            },
        ];
        stages.append(&mut frame.timings.stages);
        frame.timings.stages = stages;
        report.host_cache_bytes = self.host_bytes();
        report.gpu_cache_bytes = self.gpu_cache.gpu_bytes();
        Ok((frame, report))
    }

    /// Starts reading the nodes of the frame of `settings` that neither cache holds into the
    /// host cache, on another thread, largest on screen first, up to half the host cache. The
    /// next [`CutRenderer::render`] waits for it.
    pub fn read_ahead(
        &mut self,
        dataset: &LodDataset,
        settings: &FrameSettings,
        filter: &PointFilter,
    ) {
        if self.read_ahead.is_some() {
            return;
        }
        let view = self.cut_view(dataset, settings, filter);
        let Selected { cut, hierarchy, .. } = match dataset.select(&view) {
            Ok(selected) => selected,
            // The frame selects again and reports the error.
            Err(error) => {
                tracing::debug!(%error, "no read-ahead");
                return;
            }
        };
        let Ok(host) = self.host.lock() else {
            return;
        };
        // Up to half the cache: older nodes make way (least recently used first), and the
        // frame being finished keeps the other half.
        let mut room = host.capacity_bytes() / 2;
        let mut wanted = Vec::new();
        // The next frame of a job colors as this one did.
        let details = match self.last_coloring {
            Some(coloring) => FrameDetails::new(&self.options, dataset, coloring, filter),
            None => FrameDetails::FULL,
        };
        for node in &cut.nodes {
            let detail = details.of(node);
            if self.gpu_cache.contains(node.key, detail) || host.contains(node.key, detail) {
                continue;
            }
            let bytes = 128 + u64::from(node.points) * 24;
            if bytes > room {
                break;
            }
            room -= bytes;
            wanted.push(*node);
        }
        drop(host);
        if wanted.is_empty() {
            return;
        }
        let wanted = in_read_order(wanted, &hierarchy);
        let records = Arc::clone(&dataset.records);
        let host = Arc::clone(&self.host);
        let thread = std::thread::Builder::new()
            .name("pointfarm-read-ahead".into())
            .spawn(move || {
                let mut bytes = 0;
                for wave in wanted.chunks(LOAD_WAVE_NODES) {
                    let wave: Vec<&CutNode> = wave.iter().collect();
                    let fetched = fetch_at_details(records.as_ref(), &hierarchy, &details, &wave)?;
                    bytes += fetched.bytes_read();
                    let read = fetched.decode(records.as_ref(), &hierarchy)?;
                    if let Ok(mut host) = host.lock() {
                        for node in read {
                            host.insert(Arc::new(node));
                        }
                    }
                }
                Ok(bytes)
            });
        match thread {
            Ok(thread) => self.read_ahead = Some(ReadAhead { thread }),
            Err(error) => tracing::debug!(%error, "no read-ahead thread"),
        }
    }
}

/// A node's points as the renderer takes them: relative to the origin, colored, those that
/// pass `filter` in Morton order over the node's own grid, batched and quantised, with their
/// weight bits. Each attribute is computed once, straight into that order.
fn prepare(
    dataset: &LodDataset,
    node: &NodePoints,
    detail: Detail,
    coloring: Coloring,
    filter: &PointFilter,
) -> SegmentData {
    // A node drawn coarse is drawn from its coarse positions even where it was read whole, so
    // the frame is the same whatever the caches held.
    let coarsened;
    let node = match (detail, node.detail) {
        (Detail::Coarse, Detail::Full) => {
            coarsened = node.coarsened();
            &coarsened
        }
        _ => node,
    };
    let kept = filter.node_points(node);
    let order = morton_order_of_cells(
        &node.quantised,
        crate::lod::codec::POSITION_BITS,
        kept.as_deref(),
    );
    let positions = node.positions_at(dataset.origin, order.iter().copied());
    // Only elevation colors by height: the other modes skip the pass.
    let heights: Vec<f32> = match coloring.mode {
        ColorMode::Elevation => node
            .positions_relative_to(dataset.origin)
            .iter()
            .map(|p| p.z)
            .collect(),
        _ => Vec::new(),
    };
    let colors = dataset.coloring.colors(node, &heights, coloring);
    let mut data = SegmentData::new(&positions, order.iter().map(|&i| colors[i as usize]));
    data.weights = weight_bits(node, &order);
    data.weights
        .resize(data.weights.len().next_multiple_of(2), 0);
    data
}

/// Each point's 16 weight bits on the GPU: its weight's code (1 where the node has none) and,
/// above it, its child octant in the node, from the top bit of its 30-bit coordinates (a
/// store's nodes are quantised in their own cube, a COPC node's in its cube widened by half
/// its side on every face: in both the top bit is set from the node's centre on); those of the
/// points at `indices`, in that order.
fn weight_bits(node: &NodePoints, indices: &[u32]) -> Vec<u16> {
    let top = crate::lod::codec::POSITION_BITS - 1;
    indices
        .iter()
        .map(|&i| {
            let (i, q) = (i as usize, node.quantised[i as usize]);
            let code = node.weights.get(i).copied().unwrap_or(1);
            let octant = (q[0] >> top) & 1 | ((q[1] >> top) & 1) << 1 | ((q[2] >> top) & 1) << 2;
            code | (octant as u16) << crate::lod::weights::WEIGHT_CODE_BITS
        })
        .collect()
}

fn ms_since(started: Instant) -> f64 {
    started.elapsed().as_secs_f64() * 1e3
}

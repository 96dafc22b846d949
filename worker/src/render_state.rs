//! A worker's render state and the rendering of one leased frame (`pointfarm worker`, also
//! as the daemon's embedded worker): the dataset's points opened as a
//! [`FrameSource`](pointfarm_render::source::FrameSource) — the same assembly `pointfarm
//! render` draws with here — from the files (through the worker's dataset cache), from a
//! store of the worker's own, from the daemon's store or COPC file read node by node, or from
//! the daemon's preview sample while it builds the store; kept across the frames of the
//! dataset, and each frame encoded with its stage timings. This module decides only what to
//! open from what the daemon answered, keeps each job's exposure (the gain the frame source
//! measures on the job's frame 0, so that every worker exposes a job's frames alike), maps
//! failures to attempts, and encodes.

use std::collections::VecDeque;
use std::path::PathBuf;
use std::sync::Arc;

use pointfarm_daemon::lease::{FrameOutcome, FrameTask, PublishedStore};
use pointfarm_daemon::model::StageTiming;
use pointfarm_render::cache::{CacheOutcome, DatasetCache};
use pointfarm_render::color::Coloring;
use pointfarm_render::cut::{CutError, CutOptions, LodDataset, StoredLod};
use pointfarm_render::encode;
use pointfarm_render::filter::PointFilter;
use pointfarm_render::gpu::GpuContext;
use pointfarm_render::ingest::dataset_point_count;
use pointfarm_render::raster::{Clock, Renderer};
use pointfarm_render::request::RenderRequest;
use pointfarm_render::source::{
    frame_points, FramePoints, FrameSource, Levels, PointSourceFacts, PreviewPoints, SourceError,
    SourceEvent, SourceFrame, StoreCache,
};

use crate::daemon_store::{PreviewSample, RemoteStore};
use crate::failure::FrameFailure;
use crate::opening_reads::OpeningReads;
use crate::published_store::{self, PublishedFailures};
use crate::url_dataset::UrlReader;

/// Where a frame's points come from.
pub enum DatasetAccess {
    /// The dataset's files: downloaded, or none when the worker has the points already (see
    /// [`WorkerRenderState::needs_files`]).
    Files(Vec<PathBuf>),
    /// The daemon's store of the dataset.
    DaemonStore(Box<RemoteStore>),
    /// The daemon's preview sample of the dataset, whose store it is building; none when the
    /// worker has it loaded (see [`WorkerRenderState::has_preview`]).
    Preview(Option<Box<PreviewSample>>),
    /// The COPC object of a dataset by URL, which the worker reads itself.
    Url,
    /// The daemon's store of the dataset as published to object storage, which the worker
    /// reads itself.
    Published,
}

/// A finished frame: the PNG and what to report with it.
pub struct RenderedFrame {
    pub png: Vec<u8>,
    pub outcome: FrameOutcome,
}

/// Where a worker keeps level-of-detail stores, and the budgets of its node caches.
#[derive(Debug, Clone)]
pub struct LodConfig {
    /// One folder per dataset, named by its content hash, within the worker's cache bound:
    /// before a build, the least recently used ones are removed until it fits; a dataset
    /// whose build alone needs more is refused before it starts.
    pub stores: StoreCache,
    /// The pixel error and node-cache budgets; a request's own pixel error wins.
    pub options: CutOptions,
}

/// What the worker has open of its current dataset.
struct Loaded {
    sha256: String,
    source: FrameSource,
    /// What the points were colored and filtered for (a resident cloud keeps them).
    coloring: Coloring,
    filter: PointFilter,
    /// Where a cut's nodes are read from: the daemon (its store or COPC file), or a store of
    /// this worker's.
    from: Opened,
}

/// How the current dataset was opened.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Opened {
    /// From its files or the dataset cache, resident.
    Files,
    /// A store of this worker's.
    OwnStore,
    /// The daemon's store (`copc`: its COPC file's hierarchy), read node by node.
    DaemonStore { copc: bool },
    /// The daemon's preview sample, of this version.
    Preview { version: u32 },
    /// The COPC object of a dataset by URL, read node by node by this worker.
    Url,
    /// The daemon's store as published to object storage, read node by node by this worker.
    Published,
}

/// One worker's renderer, dataset cache and open dataset, which render its leased frames.
pub struct WorkerRenderState {
    gpu: Arc<GpuContext>,
    /// The renderer while no dataset is open (an open one's source holds it).
    idle_renderer: Option<Renderer>,
    cache: Option<Arc<DatasetCache>>,
    lod: Option<LodConfig>,
    loaded: Option<Loaded>,
    gains: JobGains,
    urls: UrlReader,
    published_failures: PublishedFailures,
    /// What the open daemon's store read as it opened, until its first frame is drawn.
    opening_reads: Option<Arc<OpeningReads>>,
}

/// The jobs a gain after Eye-Dome Lighting is kept for: enough for the jobs a worker's leases
/// interleave, each a few hundred bytes.
const KEPT_JOB_GAINS: usize = 64;

/// What a job's gain was measured for: the job, its dataset and request, and how the points
/// were drawn. A gain is reused only for frames rendered from the same.
#[derive(Debug, Clone, PartialEq)]
struct JobExposureKey {
    job_id: String,
    sha256: String,
    request: RenderRequest,
    points: FramePoints,
    lod_error: Option<f64>,
}

/// The gains of the jobs this worker rendered final frames of, newest last: each job's is
/// measured once, on its frame 0, however its leases come.
#[derive(Debug, Default)]
struct JobGains(VecDeque<(JobExposureKey, f32)>);

impl JobGains {
    fn get(&self, key: &JobExposureKey) -> Option<f32> {
        self.0.iter().find(|(k, _)| k == key).map(|&(_, gain)| gain)
    }

    fn keep(&mut self, key: JobExposureKey, gain: f32) {
        self.0.retain(|(k, _)| *k != key);
        if self.0.len() == KEPT_JOB_GAINS {
            self.0.pop_front();
        }
        self.0.push_back((key, gain));
    }
}

impl WorkerRenderState {
    /// Without a cache every new dataset is decoded from its file; without a level-of-detail
    /// folder every dataset is rendered resident.
    pub fn new(
        gpu: Arc<GpuContext>,
        cache: Option<Arc<DatasetCache>>,
        lod: Option<LodConfig>,
    ) -> Self {
        Self {
            idle_renderer: Some(Renderer::new(Arc::clone(&gpu))),
            gpu,
            cache,
            lod,
            loaded: None,
            gains: JobGains::default(),
            urls: UrlReader::default(),
            published_failures: PublishedFailures::default(),
            opening_reads: None,
        }
    }

    /// Datasets by URL read through `urls` (with its range cache).
    pub fn with_url_reader(mut self, urls: UrlReader) -> Self {
        self.urls = urls;
        self
    }

    fn store_folder(&self, task: &FrameTask) -> Option<PathBuf> {
        let lod = self.lod.as_ref()?;
        Some(lod.stores.folder_of_dataset(&task.dataset.sha256))
    }

    /// The pixel error of `task`'s cut through a store of this worker's own, or `None` to
    /// render it resident, as [`frame_points`] decides for a dataset of `points` (unknown:
    /// `None`): the request's own error, else the default.
    fn lod_error(&self, task: &FrameTask, points: Option<u64>) -> Option<f64> {
        let facts = PointSourceFacts {
            points,
            // This worker builds a store of a COPC file's points as of any other file's.
            one_copc_file: false,
            store_built: self
                .store_folder(task)
                .is_some_and(|folder| StoredLod::is_built(&folder)),
            levels_of_detail_asked: task.request.render.lod_error.is_some(),
        };
        frame_points(&facts)
            .is_cut()
            .then(|| self.daemon_lod_error(task))
            .flatten()
    }

    /// The pixel error of `task`'s cuts: the request's own, else the worker's default; `None`
    /// when the worker renders no levels of detail.
    fn daemon_lod_error(&self, task: &FrameTask) -> Option<f64> {
        let lod = self.lod.as_ref()?;
        Some(
            task.request
                .render
                .lod_error
                .unwrap_or(lod.options.lod_error),
        )
    }

    /// Whether the dataset `task` renders is open as it needs it.
    pub fn is_loaded(&self, task: &FrameTask) -> bool {
        let Some(loaded) = &self.loaded else {
            return false;
        };
        if loaded.sha256 != task.dataset.sha256 {
            return false;
        }
        let render = &task.request.render;
        match loaded.from {
            Opened::Files => {
                loaded.coloring == render.coloring()
                    && loaded.filter == render.filter
                    && self.lod_error(task, None).is_none()
            }
            // A cut at another pixel error opens the store again, with empty node caches.
            Opened::OwnStore => self.lod_error(task, None) == loaded.source.lod_error(),
            Opened::DaemonStore { .. } | Opened::Url | Opened::Published => {
                self.daemon_lod_error(task) == loaded.source.lod_error()
            }
            // A preview is asked for again: the store may be ready by now.
            Opened::Preview { .. } => false,
        }
    }

    /// Whether `task`'s dataset is open resident from its files: the daemon is asked again
    /// whether it keeps a store, so that every worker draws a job's frames as the daemon
    /// decides, whatever this one had open before.
    pub fn is_loaded_resident(&self, task: &FrameTask) -> bool {
        self.is_loaded(task) && matches!(&self.loaded, Some(loaded) if loaded.from == Opened::Files)
    }

    /// Whether the preview sample of `task`'s dataset is open as `task` needs it: of its
    /// version or a later one.
    pub fn has_preview(&self, task: &FrameTask) -> bool {
        matches!(&self.loaded, Some(loaded)
            if loaded.sha256 == task.dataset.sha256
                && loaded.coloring == task.request.render.coloring()
                && loaded.filter == task.request.render.filter
                && matches!(loaded.from, Opened::Preview { version }
                    if version >= task.preview().unwrap_or(0)))
    }

    /// Whether rendering `task` reads the dataset's files: its points are neither open, nor
    /// in the cache, nor in a built store.
    pub fn needs_files(&self, task: &FrameTask) -> bool {
        if self.is_loaded(task) {
            return false;
        }
        if let Some(folder) = self.store_folder(task) {
            if StoredLod::is_built(&folder) && self.lod_error(task, None).is_some() {
                return false;
            }
        }
        task.request.render.lod_error.is_some()
            || !self
                .cache
                .as_ref()
                .is_some_and(|c| c.contains(&task.dataset.sha256))
    }

    /// Closes the open dataset (its memory is freed before the next one opens) and gives
    /// back the renderer.
    fn close(&mut self) -> Renderer {
        self.opening_reads = None;
        let from_source = self.loaded.take().map(|l| l.source.into_renderer());
        from_source
            .or_else(|| self.idle_renderer.take())
            .unwrap_or_else(|| Renderer::new(Arc::clone(&self.gpu)))
    }

    /// Opens `task`'s dataset with `open` (given the renderer), as `from`.
    fn open(
        &mut self,
        task: &FrameTask,
        from: Opened,
        open: impl FnOnce(Renderer) -> Result<FrameSource, SourceError>,
    ) -> Result<(), FrameFailure> {
        let renderer = self.close();
        let source = open(renderer)
            .map_err(|e| FrameFailure::from(&e).context(&format!("dataset {}", task.dataset.id)))?;
        tracing::info!(
            dataset = %task.dataset.id,
            daemon_store = matches!(from, Opened::DaemonStore { .. }),
            ?from,
            lod_error = source.lod_error(),
            "dataset open"
        );
        let render = &task.request.render;
        self.loaded = Some(Loaded {
            sha256: task.dataset.sha256.clone(),
            source,
            coloring: render.coloring(),
            filter: render.filter,
            from,
        });
        Ok(())
    }

    /// Renders the frame of `task`; `files` are the dataset's files, read only when
    /// [`needs_files`](Self::needs_files) says so. Errors are failures to report.
    pub fn render(
        &mut self,
        task: &FrameTask,
        access: DatasetAccess,
    ) -> Result<RenderedFrame, FrameFailure> {
        let url_reads = self.urls.counts();
        match access {
            DatasetAccess::Preview(Some(sample)) => self.open_preview(task, *sample)?,
            DatasetAccess::Preview(None) if self.has_preview(task) => {}
            DatasetAccess::Preview(None) => {
                return Err(FrameFailure::transient("no preview sample loaded"))
            }
            DatasetAccess::DaemonStore(store) => self.open_daemon_store(task, *store)?,
            DatasetAccess::Files(files) if !self.is_loaded(task) => {
                self.open_files(task, &files)?
            }
            DatasetAccess::Files(_) => {}
            DatasetAccess::Url if !self.is_loaded(task) => self.open_url(task)?,
            DatasetAccess::Url => {}
            DatasetAccess::Published if !self.is_loaded(task) => self.open_published(task)?,
            DatasetAccess::Published => {}
        }
        let wanted_lod_error = self.daemon_lod_error(task);
        let Some(loaded) = self.loaded.as_mut() else {
            return Err(FrameFailure::transient("no dataset loaded"));
        };
        let render = &task.request.render;
        if !loaded.source.reuse_for(render, wanted_lod_error) {
            return Err(FrameFailure::permanent(
                "the open dataset cannot draw this frame's options",
            ));
        }
        // A COPC file's preview is a coarse cut, its final frame the job's.
        let copc_preview =
            loaded.from == (Opened::DaemonStore { copc: true }) && task.preview().is_some();
        loaded
            .source
            .preview_cuts(copc_preview)
            .map_err(|e| FrameFailure::from(&e))?;
        let from = loaded.from;
        let exposure_key = JobExposureKey {
            job_id: task.lease.job_id.clone(),
            sha256: task.dataset.sha256.clone(),
            request: task.request.clone(),
            points: loaded.source.frame_points(),
            lod_error: loaded.source.lod_error(),
        };
        let result = loaded.source.render_job_frame(
            &task.request,
            task.lease.index,
            self.gains.get(&exposure_key),
            &log_event,
        );
        if let Some(opening) = self.opening_reads.take() {
            opening.forget();
        }
        let rendered = match result {
            Ok(rendered) => rendered,
            Err(error) => {
                if matches!(
                    error,
                    SourceError::Cut(CutError::Store(_)) | SourceError::DamagedAgain { .. }
                ) {
                    // The daemon's store is opened again by the next attempt; a store of this
                    // worker's that could not be built again was removed, and is built anew.
                    self.close_to_idle();
                }
                let failure = FrameFailure::from(&error);
                if from == Opened::Published
                    && matches!(error, SourceError::Cut(CutError::Store(_)))
                {
                    return Err(self.published_failures.failed(task, failure));
                }
                return Err(failure);
            }
        };
        if let (Some(gain), None) = (rendered.frame.gain, rendered.preview) {
            self.gains.keep(exposure_key, gain);
        }
        // The next frame of the job is likely this worker's next lease.
        if task.lease.index + 1 < task.request.frames() {
            let next = loaded
                .source
                .frame_settings(&task.request, task.lease.index + 1);
            loaded.source.read_ahead(&next);
        }
        let mut finished = finished(rendered)?;
        if let Some(cut) = &mut finished.outcome.cut {
            let now = self.urls.counts();
            cut.object_requests = now.requests - url_reads.requests;
            cut.object_bytes = now.fetched_bytes - url_reads.fetched_bytes;
            cut.range_cache_bytes = now.cached_bytes - url_reads.cached_bytes;
        }
        Ok(finished)
    }

    /// Closes the open dataset, keeping the renderer for the next.
    fn close_to_idle(&mut self) {
        let renderer = self.close();
        self.idle_renderer = Some(renderer);
    }

    /// Opens `task`'s dataset from `files` (none when a built store or the cache has it):
    /// a cut through a store of this worker's, or resident, as [`frame_points`] decides.
    fn open_files(&mut self, task: &FrameTask, files: &[PathBuf]) -> Result<(), FrameFailure> {
        let points = if files.is_empty() {
            None
        } else {
            let failure =
                |e| FrameFailure::from(&e).context(&format!("dataset {}", task.dataset.id));
            Some(dataset_point_count(files).map_err(failure)?)
        };
        let render = &task.request.render;
        let Some(lod_error) = self.lod_error(task, points) else {
            let cache = self.cache.clone();
            let sha256 = task.dataset.sha256.clone();
            return self.open(task, Opened::Files, |renderer| {
                let cache = cache.as_deref().map(|cache| (cache, sha256.as_str()));
                FrameSource::resident(renderer, files, cache, render, &log_event)
            });
        };
        let (Some(lod), Some(folder)) = (self.lod.clone(), self.store_folder(task)) else {
            return Err(FrameFailure::transient("this worker keeps no stores"));
        };
        let options = cut_options(&lod, lod_error)?;
        let opened = self.open(task, Opened::OwnStore, |renderer| {
            FrameSource::local_store(
                renderer,
                files,
                &folder,
                lod.stores.disk_budget,
                options,
                render,
                &log_event,
            )
        });
        if opened.is_err() && files.is_empty() {
            // Opened without its files and unusable: the next attempt downloads them and
            // builds it again.
            let _ = std::fs::remove_dir_all(&folder);
            return opened.map_err(|failure| FrameFailure::transient(failure.reason));
        }
        opened
    }

    /// Opens the daemon's store of `task`'s dataset, whose nodes are fetched as cuts need
    /// them.
    fn open_daemon_store(
        &mut self,
        task: &FrameTask,
        store: RemoteStore,
    ) -> Result<(), FrameFailure> {
        let (Some(lod), Some(lod_error)) = (self.lod.clone(), self.daemon_lod_error(task)) else {
            return Err(FrameFailure::transient(
                "this worker renders no levels of detail",
            ));
        };
        let options = cut_options(&lod, lod_error)?;
        let copc = store.copc.is_some();
        let mut opening = None;
        let dataset = match &store.copc {
            // The daemon read the coarsest nodes when it opened the file.
            Some(copc) => LodDataset::with_elevation(
                store.records,
                store.hierarchy,
                store.bounds,
                copc.elevation,
            )
            .with_point_spacing(copc.point_spacing),
            None => {
                // The opening's reads are kept for the first frame, which reads the same nodes.
                let kept = Arc::new(OpeningReads::new(store.records));
                opening = Some(Arc::clone(&kept));
                match store.elevation {
                    // The daemon read the coarsest nodes when it opened the store.
                    Some(elevation) => LodDataset::with_elevation(
                        kept,
                        store.hierarchy,
                        store.bounds,
                        Some(elevation),
                    ),
                    None => LodDataset::with_records(kept, store.hierarchy, store.bounds).map_err(
                        |e| {
                            FrameFailure::from(&CutError::Store(e))
                                .context(&format!("dataset {}", task.dataset.id))
                        },
                    )?,
                }
            }
        };
        let levels = Levels::Served {
            dataset: Box::new(dataset),
            build_ms: (store.build_ms > 0.0).then_some(store.build_ms),
        };
        let render = &task.request.render;
        self.open(task, Opened::DaemonStore { copc }, |renderer| {
            FrameSource::levels(renderer, levels, options, render, &log_event)
        })?;
        if let Some(opening) = &opening {
            opening.opened();
        }
        self.opening_reads = opening;
        Ok(())
    }

    /// Opens the COPC object of `task`'s dataset by URL, cut by cut as the daemon's COPC
    /// hierarchy is, with this worker's node caches.
    fn open_url(&mut self, task: &FrameTask) -> Result<(), FrameFailure> {
        let Some(remote) = &task.dataset.remote else {
            return Err(FrameFailure::permanent("the dataset has no URL"));
        };
        let (Some(lod), Some(lod_error)) = (self.lod.clone(), self.daemon_lod_error(task)) else {
            return Err(FrameFailure::transient(
                "this worker renders no levels of detail",
            ));
        };
        let options = cut_options(&lod, lod_error)?;
        let copc = self
            .urls
            .open(remote)
            .map_err(|e| e.context(&format!("dataset {}", task.dataset.id)))?;
        let render = &task.request.render;
        self.open(task, Opened::Url, |renderer| {
            FrameSource::levels(
                renderer,
                Levels::Copc(Box::new(copc)),
                options,
                render,
                &log_event,
            )
        })
    }

    /// The published store `task` names, unless it failed on this worker before: the
    /// dataset is then read through the daemon.
    pub fn published_store<'a>(&self, task: &'a FrameTask) -> Option<&'a PublishedStore> {
        self.published_failures.store_of(task)
    }

    /// Opens the daemon's store of `task`'s dataset as published to object storage, cut by
    /// cut as the daemon's own is.
    fn open_published(&mut self, task: &FrameTask) -> Result<(), FrameFailure> {
        let Some(published) = self.published_store(task).cloned() else {
            return Err(FrameFailure::transient(
                "the dataset's store is not published",
            ));
        };
        let (Some(lod), Some(lod_error)) = (self.lod.clone(), self.daemon_lod_error(task)) else {
            return Err(FrameFailure::transient(
                "this worker renders no levels of detail",
            ));
        };
        let options = cut_options(&lod, lod_error)?;
        let dataset = match published_store::open(&mut self.urls, &published) {
            Ok(dataset) => dataset,
            Err(failure) => return Err(self.published_failures.failed(task, failure)),
        };
        let levels = Levels::Served {
            dataset: Box::new(dataset),
            build_ms: None,
        };
        let render = &task.request.render;
        self.open(task, Opened::Published, |renderer| {
            FrameSource::levels(renderer, levels, options, render, &log_event)
        })
    }

    /// Opens the daemon's preview sample of `task`'s dataset: colored, filtered and framed
    /// as `render --preview` draws it here. A sample just fetched is the daemon's latest,
    /// drawn whatever its version (a restarted daemon's build counts again from 0).
    fn open_preview(
        &mut self,
        task: &FrameTask,
        sample: PreviewSample,
    ) -> Result<(), FrameFailure> {
        let version = sample.version;
        let points = PreviewPoints {
            cloud: sample.cloud,
            points_in_files: sample.points_in_files,
            files_bounds: sample.bounds,
            stored_nodes: 0,
            stored_points: 0,
        };
        let render = &task.request.render;
        self.open(task, Opened::Preview { version }, |renderer| {
            FrameSource::preview(renderer, points, render, &log_event)
        })
    }
}

/// The worker's cut options at `lod_error`, checked.
fn cut_options(lod: &LodConfig, lod_error: f64) -> Result<CutOptions, FrameFailure> {
    let options = CutOptions {
        lod_error,
        ..lod.options
    };
    options
        .validate()
        .map_err(|e| FrameFailure::permanent(e.to_string()))?;
    Ok(options)
}

/// A frame source's steps, in the worker's log.
fn log_event(event: SourceEvent<'_>) {
    match event {
        SourceEvent::Rebuilding { folder, damage } => {
            tracing::warn!(folder = %folder.display(), reason = %damage, "rebuilding a damaged store")
        }
        SourceEvent::Filtered { kept: 0, points } => {
            tracing::warn!(points, "the filter keeps none of the points")
        }
        event => tracing::info!(?event, "dataset"),
    }
}

/// A rendered frame encoded, with its timings and what to report of it.
fn finished(mut rendered: SourceFrame) -> Result<RenderedFrame, FrameFailure> {
    let frame = &mut rendered.frame;
    let png = encode::png_bytes(frame)
        .map_err(|e| FrameFailure::transient(format!("encoding the PNG: {e}")))?;
    let opened = rendered.opened.unwrap_or_default();
    let mut timings: Vec<StageTiming> = [("load", opened.load_ms), ("build", opened.build_ms)]
        .into_iter()
        .filter_map(|(name, ms)| ms.map(|ms| stage(name, ms)))
        .collect();
    timings.extend(frame.timings.stages.iter().map(|t| StageTiming {
        stage: t.stage.name().to_string(),
        ms: t.ms,
        gpu_clock: t.clock == Clock::Gpu,
    }));
    tracing::info!(
        total_ms = timings.iter().map(|t| t.ms).sum::<f64>(),
        preview = rendered.preview.is_some(),
        "frame rendered"
    );
    Ok(RenderedFrame {
        png,
        outcome: FrameOutcome {
            timings,
            dataset_cache_hit: opened.cache.map(|outcome| outcome == CacheOutcome::Hit),
            cut: rendered.cut.map(|report| report.counts),
            preview: rendered.preview,
        },
    })
}

fn stage(name: &str, ms: f64) -> StageTiming {
    StageTiming {
        stage: name.into(),
        ms,
        gpu_clock: false,
    }
}

//! A worker's render state and the rendering of one leased frame (`pointfarm worker`, also
//! as the daemon's embedded worker): load the dataset (through the worker's
//! `DatasetCache`), colour it, keep it resident on the GPU across frames, render with the
//! job's settings and encode the PNG, with the stage timings of every step. A preview job's
//! frame whose store the daemon is still building renders from the daemon's preview sample
//! instead, resident as `render --preview` renders it here, and says how complete it is; a
//! task asking for a later version of the sample than the one loaded replaces it. A preview
//! job's first frames of a COPC dataset, which has nothing to build, are its coarse cuts, as
//! `render --preview` draws them here.

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

use pointfarm_daemon::lease::{FrameOutcome, FrameTask};
use pointfarm_daemon::model::StageTiming;
use pointfarm_render::cache::{CacheOutcome, DatasetCache};
use pointfarm_render::cloud::WorldBounds;
use pointfarm_render::color::{point_colors, Coloring};
use pointfarm_render::cut::{
    completeness, CutError, CutOptions, CutRenderer, LodDataset, StoredLod, PREVIEW_LOD_ERROR_PX,
};
use pointfarm_render::encode;
use pointfarm_render::filter::PointFilter;
use pointfarm_render::gpu::GpuContext;
use pointfarm_render::ingest::dataset_point_count;
use pointfarm_render::raster::{Clock, GpuPointCloud, Renderer};
use pointfarm_render::source::{frame_points, PointSourceFacts};

use crate::daemon_store::{PreviewSample, RemoteStore};
use crate::failure::FrameFailure;

/// The cloud currently on the GPU.
struct Resident {
    sha256: String,
    coloring: Coloring,
    filter: PointFilter,
    bounds: WorldBounds,
    /// The typical distance between the filtered points, which sizes adaptive points.
    spacing: Option<f64>,
    cloud: GpuPointCloud,
    /// How the cloud was loaded, until the next finished frame reports it.
    unreported_load: Option<(f64, CacheOutcome)>,
}

/// A dataset's preview sample on the GPU, while the daemon builds its store.
struct Preview {
    sha256: String,
    coloring: Coloring,
    filter: PointFilter,
    /// The files' header bounds within the filter's box: what the store's frames frame.
    bounds: WorldBounds,
    spacing: Option<f64>,
    cloud: GpuPointCloud,
    /// The points of the dataset's files, of which the sample is a few.
    points_in_files: u64,
    /// The sample's version: the whole tenths of the points whose stored nodes it carries.
    version: u32,
}

/// A dataset rendered from its level-of-detail store, cut by cut.
struct Stored {
    sha256: String,
    source: StoreSource,
    cut: CutRenderer,
    /// The pixel error the renderer was made for.
    lod_error: f64,
    /// How long the store took to build, until the next finished frame reports it.
    unreported_build_ms: Option<f64>,
    /// Whether the store is a COPC file's own hierarchy, previewed from coarse cuts.
    copc: bool,
}

/// Where a store's nodes are read from.
enum StoreSource {
    /// A store of this worker's, built from the dataset's files.
    Local(Box<StoredLod>),
    /// The daemon's store, read node by node.
    Daemon(LodDataset),
}

impl StoreSource {
    fn dataset(&self) -> &LodDataset {
        match self {
            StoreSource::Local(stored) => &stored.dataset,
            StoreSource::Daemon(dataset) => dataset,
        }
    }
}

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
}

/// What the worker has loaded of its current dataset.
enum Loaded {
    Resident(Box<Resident>),
    Stored(Box<Stored>),
    Preview(Box<Preview>),
}

/// A finished frame: the PNG and what to report with it.
pub struct RenderedFrame {
    pub png: Vec<u8>,
    pub outcome: FrameOutcome,
}

/// Where a worker keeps level-of-detail stores, and the budgets of its node caches.
#[derive(Debug, Clone)]
pub struct LodConfig {
    /// One folder per dataset, named by its content hash.
    pub dir: PathBuf,
    /// The pixel error and node-cache budgets; a request's own pixel error wins.
    pub options: CutOptions,
    /// The most disk the stores in `dir` take together (the worker's cache bound): before a
    /// build, the least recently used ones are removed until it fits; a dataset whose build
    /// alone needs more is refused before it starts.
    pub disk_budget: Option<u64>,
}

/// One worker's renderer, dataset cache and loaded dataset, which render its leased frames.
pub struct WorkerRenderState {
    renderer: Renderer,
    cache: Option<Arc<DatasetCache>>,
    lod: Option<LodConfig>,
    loaded: Option<Loaded>,
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
            renderer: Renderer::new(gpu),
            cache,
            lod,
            loaded: None,
        }
    }

    fn store_folder(&self, task: &FrameTask) -> Option<PathBuf> {
        self.lod
            .as_ref()
            .map(|lod| lod.dir.join(&task.dataset.sha256))
    }

    /// The pixel error of `task`'s cut through a store of this worker's own, or `None` to
    /// render it resident, as [`frame_points`] decides for a dataset of `points` (unknown:
    /// `None`): the request's own error, else the default.
    fn lod_error(&self, task: &FrameTask, points: Option<u64>) -> Option<f64> {
        let lod = self.lod.as_ref()?;
        let facts = PointSourceFacts {
            points,
            // This worker builds a store of a COPC file's points as of any other file's.
            one_copc_file: false,
            store_built: self
                .store_folder(task)
                .is_some_and(|folder| StoredLod::is_built(&folder)),
            levels_of_detail_asked: task.request.render.lod_error.is_some(),
        };
        frame_points(&facts).is_cut().then(|| {
            task.request
                .render
                .lod_error
                .unwrap_or(lod.options.lod_error)
        })
    }

    /// The pixel error of `task`'s cut from the daemon's store: the request's own, else the
    /// default.
    fn daemon_lod_error(&self, task: &FrameTask) -> Option<f64> {
        let lod = self.lod.as_ref()?;
        Some(
            task.request
                .render
                .lod_error
                .unwrap_or(lod.options.lod_error),
        )
    }

    /// Whether the dataset `task` renders is loaded as it needs it.
    pub fn is_loaded(&self, task: &FrameTask) -> bool {
        match &self.loaded {
            Some(Loaded::Resident(r)) => {
                r.sha256 == task.dataset.sha256
                    && r.coloring == task.request.render.coloring()
                    && r.filter == task.request.render.filter
                    && self.lod_error(task, None).is_none()
            }
            Some(Loaded::Stored(s)) => {
                let wanted = match s.source {
                    StoreSource::Local(_) => self.lod_error(task, None),
                    StoreSource::Daemon(_) => self.daemon_lod_error(task),
                };
                s.sha256 == task.dataset.sha256 && wanted == Some(s.lod_error)
            }
            // A preview is asked for again: the store may be ready by now.
            Some(Loaded::Preview(_)) | None => false,
        }
    }

    /// Whether the preview sample of `task`'s dataset is loaded as `task` needs it: of its
    /// version or a later one.
    pub fn has_preview(&self, task: &FrameTask) -> bool {
        matches!(&self.loaded, Some(Loaded::Preview(p))
            if p.sha256 == task.dataset.sha256
                && p.coloring == task.request.render.coloring()
                && p.filter == task.request.render.filter
                && p.version >= task.preview().unwrap_or(0))
    }

    /// Whether rendering `task` reads the dataset's files: its points are neither loaded, nor
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

    /// Renders the frame of `task`; `files` are the dataset's files, read only when
    /// [`needs_files`](Self::needs_files) says so. Errors are failures to report.
    pub fn render(
        &mut self,
        task: &FrameTask,
        access: DatasetAccess,
    ) -> Result<RenderedFrame, FrameFailure> {
        let files = match access {
            DatasetAccess::Preview(sample) => return self.render_preview(task, sample),
            DatasetAccess::Files(files) => files,
            DatasetAccess::DaemonStore(store) => {
                self.loaded = None; // free the old dataset's memory first
                let stored = self.open_daemon_store(task, store)?;
                self.loaded = Some(Loaded::Stored(Box::new(stored)));
                Vec::new()
            }
        };
        let files = files.as_slice();
        if !self.is_loaded(task) {
            self.loaded = None; // free the old dataset's memory first
            let points = if files.is_empty() {
                None
            } else {
                let failure =
                    |e| FrameFailure::from(&e).context(&format!("dataset {}", task.dataset.id));
                Some(dataset_point_count(files).map_err(failure)?)
            };
            self.loaded = Some(match self.lod_error(task, points) {
                Some(lod_error) => {
                    Loaded::Stored(Box::new(self.open_store(task, files, lod_error)?))
                }
                None => Loaded::Resident(Box::new(self.load(task, files)?)),
            });
        }
        let (mut frame, timings, dataset_cache_hit, cut, preview) = match self.loaded.as_mut() {
            Some(Loaded::Resident(current)) => {
                let settings =
                    task.request
                        .frame_settings(task.lease.index, &current.bounds, current.spacing);
                let frame = self
                    .renderer
                    .render(&current.cloud, &settings)
                    .map_err(|e| FrameFailure::from(&e))?;
                let load = current.unreported_load.take();
                let timings = load
                    .map(|(ms, _)| stage("load", ms))
                    .into_iter()
                    .collect::<Vec<_>>();
                let hit = load.map(|(_, outcome)| outcome == CacheOutcome::Hit);
                (frame, timings, hit, None, None)
            }
            Some(Loaded::Stored(stored)) => {
                let dataset = stored.source.dataset();
                let filter = &task.request.render.filter;
                let bounds = filter
                    .framing_bounds(&dataset.bounds())
                    .map_err(|e| FrameFailure::permanent(e.to_string()))?;
                let spacing = dataset.point_spacing();
                let settings = task
                    .request
                    .frame_settings(task.lease.index, &bounds, spacing);
                let coloring = task.request.render.coloring();
                // A COPC file's preview is a coarse cut, its final frame the job's.
                let preview = stored.copc
                    && task.preview().is_some()
                    && stored.lod_error < PREVIEW_LOD_ERROR_PX;
                let lod_error = if preview {
                    PREVIEW_LOD_ERROR_PX
                } else {
                    stored.lod_error
                };
                stored
                    .cut
                    .set_lod_error(lod_error)
                    .map_err(|e| FrameFailure::from(&e))?;
                let rendered =
                    stored
                        .cut
                        .render(&mut self.renderer, dataset, &settings, coloring, filter);
                let (frame, report) = match rendered {
                    Ok(done) => done,
                    Err(error) => {
                        let failure = FrameFailure::from(&error);
                        let local_folder = match &stored.source {
                            StoreSource::Local(lod) => Some(lod.folder.clone()),
                            StoreSource::Daemon(_) => None,
                        };
                        if matches!(error, CutError::Store(_)) {
                            self.loaded = None;
                            // A damaged store of this worker's is built again by the next
                            // attempt; the daemon's is opened again.
                            if let Some(folder) = local_folder {
                                tracing::warn!(%error, folder = %folder.display(), "removing a damaged store");
                                let _ = std::fs::remove_dir_all(folder);
                            }
                        }
                        return Err(failure);
                    }
                };
                // The next frame of the job is likely this worker's next lease.
                if task.lease.index + 1 < task.request.frames() {
                    let next = task
                        .request
                        .frame_settings(task.lease.index + 1, &bounds, spacing);
                    stored
                        .cut
                        .read_ahead(stored.source.dataset(), &next, filter);
                }
                let timings = stored
                    .unreported_build_ms
                    .take()
                    .map(|ms| stage("build", ms))
                    .into_iter()
                    .collect::<Vec<_>>();
                let counts = &report.counts;
                let completeness =
                    preview.then(|| completeness(counts.points_rendered, counts.points_total));
                (frame, timings, None, Some(report.counts), completeness)
            }
            Some(Loaded::Preview(_)) | None => {
                return Err(FrameFailure::transient("no dataset loaded"))
            }
        };
        finished(&mut frame, timings, dataset_cache_hit, cut, preview)
    }

    /// Renders `task`'s frame from its dataset's preview sample: `sample` loaded first, or the
    /// one loaded already. Coloured, filtered and framed as `render --preview` does here.
    fn render_preview(
        &mut self,
        task: &FrameTask,
        sample: Option<Box<PreviewSample>>,
    ) -> Result<RenderedFrame, FrameFailure> {
        let mut timings = Vec::new();
        // A sample just fetched is the daemon's latest, drawn whatever its version (a
        // restarted daemon's build counts again from 0).
        let fetched = sample.is_some();
        if let Some(sample) = sample {
            self.loaded = None; // free the old dataset's memory first
            let started = Instant::now();
            let preview = self.load_preview(task, *sample)?;
            timings.push(stage("load", started.elapsed().as_secs_f64() * 1e3));
            self.loaded = Some(Loaded::Preview(Box::new(preview)));
        }
        let loaded = fetched || self.has_preview(task);
        let (true, Some(Loaded::Preview(preview))) = (loaded, self.loaded.as_ref()) else {
            return Err(FrameFailure::transient("no preview sample loaded"));
        };
        let settings =
            task.request
                .frame_settings(task.lease.index, &preview.bounds, preview.spacing);
        let mut frame = self
            .renderer
            .render(&preview.cloud, &settings)
            .map_err(|e| FrameFailure::from(&e))?;
        let drawn = self.renderer.listed_points();
        let completeness = completeness(drawn, preview.points_in_files);
        finished(&mut frame, timings, None, None, Some(completeness))
    }

    /// The preview sample coloured, filtered and uploaded.
    fn load_preview(
        &self,
        task: &FrameTask,
        sample: PreviewSample,
    ) -> Result<Preview, FrameFailure> {
        let dataset = &task.dataset;
        let in_dataset =
            |failure: FrameFailure| failure.context(&format!("dataset {}", dataset.id));
        let render = &task.request.render;
        let mut cloud = sample.cloud;
        cloud.colors = point_colors(&cloud, render.coloring());
        render
            .filter
            .apply(&mut cloud)
            .map_err(|e| in_dataset(FrameFailure::permanent(e.to_string())))?;
        let bounds = render
            .filter
            .framing_bounds(&sample.bounds)
            .map_err(|e| in_dataset(FrameFailure::permanent(e.to_string())))?;
        let gpu_cloud = self
            .renderer
            .upload(&cloud)
            .map_err(|e| in_dataset(FrameFailure::from(&e)))?;
        tracing::info!(dataset = %dataset.id, points = cloud.len(),
            points_in_files = sample.points_in_files, version = sample.version,
            "preview sample resident");
        Ok(Preview {
            sha256: dataset.sha256.clone(),
            coloring: render.coloring(),
            filter: render.filter,
            bounds,
            spacing: cloud.spacing(),
            cloud: gpu_cloud,
            points_in_files: sample.points_in_files,
            version: sample.version,
        })
    }

    /// Opens the dataset's store, building it from `files` first when it has none.
    fn open_store(
        &self,
        task: &FrameTask,
        files: &[PathBuf],
        lod_error: f64,
    ) -> Result<Stored, FrameFailure> {
        let dataset = &task.dataset;
        let in_dataset =
            |failure: FrameFailure| failure.context(&format!("dataset {}", dataset.id));
        let (Some(lod), Some(folder)) = (self.lod.as_ref(), self.store_folder(task)) else {
            return Err(FrameFailure::transient("this worker keeps no stores"));
        };
        let options = self.cut_options(lod_error)?;
        let started = Instant::now();
        let lod_store = StoredLod::open_or_build(
            files,
            &folder,
            options.memory_budget_bytes,
            lod.disk_budget,
            &mut |_| {},
        )
        .map_err(|e| {
            if files.is_empty() {
                // Opened without its files and unusable: the next attempt downloads them and
                // builds it again.
                let _ = std::fs::remove_dir_all(&folder);
                return in_dataset(FrameFailure::transient(e.to_string()));
            }
            in_dataset(FrameFailure::from(&e))
        })?;
        let build_ms = lod_store
            .built
            .as_ref()
            .map(|_| started.elapsed().as_secs_f64() * 1e3);
        self.stored(
            task,
            StoreSource::Local(Box::new(lod_store)),
            options,
            build_ms,
        )
    }

    /// Opens the daemon's store of `task`'s dataset, whose nodes are fetched as cuts need them.
    fn open_daemon_store(
        &self,
        task: &FrameTask,
        store: Box<RemoteStore>,
    ) -> Result<Stored, FrameFailure> {
        let store = *store;
        let lod_error = self
            .daemon_lod_error(task)
            .ok_or_else(|| FrameFailure::transient("this worker renders no levels of detail"))?;
        let options = self.cut_options(lod_error)?;
        let dataset = match &store.copc {
            // The daemon read the coarsest nodes when it opened the file.
            Some(copc) => LodDataset::with_elevation(
                store.records,
                store.hierarchy,
                store.bounds,
                copc.elevation,
            )
            .with_point_spacing(copc.point_spacing),
            None => LodDataset::with_records(store.records, store.hierarchy, store.bounds)
                .map_err(|e| {
                    FrameFailure::from(&CutError::Store(e))
                        .context(&format!("dataset {}", task.dataset.id))
                })?,
        };
        let build_ms = (store.build_ms > 0.0).then_some(store.build_ms);
        let copc = store.copc.is_some();
        let stored = self.stored(task, StoreSource::Daemon(dataset), options, build_ms)?;
        Ok(Stored { copc, ..stored })
    }

    /// The worker's cut options at `lod_error`, checked.
    fn cut_options(&self, lod_error: f64) -> Result<CutOptions, FrameFailure> {
        let lod = self
            .lod
            .as_ref()
            .ok_or_else(|| FrameFailure::transient("this worker renders no levels of detail"))?;
        let options = CutOptions {
            lod_error,
            ..lod.options
        };
        options
            .validate()
            .map_err(|e| FrameFailure::permanent(e.to_string()))?;
        Ok(options)
    }

    /// A store opened from `source`, ready to render cuts with `options`; `build_ms` is how
    /// long it took to build, when it was built for this opening.
    fn stored(
        &self,
        task: &FrameTask,
        source: StoreSource,
        options: CutOptions,
        build_ms: Option<f64>,
    ) -> Result<Stored, FrameFailure> {
        let dataset = &task.dataset;
        let cut = CutRenderer::new(&self.renderer, source.dataset(), options)
            .map_err(|e| FrameFailure::from(&e).context(&format!("dataset {}", dataset.id)))?;
        tracing::info!(
            dataset = %dataset.id,
            points = source.dataset().point_count(),
            lod_error = options.lod_error,
            built = build_ms.is_some(),
            daemon_store = matches!(source, StoreSource::Daemon(_)),
            "rendering from levels of detail"
        );
        Ok(Stored {
            sha256: dataset.sha256.clone(),
            source,
            cut,
            lod_error: options.lod_error,
            unreported_build_ms: build_ms,
            copc: false,
        })
    }

    /// Loads a dataset (from the cache when it has it), colours it and uploads it.
    fn load(&self, task: &FrameTask, files: &[PathBuf]) -> Result<Resident, FrameFailure> {
        let dataset = &task.dataset;
        let in_dataset =
            |failure: FrameFailure| failure.context(&format!("dataset {}", dataset.id));
        let started = Instant::now();
        let loaded = match &self.cache {
            Some(cache) => cache
                .load(&dataset.sha256, files)
                .map_err(|e| FrameFailure::from(&e)),
            None => pointfarm_render::ingest::load_dataset(files)
                .map(|cloud| (cloud, CacheOutcome::Miss))
                .map_err(|e| FrameFailure::from(&e)),
        };
        let (mut cloud, outcome) = loaded.map_err(in_dataset)?;
        let load_ms = started.elapsed().as_secs_f64() * 1e3;
        let render = &task.request.render;
        cloud.colors = point_colors(&cloud, render.coloring());
        let points = cloud.len();
        let kept = render
            .filter
            .apply(&mut cloud)
            .map_err(|e| in_dataset(FrameFailure::permanent(e.to_string())))?;
        if kept == 0 {
            tracing::warn!(dataset = %dataset.id, points, "the filter keeps none of the points");
        }
        let gpu_cloud = self
            .renderer
            .upload(&cloud)
            .map_err(|e| in_dataset(FrameFailure::from(&e)))?;
        tracing::info!(dataset = %dataset.id, points = cloud.len(), load_ms, ?outcome, "cloud resident");
        Ok(Resident {
            sha256: dataset.sha256.clone(),
            coloring: render.coloring(),
            filter: render.filter,
            bounds: cloud.bounds,
            spacing: cloud.spacing(),
            cloud: gpu_cloud,
            unreported_load: Some((load_ms, outcome)),
        })
    }
}

/// A rendered frame encoded, with its timings and what to report of it.
fn finished(
    frame: &mut pointfarm_render::raster::Frame,
    mut timings: Vec<StageTiming>,
    dataset_cache_hit: Option<bool>,
    cut: Option<pointfarm_daemon::model::FrameCut>,
    preview: Option<f64>,
) -> Result<RenderedFrame, FrameFailure> {
    let png = encode::png_bytes(frame)
        .map_err(|e| FrameFailure::transient(format!("encoding the PNG: {e}")))?;
    timings.extend(frame.timings.stages.iter().map(|t| StageTiming {
        stage: t.stage.name().to_string(),
        ms: t.ms,
        gpu_clock: t.clock == Clock::Gpu,
    }));
    tracing::info!(
        total_ms = timings.iter().map(|t| t.ms).sum::<f64>(),
        preview = preview.is_some(),
        "frame rendered"
    );
    Ok(RenderedFrame {
        png,
        outcome: FrameOutcome {
            timings,
            dataset_cache_hit,
            cut,
            preview,
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

//! A worker's render state and the rendering of one leased frame (`pointfarm worker`, also
//! as the daemon's embedded worker): load the dataset (through the worker's
//! `DatasetCache`), colour it, keep it resident on the GPU across frames, render with the
//! job's settings and encode the PNG, with the stage timings of every step.

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

use pointfarm_render::cache::{CacheOutcome, DatasetCache};
use pointfarm_render::cloud::WorldBounds;
use pointfarm_render::color::{point_colors, ColorMode};
use pointfarm_render::encode;
use pointfarm_render::gpu::GpuContext;
use pointfarm_render::raster::{Clock, GpuPointCloud, Renderer};

use crate::lease::{FrameOutcome, FrameTask};
use crate::model::StageTiming;
use crate::worker::failure::FrameFailure;

/// The cloud currently on the GPU.
struct Resident {
    sha256: String,
    color_mode: ColorMode,
    bounds: WorldBounds,
    cloud: GpuPointCloud,
    /// How the cloud was loaded, until the next finished frame reports it.
    unreported_load: Option<(f64, CacheOutcome)>,
}

/// A finished frame: the PNG and what to report with it.
pub struct RenderedFrame {
    pub png: Vec<u8>,
    pub outcome: FrameOutcome,
}

/// One worker's renderer, dataset cache and resident cloud, which render its leased frames.
pub struct WorkerRenderState {
    renderer: Renderer,
    cache: Option<Arc<DatasetCache>>,
    resident: Option<Resident>,
}

impl WorkerRenderState {
    /// Without a cache every new dataset is decoded from its file.
    pub fn new(gpu: Arc<GpuContext>, cache: Option<Arc<DatasetCache>>) -> Self {
        Self {
            renderer: Renderer::new(gpu),
            cache,
            resident: None,
        }
    }

    fn is_resident(&self, task: &FrameTask) -> bool {
        self.resident.as_ref().is_some_and(|r| {
            r.sha256 == task.dataset.sha256 && r.color_mode == task.request.render.color_mode
        })
    }

    /// Whether rendering `task` reads the dataset's files: its points are neither on the GPU
    /// nor in the cache.
    pub fn needs_files(&self, task: &FrameTask) -> bool {
        !self.is_resident(task)
            && !self
                .cache
                .as_ref()
                .is_some_and(|c| c.contains(&task.dataset.sha256))
    }

    /// Renders the frame of `task`; `files` are the dataset's files, read only when
    /// [`needs_files`](Self::needs_files) says so. Errors are failures to report.
    pub fn render(
        &mut self,
        task: &FrameTask,
        files: &[PathBuf],
    ) -> Result<RenderedFrame, FrameFailure> {
        if !self.is_resident(task) {
            self.resident = None; // free the old cloud's GPU memory first
            self.resident = Some(self.load(task, files)?);
        }
        let Some(current) = self.resident.as_mut() else {
            return Err(FrameFailure::transient("no resident cloud"));
        };
        let settings = task
            .request
            .frame_settings(task.lease.index, &current.bounds);
        let mut frame = self
            .renderer
            .render(&current.cloud, &settings)
            .map_err(|e| FrameFailure::from(&e))?;
        let png = encode::png_bytes(&mut frame)
            .map_err(|e| FrameFailure::transient(format!("encoding the PNG: {e}")))?;

        let mut timings: Vec<StageTiming> = Vec::new();
        let load = current.unreported_load.take();
        if let Some((ms, _)) = load {
            timings.push(StageTiming {
                stage: "load".into(),
                ms,
                gpu_clock: false,
            });
        }
        timings.extend(frame.timings.stages.iter().map(|t| StageTiming {
            stage: t.stage.name().to_string(),
            ms: t.ms,
            gpu_clock: t.clock == Clock::Gpu,
        }));
        tracing::info!(
            total_ms = timings.iter().map(|t| t.ms).sum::<f64>(),
            "frame rendered"
        );
        Ok(RenderedFrame {
            png,
            outcome: FrameOutcome {
                timings,
                dataset_cache_hit: load.map(|(_, outcome)| outcome == CacheOutcome::Hit),
            },
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
        cloud.colors = point_colors(&cloud, task.request.render.color_mode);
        let gpu_cloud = self
            .renderer
            .upload(&cloud)
            .map_err(|e| in_dataset(FrameFailure::from(&e)))?;
        tracing::info!(dataset = %dataset.id, points = cloud.len(), load_ms, ?outcome, "cloud resident");
        Ok(Resident {
            sha256: dataset.sha256.clone(),
            color_mode: task.request.render.color_mode,
            bounds: cloud.bounds,
            cloud: gpu_cloud,
            unreported_load: Some((load_ms, outcome)),
        })
    }
}

//! The embedded worker: a thread that takes frame tasks from the store, renders them with
//! `pointfarm-worker` and records the results. The cloud of the current dataset stays
//! resident on the GPU across frames and jobs; it is loaded again only for another dataset or
//! colour mode.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

use pointfarm_worker::cache::{CacheOutcome, DatasetCache};
use pointfarm_worker::cloud::WorldBounds;
use pointfarm_worker::color::{point_colours, ColorMode as WorkerColorMode};
use pointfarm_worker::gpu::GpuContext;
use pointfarm_worker::raster::{
    Clock, FillSettings, FrameSettings, GpuPointCloud, Quality as WorkerQuality, Renderer,
    Shading as WorkerShading,
};

use crate::camera_path::camera_for_frame;
use crate::model::{
    ColorMode, FrameReport, FrameState, Job, JobState, Quality, Shading, StageTiming,
};
use crate::service::Daemon;

/// The cloud currently on the GPU.
struct Resident {
    dataset_id: String,
    color_mode: ColorMode,
    bounds: WorldBounds,
    cloud: GpuPointCloud,
    /// How the cloud was loaded, until the next finished frame reports it.
    unreported_load: Option<(f64, CacheOutcome)>,
}

/// Runs the worker until `stop` is set. Returns when the current frame is finished.
pub fn run(daemon: Arc<Daemon>, gpu: Arc<GpuContext>, stop: Arc<AtomicBool>) {
    let mut renderer = Renderer::new(gpu);
    let cache = match DatasetCache::open(
        &daemon.config.worker_cache_dir(),
        daemon.config.worker_cache_bytes,
    ) {
        Ok(cache) => Some(cache),
        Err(e) => {
            tracing::error!(error = %e, "the dataset cache is unavailable; decoding every time");
            None
        }
    };
    let mut resident: Option<Resident> = None;
    while !stop.load(Ordering::SeqCst) {
        let task = match daemon.store.next_task() {
            Ok(task) => task,
            Err(e) => {
                tracing::error!(error = %e, "cannot read the job store");
                daemon.work.wait(Duration::from_secs(1));
                continue;
            }
        };
        let Some((job, index)) = task else {
            daemon.work.wait(Duration::from_millis(500));
            continue;
        };
        let span = tracing::info_span!("frame", job = %job.id, frame = index);
        let _entered = span.enter();
        if let Err(e) = render_task(
            &daemon,
            cache.as_ref(),
            &mut renderer,
            &mut resident,
            job,
            index,
        ) {
            tracing::error!(error = %e, "frame task failed");
        }
    }
}

fn render_task(
    daemon: &Daemon,
    cache: Option<&DatasetCache>,
    renderer: &mut Renderer,
    resident: &mut Option<Resident>,
    job: Job,
    index: u32,
) -> Result<(), crate::error::DaemonError> {
    let job = if job.state == JobState::Queued {
        let job = daemon
            .store
            .update_job(&job.id, |j| j.state = JobState::Running)?
            .unwrap_or(job);
        daemon.publish(&job, None);
        job
    } else {
        job
    };
    let spec = &job.spec;

    let is_current = resident
        .as_ref()
        .is_some_and(|r| r.dataset_id == spec.dataset_id && r.color_mode == spec.render.color_mode);
    if !is_current {
        *resident = None; // free the old cloud's GPU memory first
        match load_resident(
            daemon,
            cache,
            renderer,
            spec.dataset_id.as_str(),
            spec.render.color_mode,
        ) {
            Ok(loaded) => *resident = Some(loaded),
            Err(reason) => return fail_job(daemon, &job, reason),
        }
    }
    let Some(current) = resident.as_mut() else {
        return Ok(());
    };

    let aspect = spec.width as f64 / spec.height as f64;
    let camera = camera_for_frame(&spec.camera_path, index, &current.bounds, aspect);
    let settings = FrameSettings {
        point_size: spec.render.point_size,
        background: spec.render.background,
        quality: match spec.render.quality {
            Quality::Basic => WorkerQuality::Basic,
            Quality::High { depth_band } => WorkerQuality::High { depth_band },
        },
        shading: match spec.render.shading {
            Shading::None => WorkerShading::None,
            Shading::Edl { strength, radius } => WorkerShading::Edl { strength, radius },
            Shading::Pintus { levels, exponent } => WorkerShading::Pintus { levels, exponent },
        },
        fill: spec.render.fill.map(|f| FillSettings { kernel: f.kernel }),
        ..FrameSettings::new(spec.width, spec.height, camera)
    };
    let rendered = renderer
        .render(&current.cloud, &settings)
        .map_err(|e| e.to_string())
        .and_then(|mut frame| {
            let path = daemon.config.frame_path(&job.id, index);
            let partial = path.with_extension("png.part");
            std::fs::create_dir_all(daemon.config.frames_dir(&job.id))
                .map_err(|e| e.to_string())?;
            frame.save_png(&partial).map_err(|e| e.to_string())?;
            // The rename makes the frame appear whole or not at all.
            std::fs::rename(&partial, &path).map_err(|e| e.to_string())?;
            Ok(frame)
        });

    // The job may have been cancelled while the frame rendered.
    let current_job = daemon.job(&job.id)?;
    if current_job.state.is_terminal() {
        return Ok(());
    }
    match rendered {
        Ok(frame) => {
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
            let report = FrameReport {
                index,
                timings,
                dataset_cache_hit: load.map(|(_, outcome)| outcome == CacheOutcome::Hit),
            };
            daemon
                .store
                .set_frame(&job.id, index, &FrameState::Done(report.clone()))?;
            let updated = daemon
                .store
                .update_job(&job.id, |j| {
                    j.frames_done += 1;
                    if j.frames_done >= j.frames_total {
                        j.state = JobState::Succeeded;
                    }
                })?
                .unwrap_or(current_job);
            daemon.store.flush()?;
            tracing::info!(%frame.timings, "frame done");
            daemon.publish(&updated, Some(report));
        }
        Err(reason) => {
            let attempts = match daemon.store.frame(&job.id, index)? {
                Some(FrameState::Pending { attempts }) => attempts + 1,
                _ => 1,
            };
            tracing::warn!(attempts, %reason, "frame failed");
            if attempts >= daemon.config.max_frame_attempts {
                return fail_job(
                    daemon,
                    &job,
                    format!("frame {index} failed {attempts} times: {reason}"),
                );
            }
            daemon
                .store
                .set_frame(&job.id, index, &FrameState::Pending { attempts })?;
        }
    }
    Ok(())
}

/// Loads a dataset (from the cache when it has it), colours it and uploads it.
fn load_resident(
    daemon: &Daemon,
    cache: Option<&DatasetCache>,
    renderer: &Renderer,
    dataset_id: &str,
    color_mode: ColorMode,
) -> Result<Resident, String> {
    let started = std::time::Instant::now();
    let dataset = daemon.dataset(dataset_id).map_err(|e| e.to_string())?;
    let loaded = match cache {
        Some(cache) => cache
            .load(&dataset.sha256, &dataset.path)
            .map_err(|e| e.to_string()),
        None => pointfarm_worker::ingest::load_point_cloud(&dataset.path)
            .map(|cloud| (cloud, CacheOutcome::Miss))
            .map_err(|e| e.to_string()),
    };
    let (mut cloud, outcome) = loaded.map_err(|e| format!("dataset {dataset_id}: {e}"))?;
    let load_ms = started.elapsed().as_secs_f64() * 1e3;
    cloud.colors = point_colours(&cloud, worker_color_mode(color_mode));
    let gpu_cloud = renderer
        .upload(&cloud)
        .map_err(|e| format!("dataset {dataset_id}: {e}"))?;
    Ok(Resident {
        dataset_id: dataset_id.to_string(),
        color_mode,
        bounds: cloud.bounds,
        cloud: gpu_cloud,
        unreported_load: Some((load_ms, outcome)),
    })
}

fn worker_color_mode(mode: ColorMode) -> WorkerColorMode {
    match mode {
        ColorMode::Rgb => WorkerColorMode::Rgb,
        ColorMode::Intensity => WorkerColorMode::Intensity,
        ColorMode::Elevation => WorkerColorMode::Elevation,
        ColorMode::Classification => WorkerColorMode::Classification,
        ColorMode::ReturnNumber => WorkerColorMode::ReturnNumber,
        ColorMode::Fixed(rgb) => WorkerColorMode::Fixed(rgb),
    }
}

fn fail_job(daemon: &Daemon, job: &Job, reason: String) -> Result<(), crate::error::DaemonError> {
    tracing::warn!(job = %job.id, %reason, "job failed");
    if let Some(failed) = daemon.store.update_job(&job.id, |j| {
        j.state = JobState::Failed;
        j.error = Some(reason);
    })? {
        daemon.store.flush()?;
        daemon.publish(&failed, None);
    }
    Ok(())
}

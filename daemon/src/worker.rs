//! The embedded worker: a thread that takes frame tasks from the store, renders them with
//! `pointfarm-worker` and records the results. The cloud of the current dataset stays
//! resident on the GPU across frames and jobs; it is loaded again only for another dataset or
//! colour mode.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

use pointfarm_worker::cloud::{PointCloud, WorldBounds};
use pointfarm_worker::color::{point_colours, ColorMode as WorkerColorMode};
use pointfarm_worker::gpu::GpuContext;
use pointfarm_worker::ingest::load_point_cloud;
use pointfarm_worker::raster::{
    Clock, FrameSettings, GpuPointCloud, Quality as WorkerQuality, Renderer,
    Shading as WorkerShading,
};

use crate::camera_path::camera_for_frame;
use crate::model::{ColorMode, FrameState, Job, JobState, Quality, Shading, StageTiming};
use crate::service::Daemon;

/// The cloud currently on the GPU.
struct Resident {
    dataset_id: String,
    color_mode: ColorMode,
    bounds: WorldBounds,
    cloud: GpuPointCloud,
}

/// Runs the worker until `stop` is set. Returns when the current frame is finished.
pub fn run(daemon: Arc<Daemon>, gpu: Arc<GpuContext>, stop: Arc<AtomicBool>) {
    let mut renderer = Renderer::new(gpu);
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
        if let Err(e) = render_task(&daemon, &mut renderer, &mut resident, job, index) {
            tracing::error!(error = %e, "frame task failed");
        }
    }
}

fn render_task(
    daemon: &Daemon,
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
            renderer,
            spec.dataset_id.as_str(),
            spec.render.color_mode,
        ) {
            Ok(loaded) => *resident = Some(loaded),
            Err(reason) => return fail_job(daemon, &job, reason),
        }
    }
    let Some(current) = resident.as_ref() else {
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
        },
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
            let timings: Vec<StageTiming> = frame
                .timings
                .stages
                .iter()
                .map(|t| StageTiming {
                    stage: t.stage.name().to_string(),
                    ms: t.ms,
                    gpu_clock: t.clock == Clock::Gpu,
                })
                .collect();
            daemon.store.set_frame(
                &job.id,
                index,
                &FrameState::Done {
                    timings: timings.clone(),
                },
            )?;
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
            daemon.publish(&updated, Some((index, timings)));
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

fn load_resident(
    daemon: &Daemon,
    renderer: &Renderer,
    dataset_id: &str,
    color_mode: ColorMode,
) -> Result<Resident, String> {
    let dataset = daemon.dataset(dataset_id).map_err(|e| e.to_string())?;
    let mut cloud: PointCloud =
        load_point_cloud(&dataset.path).map_err(|e| format!("dataset {dataset_id}: {e}"))?;
    cloud.colors = point_colours(&cloud, worker_color_mode(color_mode));
    let gpu_cloud = renderer
        .upload(&cloud)
        .map_err(|e| format!("dataset {dataset_id}: {e}"))?;
    Ok(Resident {
        dataset_id: dataset_id.to_string(),
        color_mode,
        bounds: cloud.bounds,
        cloud: gpu_cloud,
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

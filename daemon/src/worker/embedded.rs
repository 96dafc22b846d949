//! The embedded worker: a thread of the daemon that leases frames in-process, through the same
//! leases as remote workers, and renders them with [`WorkerRenderState`]. It reads datasets from
//! the daemon's own files; its cloud stays resident on the GPU across frames and jobs.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

use pointfarm_render::cache::DatasetCache;
use pointfarm_render::gpu::GpuContext;

use crate::error::DaemonError;
use crate::lease::FrameTask;
use crate::service::Daemon;
use crate::worker::render_state::WorkerRenderState;

/// Runs the worker until `stop` is set. Returns when the current frame is finished.
pub fn run(daemon: Arc<Daemon>, gpu: Arc<GpuContext>, stop: Arc<AtomicBool>) {
    let cache = match DatasetCache::open(
        &daemon.config.worker_cache_dir(),
        daemon.config.worker_cache_bytes,
    ) {
        Ok(cache) => Some(Arc::new(cache)),
        Err(e) => {
            tracing::error!(error = %e, "the dataset cache is unavailable; decoding every time");
            None
        }
    };
    let mut render_state = WorkerRenderState::new(gpu, cache);
    let name = "embedded";
    while !stop.load(Ordering::SeqCst) {
        let task = match daemon.lease_frame(name, true) {
            Ok(task) => task,
            Err(e) => {
                tracing::error!(error = %e, "cannot lease a frame");
                daemon.work.wait(Duration::from_secs(1));
                continue;
            }
        };
        let Some(task) = task else {
            daemon.work.wait(Duration::from_millis(500));
            continue;
        };
        let span = tracing::info_span!(
            "frame",
            job = %task.lease.job_id,
            frame = task.lease.index,
            worker = name
        );
        let _entered = span.enter();
        if let Err(e) = render_task(&daemon, &mut render_state, &task) {
            tracing::error!(error = %e, "frame task failed");
        }
    }
}

fn render_task(
    daemon: &Daemon,
    render_state: &mut WorkerRenderState,
    task: &FrameTask,
) -> Result<(), DaemonError> {
    let rendered = daemon
        .dataset(&task.dataset.id)
        .map_err(|e| e.to_string())
        .and_then(|dataset| render_state.render(task, &dataset.path));
    match rendered {
        Ok(frame) => match daemon.complete_frame(&task.lease.id, &frame.png, frame.outcome) {
            Ok(_) => tracing::info!("frame done"),
            // The job was cancelled or failed while the frame rendered.
            Err(DaemonError::FailedPrecondition(reason)) => {
                tracing::info!(%reason, "frame dropped")
            }
            Err(e) => return Err(e),
        },
        Err(reason) => match daemon.fail_frame(&task.lease.id, &reason) {
            Ok(()) | Err(DaemonError::FailedPrecondition(_)) => {}
            Err(e) => return Err(e),
        },
    }
    Ok(())
}

//! The daemon's scheduler: how long leasing a frame takes against the length of the job
//! history. Each history level is a state database holding that many finished jobs and one
//! queued job; a sample leases one of its frames and gives it back. No GPU: nothing renders.
//! The baseline is the same run's empty history (`docs/perf/lease-index.md`).

use std::time::Instant;

use pointfarm_daemon::model::{FrameReport, FrameState, JobSpec, JobState};
use pointfarm_daemon::service::{Daemon, DaemonConfig};
use pointfarm_render::request::RenderRequest;
use serde::Serialize;

use crate::error::BenchError;
use crate::stats::{median, percentile};

/// The finished jobs of the full run's longest history.
pub const FULL_HISTORY_JOBS: usize = 10_000;

/// Leasing at one length of history.
#[derive(Debug, Clone, Serialize)]
pub struct SchedulerResult {
    /// Finished jobs in the state database.
    pub history_jobs: usize,
    pub samples: usize,
    /// Time of `Daemon::lease_frame`, the work behind `LeaseFrame`.
    pub lease_median_ms: f64,
    pub lease_p95_ms: f64,
    /// This level's median over the empty history's.
    pub over_empty_history: f64,
}

fn job(request_id: String, frames: u32) -> JobSpec {
    JobSpec::new(
        request_id,
        String::new(),
        RenderRequest::turntable(64, 48, frames),
    )
}

/// Measures leasing at each length of `histories` (ascending, starting from 0), `samples`
/// leases at each.
pub fn measure(
    histories: &[usize],
    samples: usize,
    progress: &mut dyn FnMut(&str),
) -> Result<Vec<SchedulerResult>, BenchError> {
    let scratch = tempfile::tempdir().map_err(|e| BenchError::Scratch(e.to_string()))?;
    let daemon_error =
        |e: pointfarm_daemon::error::DaemonError| BenchError::Scheduler(e.to_string());
    let roots = scratch.path().join("roots");
    std::fs::create_dir_all(&roots).map_err(|e| BenchError::Scratch(e.to_string()))?;
    // Registering only hashes the file: it is never decoded here.
    std::fs::write(roots.join("d.las"), b"LASF").map_err(|e| BenchError::Scratch(e.to_string()))?;
    let mut config = DaemonConfig::new(scratch.path().join("data"));
    config.data_roots = vec![roots];
    let daemon = Daemon::open(config).map_err(daemon_error)?;
    let dataset = daemon
        .register_dataset(&["d.las".to_string()], "")
        .map_err(daemon_error)?;
    let finished = FrameState::Done(FrameReport::default());

    let mut results: Vec<SchedulerResult> = Vec::new();
    let mut history = 0;
    for &target in histories {
        progress(&format!("scheduler: {target} finished jobs"));
        while history < target {
            // A finished job as the state database holds one: its frame done, its state ended.
            let mut spec = job(format!("history-{history}"), 1);
            spec.dataset_id = dataset.id.clone();
            let done = daemon.submit_job(spec).map_err(daemon_error)?;
            let state = &daemon.state;
            let stored =
                |e: pointfarm_daemon::error::StateError| BenchError::Scheduler(e.to_string());
            state.set_frame(&done.id, 0, &finished).map_err(stored)?;
            state
                .update_job(&done.id, |j| {
                    (j.frames_done, j.state) = (1, JobState::Succeeded)
                })
                .map_err(stored)?;
            history += 1;
        }
        let mut queued = job(format!("queued-{target}"), 16);
        queued.dataset_id = dataset.id.clone();
        let queued = daemon.submit_job(queued).map_err(daemon_error)?;
        let mut times = Vec::with_capacity(samples);
        for _ in 0..samples {
            let started = Instant::now();
            let task = daemon
                .lease_frame("bench", false, &Default::default())
                .map_err(daemon_error)?;
            times.push(started.elapsed().as_secs_f64() * 1e3);
            let task = task.ok_or_else(|| BenchError::Scheduler("no frame to lease".into()))?;
            daemon.release_frame(&task.lease.id).map_err(daemon_error)?;
        }
        daemon.cancel_job(&queued.id).map_err(daemon_error)?;
        let lease_median_ms = median(times.clone());
        let baseline = results
            .first()
            .map_or(lease_median_ms, |r| r.lease_median_ms);
        results.push(SchedulerResult {
            history_jobs: target,
            samples,
            lease_median_ms,
            lease_p95_ms: percentile(times, 0.95),
            over_empty_history: lease_median_ms / baseline,
        });
    }
    Ok(results)
}

/// The scheduler's table.
pub fn markdown(results: &[SchedulerResult]) -> String {
    let mut md = String::from(
        "| finished jobs | leases | lease median (ms) | p95 (ms) | over the empty history |\n\
         |---:|---:|---:|---:|---:|\n",
    );
    for r in results {
        md.push_str(&format!(
            "| {} | {} | {:.3} | {:.3} | {:.2}x |\n",
            r.history_jobs, r.samples, r.lease_median_ms, r.lease_p95_ms, r.over_empty_history
        ));
    }
    md
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn leases_are_measured_at_every_history_length() {
        let results = measure(&[0, 30], 5, &mut |_| {}).expect("measure");
        assert_eq!(results.len(), 2);
        assert_eq!(results[1].history_jobs, 30);
        assert!(results
            .iter()
            .all(|r| r.lease_median_ms > 0.0 && r.samples == 5));
        assert_eq!(results[0].over_empty_history, 1.0);
        assert!(markdown(&results).contains("| 30 | 5 |"));
    }
}

//! Retention: jobs that ended more than `job_retention` ago are removed with their frames
//! (`serve --job-retention-days`), and while the stored frames take more than
//! `frame_quota_bytes` (`serve --frame-quota`), the jobs that ended first are removed, with
//! theirs, until they fit. Unfinished jobs and their frames are never removed.
//!
//! A sweep runs every `retention_sweep_period` on a blocking thread of its own: it reads the
//! ended jobs and measures the frames outside the scheduling lock, then takes the lock once
//! per job it removes, so leasing never waits on a whole sweep. Each removal is logged and
//! counted (`pointfarm_jobs_removed_total`). The rule takes its "now" as an argument, so that
//! tests move the clock rather than wait for it.

use std::sync::Arc;

use pointfarm_render::lod::disk_usage::folder_bytes;

use crate::error::DaemonError;
use crate::job_control::remove_moved_frames;
use crate::model::{now_unix_ms, Job, JobId};
use crate::service::Daemon;

/// What one sweep removed.
#[derive(Debug, Default, Clone, PartialEq, Eq)]
pub struct RetentionSweep {
    /// Jobs that had ended more than the retention before, oldest end first.
    pub expired: Vec<JobId>,
    /// Jobs removed, oldest end first, so that the stored frames fit the quota.
    pub over_quota: Vec<JobId>,
    /// Bytes of frames stored after the sweep; measured only under a quota.
    pub frame_bytes: u64,
}

impl Daemon {
    /// Applies the retention rules as of `now_unix_ms`: the ended jobs older than the
    /// retention go, then the oldest ended jobs while the stored frames pass the quota.
    pub fn sweep_retention(&self, now_unix_ms: i64) -> Result<RetentionSweep, DaemonError> {
        let config = &self.config;
        let mut sweep = RetentionSweep::default();
        if config.job_retention.is_none() && config.frame_quota_bytes.is_none() {
            return Ok(sweep);
        }
        let mut ended = self.state.ended_jobs()?;
        ended.sort_by(|a, b| (a.updated_unix_ms, &a.id).cmp(&(b.updated_unix_ms, &b.id)));
        if let Some(retention) = config.job_retention {
            let cutoff = now_unix_ms.saturating_sub(retention.as_millis() as i64);
            let (old, recent): (Vec<Job>, Vec<Job>) = ended
                .into_iter()
                .partition(|job| job.updated_unix_ms < cutoff);
            for job in old {
                if self.remove_unchanged(&job)? {
                    sweep.expired.push(job.id);
                }
            }
            ended = recent;
        }
        if let Some(quota) = config.frame_quota_bytes {
            let jobs_dir = config.data_dir.join("jobs");
            sweep.frame_bytes = folder_bytes(&jobs_dir);
            for job in ended {
                if sweep.frame_bytes <= quota {
                    break;
                }
                let bytes = folder_bytes(&config.frames_dir(&job.id));
                if bytes > 0 && self.remove_unchanged(&job)? {
                    sweep.frame_bytes = sweep.frame_bytes.saturating_sub(bytes);
                    sweep.over_quota.push(job.id);
                }
            }
        }
        self.metrics
            .jobs_removed("retention", sweep.expired.len() as u64);
        self.metrics
            .jobs_removed("frame_quota", sweep.over_quota.len() as u64);
        if !sweep.expired.is_empty() || !sweep.over_quota.is_empty() {
            tracing::info!(
                expired = sweep.expired.len(),
                over_quota = sweep.over_quota.len(),
                frame_bytes = sweep.frame_bytes,
                "retention removed ended jobs with their frames"
            );
        }
        Ok(sweep)
    }

    /// Removes `job` as it was read, unless it changed since (retried, deleted); returns
    /// whether it did.
    fn remove_unchanged(&self, job: &Job) -> Result<bool, DaemonError> {
        let moved = {
            let _scheduling = self.scheduling()?;
            match self.state.job(&job.id)? {
                Some(current) if current == *job => self.remove_ended_job_locked(job)?,
                _ => return Ok(false),
            }
        };
        remove_moved_frames(moved);
        Ok(true)
    }
}

/// Starts the retention sweep of `daemon` on the runtime, after removing the frames of
/// deleted jobs that a stop left behind; without a retention rule it ends after that.
pub fn spawn_sweep(daemon: Arc<Daemon>) -> tokio::task::JoinHandle<()> {
    let config = &daemon.config;
    let ruled = config.job_retention.is_some() || config.frame_quota_bytes.is_some();
    let period = config.retention_sweep_period;
    tokio::spawn(async move {
        let first = daemon.clone();
        let _ = tokio::task::spawn_blocking(move || first.remove_deleted_frames_left()).await;
        if !ruled {
            return;
        }
        let mut tick = tokio::time::interval(period);
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        loop {
            tick.tick().await;
            let daemon = daemon.clone();
            match tokio::task::spawn_blocking(move || daemon.sweep_retention(now_unix_ms())).await {
                Ok(Ok(_)) => {}
                Ok(Err(e)) => tracing::error!(error = %e, "the retention sweep"),
                Err(e) => tracing::error!(error = %e, "the retention sweep panicked"),
            }
        }
    })
}

#[cfg(test)]
mod tests;

//! Job control: what users do to a job once it is submitted, as render farms let them
//! (Flamenco, Deadline, OpenCue): cancel it, queue a failed job's frames again, pause and
//! resume it, change its priority, delete it; and the names and labels it is found by. More
//! `Daemon` methods, for the gRPC layer and the dashboard alike; the retention sweep
//! (`retention.rs`) deletes through [`Daemon::remove_ended_job_locked`] too.
//!
//! Every change happens under the scheduling lock, so none races a lease or a completion.
//! Only cancelling (and deleting a job that has not ended, which cancels it) ends a job:
//! retrying, pausing and resuming tell watchers, never the webhooks.

use std::collections::BTreeMap;
use std::ops::RangeInclusive;
use std::path::PathBuf;

use crate::error::DaemonError;
use crate::model::{Job, JobState};
use crate::service::{unique_suffix, Daemon};
use crate::state::{JobFilter, Page};

/// The priorities a job may have; higher runs first.
pub const PRIORITY_RANGE: RangeInclusive<i32> = -100..=100;
/// The longest name of a job, in characters.
pub const MAX_NAME_CHARS: usize = 128;
/// Most labels on one job.
pub const MAX_LABELS: usize = 32;
/// The longest label key, in characters of `a-z0-9_.-`.
pub const MAX_LABEL_KEY_CHARS: usize = 63;
/// The longest label value, in bytes.
pub const MAX_LABEL_VALUE_BYTES: usize = 256;

/// Where deleted jobs' frames are moved, below the data folder, before they are removed: a
/// folder of frames without its job in `jobs/` would stop the next start.
const DELETED_DIR: &str = "deleted-frames";

/// A job's name (the request's `field`): at most [`MAX_NAME_CHARS`] characters, none of them
/// a control character.
pub fn check_name(field: &str, name: &str) -> Result<(), DaemonError> {
    let chars = name.chars().count();
    if chars > MAX_NAME_CHARS {
        return Err(DaemonError::invalid(
            field,
            format!("is {chars} characters long; a job's name has at most {MAX_NAME_CHARS}"),
        ));
    }
    if name.chars().any(char::is_control) {
        return Err(DaemonError::invalid(
            field,
            "holds a control character; a job's name is printable text",
        ));
    }
    Ok(())
}

/// A job's labels (or those a listing asks for): at most [`MAX_LABELS`], keys of 1 to
/// [`MAX_LABEL_KEY_CHARS`] characters of `a-z0-9_.-`, values of at most
/// [`MAX_LABEL_VALUE_BYTES`] bytes without control characters.
pub fn check_labels(field: &str, labels: &BTreeMap<String, String>) -> Result<(), DaemonError> {
    if labels.len() > MAX_LABELS {
        return Err(DaemonError::invalid(
            field,
            format!(
                "has {} labels; a job has at most {MAX_LABELS}",
                labels.len()
            ),
        ));
    }
    for (key, value) in labels {
        let key_chars = |c: char| matches!(c, 'a'..='z' | '0'..='9' | '_' | '.' | '-');
        if key.is_empty() || key.len() > MAX_LABEL_KEY_CHARS || !key.chars().all(key_chars) {
            return Err(DaemonError::invalid(
                field,
                format!(
                    "key {key:?} is not 1 to {MAX_LABEL_KEY_CHARS} characters of a-z, 0-9, \
                     '_', '.' and '-'"
                ),
            ));
        }
        if value.len() > MAX_LABEL_VALUE_BYTES {
            return Err(DaemonError::invalid(
                format!("{field}[{key}]"),
                format!(
                    "is {} bytes long; a label's value has at most {MAX_LABEL_VALUE_BYTES}",
                    value.len()
                ),
            ));
        }
        if value.chars().any(char::is_control) {
            return Err(DaemonError::invalid(
                format!("{field}[{key}]"),
                "holds a control character",
            ));
        }
    }
    Ok(())
}

/// A job's priority: within [`PRIORITY_RANGE`].
pub fn check_priority(field: &str, priority: i32) -> Result<(), DaemonError> {
    if PRIORITY_RANGE.contains(&priority) {
        return Ok(());
    }
    Err(DaemonError::invalid(
        field,
        format!(
            "{priority} is outside {}..={}",
            PRIORITY_RANGE.start(),
            PRIORITY_RANGE.end()
        ),
    ))
}

/// Refuses a change to `job`, which has ended, saying what it was for.
fn ended(job: &Job, what: &str) -> DaemonError {
    DaemonError::FailedPrecondition(format!(
        "job {} already {}; {what}",
        job.id,
        job.state.name()
    ))
}

impl Daemon {
    /// A page of the jobs `filter` accepts, in the order they were submitted.
    pub fn find_jobs(
        &self,
        filter: &JobFilter,
        page_size: u32,
        token: &str,
    ) -> Result<Page<Job>, DaemonError> {
        check_labels("labels", &filter.labels)?;
        Ok(self
            .state
            .list_matching_jobs(filter, page_size as usize, token)?)
    }

    /// Cancels a job that has not ended; its workers drop their frames at their next
    /// heartbeat. A cancelled job is returned as it is; one that succeeded or failed is
    /// refused.
    pub fn cancel_job(&self, id: &str) -> Result<Job, DaemonError> {
        // Under the scheduling lock, so no frame completes after the cancel.
        let _scheduling = self.scheduling()?;
        let job = self.job(id)?;
        match job.state {
            JobState::Cancelled => Ok(job),
            state if state.is_terminal() => Err(ended(&job, "nothing to cancel")),
            _ => self.cancel_locked(id),
        }
    }

    /// Cancels the unfinished job `id`: its end is logged, told to the webhooks and settles
    /// the jobs after it.
    fn cancel_locked(&self, id: &str) -> Result<Job, DaemonError> {
        let job = self
            .state
            .update_job(id, |j| j.state = JobState::Cancelled)?
            .ok_or_else(|| DaemonError::NotFound(format!("job {id}")))?;
        self.state.flush()?;
        self.log_job_end(&job, 0);
        self.publish(&job, None);
        Ok(job)
    }

    /// Puts the frames of a failed job that did not finish back in the queue, each with its
    /// attempts counted from zero, and empties its blocklist: the job is running again. A job
    /// that has not failed is refused (a cancelled one too), as is one whose chain is broken
    /// (the job it runs after must be retried first).
    pub fn retry_job(&self, id: &str) -> Result<Job, DaemonError> {
        let _scheduling = self.scheduling()?;
        let job = self.job(id)?;
        match job.state {
            JobState::Failed => {}
            JobState::Cancelled => {
                return Err(DaemonError::FailedPrecondition(format!(
                    "job {id} was cancelled; only a failed job can be retried"
                )))
            }
            state => {
                return Err(DaemonError::FailedPrecondition(format!(
                    "job {id} is {}; only a failed job can be retried",
                    state.name()
                )))
            }
        }
        if job.awaits_video() {
            return self.retry_video_locked(&job);
        }
        if job.frames_done >= job.frames_total {
            return Err(DaemonError::FailedPrecondition(format!(
                "job {id} has no failed frames to retry"
            )));
        }
        if let Some(reason) = self.broken_chain(&job)? {
            return Err(DaemonError::FailedPrecondition(format!(
                "job {id} cannot run again: {reason}; retry that job first"
            )));
        }
        let retried = self
            .state
            .requeue_unfinished_frames(id, |job| {
                job.state = JobState::Running;
                job.error = None;
                job.worker_failures.clear();
                job.blocklist.clear();
            })?
            .ok_or_else(|| DaemonError::NotFound(format!("job {id}")))?;
        tracing::info!(
            job = %id,
            frames = retried.frames_total - retried.frames_done,
            "the failed job's unfinished frames are queued again"
        );
        self.publish(&retried, None);
        self.work.notify();
        Ok(retried)
    }

    /// Pauses a queued or running job: none of its frames is leased until it is resumed,
    /// and frames being rendered finish. A paused job is returned as it is; one that has
    /// ended is refused.
    pub fn pause_job(&self, id: &str) -> Result<Job, DaemonError> {
        self.change_state(
            id,
            JobState::Paused,
            "only a queued or running job can be paused",
        )
    }

    /// Puts a paused job back in the queue. A queued or running job is returned as it is;
    /// one that has ended is refused.
    pub fn resume_job(&self, id: &str) -> Result<Job, DaemonError> {
        self.change_state(id, JobState::Queued, "only a paused job can be resumed")
    }

    /// Pauses (`to` paused) or resumes (`to` queued) job `id`; `refusal` says why a job that
    /// has ended is refused.
    fn change_state(&self, id: &str, to: JobState, refusal: &str) -> Result<Job, DaemonError> {
        let _scheduling = self.scheduling()?;
        let job = self.job(id)?;
        let unchanged = match to {
            JobState::Paused => job.state == JobState::Paused,
            _ => job.state != JobState::Paused,
        };
        if job.state.is_terminal() {
            return Err(ended(&job, refusal));
        }
        if unchanged {
            return Ok(job);
        }
        let changed = self
            .state
            .update_job(id, |j| j.state = to)?
            .ok_or_else(|| DaemonError::NotFound(format!("job {id}")))?;
        self.state.flush()?;
        tracing::info!(job = %id, state = changed.state.name(), "job paused or resumed");
        self.publish(&changed, None);
        self.work.notify();
        Ok(changed)
    }

    /// Gives a job that has not ended a new priority (within [`PRIORITY_RANGE`]): its
    /// frames are leased in its new place from the next lease on.
    pub fn set_job_priority(&self, id: &str, priority: i32) -> Result<Job, DaemonError> {
        check_priority("priority", priority)?;
        let _scheduling = self.scheduling()?;
        let job = self.job(id)?;
        if job.state.is_terminal() {
            return Err(ended(&job, "its priority no longer matters"));
        }
        if job.spec.priority == priority {
            return Ok(job);
        }
        let changed = self
            .state
            .set_priority(id, priority)?
            .ok_or_else(|| DaemonError::NotFound(format!("job {id}")))?;
        tracing::info!(job = %id, priority, "job priority changed");
        self.publish(&changed, None);
        self.work.notify();
        Ok(changed)
    }

    /// Deletes a job that has ended with its frames and records, and returns it as it was; a
    /// job that has not ended is refused unless `force`, which cancels it first. Jobs that
    /// run after it fail.
    pub fn delete_job(&self, id: &str, force: bool) -> Result<Job, DaemonError> {
        let (job, moved) = {
            let _scheduling = self.scheduling()?;
            let job = self.job(id)?;
            let job = match job.state {
                state if state.is_terminal() => job,
                _ if force => self.cancel_locked(id)?,
                state => {
                    return Err(DaemonError::FailedPrecondition(format!(
                        "job {id} is {}; cancel it first, or delete it with force \
                         (`pointfarm jobs rm --force`)",
                        state.name()
                    )))
                }
            };
            let moved = self.remove_ended_job_locked(&job)?;
            (job, moved)
        };
        self.metrics.jobs_removed("deleted", 1);
        remove_moved_frames(moved);
        Ok(job)
    }

    /// Removes `job`, which has ended, from the state and its frames from the frames'
    /// folder, and fails the jobs that run after it. Returns where its frames were moved, to
    /// be removed outside the scheduling lock ([`remove_moved_frames`]).
    pub(crate) fn remove_ended_job_locked(
        &self,
        job: &Job,
    ) -> Result<Option<PathBuf>, DaemonError> {
        let frames = self.config.frames_dir(&job.id);
        let moved = if frames.exists() {
            let deleted = self.config.data_dir.join(DELETED_DIR);
            std::fs::create_dir_all(&deleted)?;
            let aside = deleted.join(format!("{}-{}", job.id, unique_suffix()));
            std::fs::rename(&frames, &aside)?;
            Some(aside)
        } else {
            None
        };
        if let Err(e) = self.state.delete_job(&job.id) {
            // The job stays; so do its frames.
            if let Some(aside) = &moved {
                let _ = std::fs::rename(aside, &frames);
            }
            return Err(e.into());
        }
        tracing::info!(job = %job.id, state = job.state.name(), "job deleted");
        self.end_chain_of_deleted_locked(&job.id)?;
        Ok(moved)
    }

    /// When job `job_id` was deleted, removes the (empty) folder that a frame handed in
    /// under its lease made again, so that no folder of frames outlives its job; returns
    /// whether the job was deleted.
    pub(crate) fn remove_folder_of_deleted_job_locked(
        &self,
        job_id: &str,
    ) -> Result<bool, DaemonError> {
        if self.state.job(job_id)?.is_some() {
            return Ok(false);
        }
        let _ = std::fs::remove_dir(self.config.frames_dir(job_id));
        Ok(true)
    }

    /// Removes the frames of deleted jobs that a stop left behind (moved aside, not yet
    /// removed).
    pub(crate) fn remove_deleted_frames_left(&self) {
        let Ok(entries) = std::fs::read_dir(self.config.data_dir.join(DELETED_DIR)) else {
            return;
        };
        for entry in entries.flatten() {
            remove_moved_frames(Some(entry.path()));
        }
    }
}

/// Removes the frames of a deleted job, moved aside; a failure is logged (the next start
/// tries again).
pub(crate) fn remove_moved_frames(moved: Option<PathBuf>) {
    let Some(path) = moved else {
        return;
    };
    match std::fs::remove_dir_all(&path) {
        Ok(()) => {}
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
        Err(e) => {
            tracing::warn!(folder = %path.display(), error = %e, "removing a deleted job's frames")
        }
    }
}

#[cfg(test)]
mod tests;

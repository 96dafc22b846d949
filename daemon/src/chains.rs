//! Job chains: a job submitted after others waits, queued, until each has succeeded, and fails
//! when one fails or is cancelled, then so do the jobs after it, along the chain. The jobs a
//! job runs after exist before it, so a chain never closes on itself. More `Daemon` methods:
//! `lease_frame` and `job_availability` ask [`Daemon::unmet_prerequisite`], and every job's
//! end (`log_job_end`) comes through [`Daemon::end_chain_locked`].

use std::collections::HashSet;

use crate::error::DaemonError;
use crate::model::{Job, JobId, JobState};
use crate::service::{lookup, Daemon};

/// Most jobs one job may run after: a chain's fan-in, kept small enough to check at each
/// lease.
pub const MAX_AFTER_JOBS: usize = 32;

impl Daemon {
    /// The jobs a submission runs after, checked: at most [`MAX_AFTER_JOBS`] once each, in
    /// the order given, and each an existing job (NotFound names the first that is not).
    pub(crate) fn checked_after(&self, after: &[JobId]) -> Result<Vec<JobId>, DaemonError> {
        let mut seen = HashSet::new();
        let unique: Vec<JobId> = after
            .iter()
            .filter(|id| seen.insert(id.as_str()))
            .cloned()
            .collect();
        if unique.len() > MAX_AFTER_JOBS {
            return Err(DaemonError::invalid(
                "after_job_ids",
                format!(
                    "names {} jobs; a job runs after at most {MAX_AFTER_JOBS}",
                    unique.len()
                ),
            ));
        }
        for id in &unique {
            lookup("after_job_ids", "job", id, |id| self.state.job(id))?;
        }
        Ok(unique)
    }

    /// The first job `job` runs after that has not succeeded (yet), so its frames are not
    /// leased; None when each has.
    pub(crate) fn unmet_prerequisite(&self, job: &Job) -> Option<JobId> {
        job.spec
            .after
            .iter()
            .find(|id| {
                !matches!(self.state.job(id), Ok(Some(found)) if found.state == JobState::Succeeded)
            })
            .cloned()
    }

    /// Why `job` can never run: a job it runs after has ended without succeeding, or is gone.
    pub(crate) fn broken_chain(&self, job: &Job) -> Result<Option<String>, DaemonError> {
        for id in &job.spec.after {
            let reason = match self.state.job(id)? {
                None => deleted_prerequisite(id),
                Some(found) => match prerequisite_failure(&found) {
                    Some(reason) => reason,
                    None => continue,
                },
            };
            return Ok(Some(reason));
        }
        Ok(None)
    }

    /// Fails `job` at once, under the scheduling lock, if a job it runs after has already
    /// ended without succeeding: a submission after such a job, or a job whose chain was
    /// left unfinished by a crash.
    pub(crate) fn fail_if_chain_broken_locked(&self, job: &Job) -> Result<(), DaemonError> {
        if job.state.is_terminal() {
            return Ok(());
        }
        match self.broken_chain(job)? {
            Some(reason) => self.fail_waiting_job_locked(&job.id, reason),
            None => Ok(()),
        }
    }

    /// Settles the jobs after `ended`, under the scheduling lock where it ended: they may run
    /// now that it succeeded (the workers are woken), or they fail, and those after them.
    pub(crate) fn end_chain_locked(&self, ended: &Job) -> Result<(), DaemonError> {
        let waiting: Vec<Job> = self
            .state
            .unfinished_jobs()?
            .into_iter()
            .filter(|job| job.spec.after.contains(&ended.id))
            .collect();
        if waiting.is_empty() {
            return Ok(());
        }
        let Some(reason) = prerequisite_failure(ended) else {
            self.work.notify();
            return Ok(());
        };
        for job in waiting {
            self.fail_waiting_job_locked(&job.id, reason.clone())?;
        }
        Ok(())
    }

    /// Fails the unfinished jobs that run after `deleted`, under the scheduling lock where
    /// it was deleted, and those after them.
    pub(crate) fn end_chain_of_deleted_locked(&self, deleted: &str) -> Result<(), DaemonError> {
        let reason = deleted_prerequisite(deleted);
        for job in self.state.unfinished_jobs()? {
            if job.spec.after.iter().any(|id| id == deleted) {
                self.fail_waiting_job_locked(&job.id, reason.clone())?;
            }
        }
        Ok(())
    }

    /// At start-up, fails each unfinished job whose chain is broken: a crash between a job's
    /// end and the failure of the jobs after it leaves them waiting for nothing.
    pub(crate) fn fail_broken_chains(&self) -> Result<(), DaemonError> {
        let _scheduling = self.scheduling()?;
        for job in self.state.unfinished_jobs()? {
            // An earlier job of this pass may have failed it already, along its chain.
            if let Some(current) = self.state.job(&job.id)? {
                self.fail_if_chain_broken_locked(&current)?;
            }
        }
        Ok(())
    }

    /// Fails a job that waits on a failed chain, tells its watchers, and goes on along the
    /// chain (through `log_job_end`).
    fn fail_waiting_job_locked(&self, id: &str, reason: String) -> Result<(), DaemonError> {
        let mut had_ended = false;
        let Some(failed) = self.state.update_job(id, |job| {
            had_ended = job.state.is_terminal();
            if !had_ended {
                job.state = JobState::Failed;
                job.error = Some(reason);
            }
        })?
        else {
            return Ok(());
        };
        if had_ended {
            return Ok(());
        }
        self.state.flush()?;
        self.log_job_end(&failed, 0);
        self.publish(&failed, None);
        Ok(())
    }
}

/// Why the jobs after `ended` fail: None when it succeeded (or has not ended).
fn prerequisite_failure(ended: &Job) -> Option<String> {
    match ended.state {
        JobState::Failed => Some(format!("job {} failed", ended.id)),
        JobState::Cancelled => Some(format!("job {} was cancelled", ended.id)),
        JobState::Queued | JobState::Running | JobState::Paused | JobState::Succeeded => None,
    }
}

/// Why the jobs after job `id`, which is gone, fail.
fn deleted_prerequisite(id: &str) -> String {
    format!("job {id} it runs after was deleted")
}

#[cfg(test)]
mod tests;

//! What job control changes in the records: a failed job's unfinished frames queued again, a
//! job moved in the scheduling index by a new priority, a job removed with everything stored
//! of it, and the jobs a filtered listing or the retention sweep looks for.

use std::collections::BTreeMap;

use sled::Transactional;

use super::records::Records;
use super::{decode, encode, frames_prefix, page, queue_key, transaction_error, Page};
use crate::error::StateError;
use crate::model::{now_unix_ms, FrameState, Job, JobState};

/// Which jobs a listing shows.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct JobFilter {
    /// Only jobs in this state; every state when None.
    pub state: Option<JobState>,
    /// Only jobs that have each of these labels with this value.
    pub labels: BTreeMap<String, String>,
}

impl JobFilter {
    pub fn matches(&self, job: &Job) -> bool {
        self.state.is_none_or(|state| job.state == state)
            && self
                .labels
                .iter()
                .all(|(key, value)| job.spec.labels.get(key) == Some(value))
    }
}

impl Records {
    /// Puts every unfinished frame of job `id` back in the queue with no attempt counted and
    /// applies `change` to the job (which must leave it unfinished), as one flushed
    /// transaction. None if there is no such job.
    pub(super) fn requeue_unfinished_frames(
        &self,
        id: &str,
        change: impl FnOnce(&mut Job),
    ) -> Result<Option<Job>, StateError> {
        let Some(job) = self.changed_job(id, change)? else {
            return Ok(None);
        };
        let fresh = encode(&FrameState::Pending { attempts: 0 })?;
        let (mut frames, mut pending) = (sled::Batch::default(), sled::Batch::default());
        for entry in self.trees.frames.scan_prefix(frames_prefix(id)) {
            let (key, value) = entry?;
            if let FrameState::Pending { .. } = decode::<FrameState>(&value)? {
                frames.insert(key.clone(), fresh.clone());
                pending.insert(key, &[]);
            }
        }
        let encoded = encode(&job)?;
        let queued = !job.state.is_terminal();
        let trees = (
            &self.trees.frames,
            &self.trees.pending,
            &self.trees.jobs,
            &self.trees.queue,
        );
        trees
            .transaction(|(frames_tree, pending_tree, jobs, queue)| {
                frames_tree.apply_batch(&frames)?;
                pending_tree.apply_batch(&pending)?;
                jobs.insert(job.id.as_bytes(), encoded.as_slice())?;
                if queued {
                    queue.insert(queue_key(&job), job.id.as_bytes())?;
                }
                Ok(())
            })
            .map_err(transaction_error)?;
        self.db.flush()?;
        Ok(Some(job))
    }

    /// Gives job `id` the priority `priority` and, while it is unfinished, its place in the
    /// scheduling index for it, as one flushed transaction. None if there is no such job.
    pub(super) fn set_priority(&self, id: &str, priority: i32) -> Result<Option<Job>, StateError> {
        let Some(before) = self.job(id)? else {
            return Ok(None);
        };
        let mut job = before.clone();
        job.spec.priority = priority;
        job.updated_unix_ms = now_unix_ms();
        let encoded = encode(&job)?;
        let queued = !job.state.is_terminal();
        (&self.trees.jobs, &self.trees.queue)
            .transaction(|(jobs, queue)| {
                jobs.insert(job.id.as_bytes(), encoded.as_slice())?;
                if queued {
                    queue.remove(queue_key(&before))?;
                    queue.insert(queue_key(&job), job.id.as_bytes())?;
                }
                Ok(())
            })
            .map_err(transaction_error)?;
        self.db.flush()?;
        Ok(Some(job))
    }

    /// Removes job `id` and every record of it (its frames, pending frames and previews, its
    /// place in the scheduling index, its request id) as one flushed transaction, and returns
    /// it. Its leases stay until they are next used or run out, so that their holders learn
    /// why to stop. None if there is no such job.
    pub(super) fn delete_job(&self, id: &str) -> Result<Option<Job>, StateError> {
        let Some(job) = self.job(id)? else {
            return Ok(None);
        };
        let prefix = frames_prefix(id);
        let removal = |tree: &sled::Tree| -> Result<sled::Batch, StateError> {
            let mut batch = sled::Batch::default();
            for key in tree.scan_prefix(&prefix).keys() {
                batch.remove(key?);
            }
            Ok(batch)
        };
        let frames = removal(&self.trees.frames)?;
        let pending = removal(&self.trees.pending)?;
        let previews = removal(&self.trees.previews)?;
        // A later submission with the same request id makes a new job.
        let requested = !job.spec.request_id.is_empty()
            && self
                .trees
                .requests
                .get(job.spec.request_id.as_bytes())?
                .as_deref()
                == Some(id.as_bytes());
        let trees = (
            &self.trees.jobs,
            &self.trees.queue,
            &self.trees.frames,
            &self.trees.pending,
            &self.trees.previews,
            &self.trees.requests,
        );
        trees
            .transaction(
                |(jobs, queue, frames_tree, pending_tree, previews_tree, requests)| {
                    jobs.remove(id.as_bytes())?;
                    queue.remove(queue_key(&job))?;
                    frames_tree.apply_batch(&frames)?;
                    pending_tree.apply_batch(&pending)?;
                    previews_tree.apply_batch(&previews)?;
                    if requested {
                        requests.remove(job.spec.request_id.as_bytes())?;
                    }
                    Ok(())
                },
            )
            .map_err(transaction_error)?;
        self.db.flush()?;
        Ok(Some(job))
    }

    pub(super) fn list_matching_jobs(
        &self,
        filter: &JobFilter,
        page_size: usize,
        token: &str,
    ) -> Result<Page<Job>, StateError> {
        page(
            &self.trees.jobs,
            page_size,
            token,
            |job: &Job| filter.matches(job),
            |job| job.id.clone(),
        )
    }

    /// Every job that has ended: every job is read (the retention sweep asks, now and then).
    pub(super) fn ended_jobs(&self) -> Result<Vec<Job>, StateError> {
        let mut ended = Vec::new();
        for entry in self.trees.jobs.iter() {
            let job: Job = decode(&entry?.1)?;
            if job.state.is_terminal() {
                ended.push(job);
            }
        }
        Ok(ended)
    }
}

//! The records of one opened database and what is done with them; the `StateDb` around it
//! adds the manifest, the disk's health and reopening.

use sled::Transactional;

use super::trees::Trees;
use super::{
    decode, decode_stored, encode, frame_key, frames_prefix, page, queue_key, transaction_error,
    Page, INDEX_VERSION, INDEX_VERSION_KEY,
};
use crate::error::StateError;
use crate::lease_record::Lease;
use crate::model::{now_unix_ms, Dataset, FrameReport, FrameState, Job, JobSpec, JobState};

/// An opened database and its trees.
pub(super) struct Records {
    pub(super) db: sled::Db,
    pub(super) trees: Trees,
}

impl Records {
    /// Builds the scheduling index from the jobs and frames (a database written before the
    /// index existed).
    pub(super) fn rebuild_index(&self) -> Result<(), StateError> {
        self.trees.queue.clear()?;
        self.trees.pending.clear()?;
        for entry in self.trees.jobs.iter() {
            let job: Job = decode(&entry?.1)?;
            if !job.state.is_terminal() {
                self.trees
                    .queue
                    .insert(queue_key(&job), job.id.as_bytes())?;
            }
        }
        for entry in self.trees.frames.iter() {
            let (key, value) = entry?;
            if let FrameState::Pending { .. } = decode::<FrameState>(&value)? {
                self.trees.pending.insert(key, &[])?;
            }
        }
        self.trees.meta.insert(INDEX_VERSION_KEY, INDEX_VERSION)?;
        self.db.flush()?;
        Ok(())
    }

    /// Writes everything to disk.
    pub(super) fn flush(&self) -> Result<(), StateError> {
        self.db.flush()?;
        Ok(())
    }

    pub(super) fn put_dataset(&self, dataset: &Dataset) -> Result<bool, StateError> {
        let replaced = self
            .trees
            .datasets
            .insert(dataset.id.as_bytes(), encode(dataset)?)?;
        if replaced.is_none() {
            self.db.flush()?;
        }
        Ok(replaced.is_none())
    }

    pub(super) fn dataset(&self, id: &str) -> Result<Option<Dataset>, StateError> {
        decode_stored(self.trees.datasets.get(id.as_bytes())?)
    }

    pub(super) fn delete_dataset(&self, id: &str) -> Result<Option<Dataset>, StateError> {
        let removed = decode_stored(self.trees.datasets.remove(id.as_bytes())?);
        self.db.flush()?;
        removed
    }

    pub(super) fn list_datasets(
        &self,
        page_size: usize,
        token: &str,
    ) -> Result<Page<Dataset>, StateError> {
        page(
            &self.trees.datasets,
            page_size,
            token,
            |_: &Dataset| true,
            |d| d.id.clone(),
        )
    }

    /// Creates a job with all its frames pending, or returns the job that an earlier
    /// submission with the same request id created (`false`).
    /// The job an earlier submission with `request_id` created, if any.
    pub(super) fn requested_job(&self, request_id: &str) -> Result<Option<Job>, StateError> {
        if request_id.is_empty() {
            return Ok(None);
        }
        match self.trees.requests.get(request_id.as_bytes())? {
            Some(id) => self.job(&String::from_utf8_lossy(&id)),
            None => Ok(None),
        }
    }

    pub(super) fn submit_job(&self, spec: JobSpec) -> Result<(Job, bool), StateError> {
        if let Some(job) = self.requested_job(&spec.request_id)? {
            return Ok((job, false));
        }
        // Ids sort by creation: a monotonic counter, zero-padded.
        let id = format!("job-{:012}", self.db.generate_id()?);
        let now = now_unix_ms();
        let frames = spec.request.frames();
        let job = Job {
            id: id.clone(),
            state: JobState::Queued,
            frames_total: frames,
            frames_done: 0,
            error: None,
            created_unix_ms: now,
            updated_unix_ms: now,
            spec,
            worker_failures: Default::default(),
            blocklist: Default::default(),
            encode: None,
            outputs: Default::default(),
        };
        let pending = encode(&FrameState::Pending { attempts: 0 })?;
        let (mut frame_batch, mut pending_batch) = (sled::Batch::default(), sled::Batch::default());
        for index in 0..frames {
            frame_batch.insert(frame_key(&id, index), pending.clone());
            pending_batch.insert(frame_key(&id, index), &[]);
        }
        let encoded = encode(&job)?;
        let trees = (
            &self.trees.frames,
            &self.trees.pending,
            &self.trees.jobs,
            &self.trees.requests,
            &self.trees.queue,
        );
        trees
            .transaction(|(frames, pending, jobs, requests, queue)| {
                frames.apply_batch(&frame_batch)?;
                pending.apply_batch(&pending_batch)?;
                jobs.insert(id.as_bytes(), encoded.as_slice())?;
                if !job.spec.request_id.is_empty() {
                    requests.insert(job.spec.request_id.as_bytes(), id.as_bytes())?;
                }
                queue.insert(queue_key(&job), id.as_bytes())?;
                Ok(())
            })
            .map_err(transaction_error)?;
        self.db.flush()?;
        Ok((job, true))
    }

    pub(super) fn job(&self, id: &str) -> Result<Option<Job>, StateError> {
        decode_stored(self.trees.jobs.get(id.as_bytes())?)
    }

    /// Stores `job`; a job that has ended leaves the scheduling index, with its frames.
    pub(super) fn put_job(&self, job: &Job) -> Result<(), StateError> {
        let encoded = encode(job)?;
        if !job.state.is_terminal() {
            self.trees.jobs.insert(job.id.as_bytes(), encoded)?;
            return Ok(());
        }
        let prefix = frames_prefix(&job.id);
        let mut unlisted = sled::Batch::default();
        for key in self.trees.pending.scan_prefix(&prefix).keys() {
            unlisted.remove(key?);
        }
        (&self.trees.jobs, &self.trees.queue, &self.trees.pending)
            .transaction(|(jobs, queue, pending)| {
                jobs.insert(job.id.as_bytes(), encoded.as_slice())?;
                queue.remove(queue_key(job))?;
                pending.apply_batch(&unlisted)?;
                Ok(())
            })
            .map_err(transaction_error)
    }

    /// Applies `change` to the stored job and returns the result (None if there is no such
    /// job). Bumps the update time.
    pub(super) fn update_job(
        &self,
        id: &str,
        change: impl FnOnce(&mut Job),
    ) -> Result<Option<Job>, StateError> {
        let changed = self.changed_job(id, change)?;
        if let Some(job) = &changed {
            self.put_job(job)?;
        }
        Ok(changed)
    }

    /// The stored job `id` with `change` applied and its update time bumped, not yet written.
    pub(super) fn changed_job(
        &self,
        id: &str,
        change: impl FnOnce(&mut Job),
    ) -> Result<Option<Job>, StateError> {
        Ok(self.job(id)?.map(|mut job| {
            change(&mut job);
            job.updated_unix_ms = now_unix_ms();
            job
        }))
    }

    /// Whether an unfinished job renders the dataset `dataset_id`: every job is looked at.
    pub(super) fn dataset_in_use(&self, dataset_id: &str) -> Result<bool, StateError> {
        for entry in self.trees.jobs.iter() {
            let job: Job = decode(&entry?.1)?;
            if job.spec.dataset_id == dataset_id && !job.state.is_terminal() {
                return Ok(true);
            }
        }
        Ok(false)
    }

    /// The bytes of the datasets whose files lie in `uploads` (the ones uploaded, not
    /// registered from a data root).
    /// Bytes of the distinct uploaded files (several datasets may share one).
    pub(super) fn uploaded_bytes(&self, uploads: &std::path::Path) -> Result<u64, StateError> {
        let mut counted = std::collections::HashSet::new();
        let mut total = 0u64;
        for dataset in self.datasets()? {
            for file in dataset.files() {
                if file.path.starts_with(uploads) && counted.insert(file.path) {
                    total = total.saturating_add(file.size_bytes);
                }
            }
        }
        Ok(total)
    }

    pub(super) fn datasets(&self) -> Result<Vec<Dataset>, StateError> {
        self.trees
            .datasets
            .iter()
            .map(|entry| decode(&entry?.1))
            .collect()
    }

    pub(super) fn frame(&self, job_id: &str, index: u32) -> Result<Option<FrameState>, StateError> {
        decode_stored(self.trees.frames.get(frame_key(job_id, index))?)
    }

    /// Marks the frame of `lease` done with `report`, removes the lease and applies `change`
    /// to its job, in one transaction, flushed: after a crash or a failed write either all of
    /// it happened or none. None if there is no such job.
    pub(super) fn finish_frame(
        &self,
        lease: &Lease,
        report: &FrameReport,
        change: impl FnOnce(&mut Job),
    ) -> Result<Option<Job>, StateError> {
        let Some(mut job) = self.job(&lease.job_id)? else {
            return Ok(None);
        };
        change(&mut job);
        job.updated_unix_ms = now_unix_ms();
        let key = frame_key(&lease.job_id, lease.index);
        let frame = encode(&FrameState::Done(report.clone()))?;
        let encoded = encode(&job)?;
        let ended = job.state.is_terminal();
        let mut unlisted = sled::Batch::default();
        if ended {
            let prefix = frames_prefix(&job.id);
            for key in self.trees.pending.scan_prefix(&prefix).keys() {
                unlisted.remove(key?);
            }
        }
        let trees = (
            &self.trees.frames,
            &self.trees.pending,
            &self.trees.leases,
            &self.trees.jobs,
            &self.trees.queue,
            &self.trees.previews,
        );
        trees
            .transaction(|(frames, pending, leases, jobs, queue, previews)| {
                frames.insert(key.as_slice(), frame.as_slice())?;
                pending.remove(key.as_slice())?;
                previews.remove(key.as_slice())?;
                leases.remove(lease.id.as_bytes())?;
                jobs.insert(job.id.as_bytes(), encoded.as_slice())?;
                if ended {
                    queue.remove(queue_key(&job))?;
                    pending.apply_batch(&unlisted)?;
                }
                Ok(())
            })
            .map_err(transaction_error)?;
        self.db.flush()?;
        Ok(Some(job))
    }

    /// Keeps `report` as the preview of the (still pending) frame of `lease` and removes the
    /// lease, in one flushed transaction; the job's update time is set. None if there is no
    /// such job.
    pub(super) fn keep_preview(
        &self,
        lease: &Lease,
        report: &FrameReport,
    ) -> Result<Option<Job>, StateError> {
        let Some(mut job) = self.job(&lease.job_id)? else {
            return Ok(None);
        };
        job.updated_unix_ms = now_unix_ms();
        let key = frame_key(&lease.job_id, lease.index);
        let preview = encode(report)?;
        let encoded = encode(&job)?;
        (&self.trees.previews, &self.trees.leases, &self.trees.jobs)
            .transaction(|(previews, leases, jobs)| {
                previews.insert(key.as_slice(), preview.as_slice())?;
                leases.remove(lease.id.as_bytes())?;
                jobs.insert(job.id.as_bytes(), encoded.as_slice())?;
                Ok(())
            })
            .map_err(transaction_error)?;
        self.db.flush()?;
        Ok(Some(job))
    }

    /// Whether frame `index` of job `job_id` has a preview.
    pub(super) fn has_preview(&self, job_id: &str, index: u32) -> Result<bool, StateError> {
        Ok(self.trees.previews.contains_key(frame_key(job_id, index))?)
    }

    /// The version of the preview of frame `index` of job `job_id`, when it has one.
    pub(super) fn preview_version(
        &self,
        job_id: &str,
        index: u32,
    ) -> Result<Option<u32>, StateError> {
        let preview: Option<FrameReport> =
            decode_stored(self.trees.previews.get(frame_key(job_id, index))?)?;
        Ok(preview.map(|report| report.preview_version))
    }

    pub(super) fn set_frame(
        &self,
        job_id: &str,
        index: u32,
        state: &FrameState,
    ) -> Result<(), StateError> {
        let key = frame_key(job_id, index);
        let encoded = encode(state)?;
        let is_pending = matches!(state, FrameState::Pending { .. });
        (&self.trees.frames, &self.trees.pending)
            .transaction(|(frames, pending)| {
                frames.insert(key.as_slice(), encoded.as_slice())?;
                if is_pending {
                    pending.insert(key.as_slice(), &[])?;
                } else {
                    pending.remove(key.as_slice())?;
                }
                Ok(())
            })
            .map_err(transaction_error)
    }

    /// The next frame to render: the first pending frame that is not `leased`, of the
    /// unfinished job with the highest priority that `usable` accepts, the oldest first among
    /// equals; of a preview job, the frame of the lowest `turn`. Reads the scheduling index,
    /// so finished jobs cost nothing.
    pub(super) fn next_task(
        &self,
        leased: &std::collections::HashSet<(String, u32)>,
        usable: &dyn Fn(&Job) -> bool,
        turn: &dyn Fn(&Job, Option<u32>) -> Option<u32>,
    ) -> Result<Option<(Job, u32)>, StateError> {
        for entry in self.trees.queue.iter() {
            let (_, job_id) = entry?;
            let job_id = String::from_utf8_lossy(&job_id).into_owned();
            let prefix = frames_prefix(&job_id);
            let mut job: Option<Job> = None;
            // The preview job's frame of the lowest turn so far, and that turn.
            let mut later: Option<(u32, u32)> = None;
            for key in self.trees.pending.scan_prefix(&prefix).keys() {
                let key = key?;
                let index_bytes: [u8; 4] = key[prefix.len()..].try_into().unwrap_or([0; 4]);
                let index = u32::from_be_bytes(index_bytes);
                if leased.contains(&(job_id.clone(), index)) {
                    continue;
                }
                // Every frame of a job is alike to `usable`: one look decides for the job.
                if job.is_none() {
                    match self.job(&job_id)? {
                        Some(found) if !found.state.is_terminal() && usable(&found) => {
                            job = Some(found)
                        }
                        _ => break,
                    }
                }
                let Some(found) = &job else { break };
                // A preview job's previewed frames wait while its store builds, until the
                // build's version moves past their previews'; then the oldest preview is
                // drawn again first, so that every frame sharpens, not only the first ones.
                if found.spec.preview {
                    match turn(found, self.preview_version(&job_id, index)?) {
                        None => continue,
                        Some(0) => {}
                        Some(turn) => {
                            if later.is_none_or(|(best, _)| turn < best) {
                                later = Some((turn, index));
                            }
                            continue;
                        }
                    }
                }
                return Ok(Some((found.clone(), index)));
            }
            if let (Some(job), Some((_, index))) = (job, later) {
                return Ok(Some((job, index)));
            }
        }
        Ok(None)
    }

    pub(super) fn unfinished_jobs(&self) -> Result<Vec<Job>, StateError> {
        let mut jobs = Vec::new();
        for entry in self.trees.queue.iter() {
            let (_, job_id) = entry?;
            if let Some(job) = self.job(&String::from_utf8_lossy(&job_id))? {
                if !job.state.is_terminal() {
                    jobs.push(job);
                }
            }
        }
        Ok(jobs)
    }

    /// Sets frame `index` of job `job_id` pending after `attempts` failed attempts and applies
    /// `change` to its job, in one transaction. None if there is no such job.
    pub(super) fn count_failed_attempt(
        &self,
        job_id: &str,
        index: u32,
        attempts: u32,
        change: impl FnOnce(&mut Job),
    ) -> Result<Option<Job>, StateError> {
        let Some(job) = self.changed_job(job_id, change)? else {
            return Ok(None);
        };
        let key = frame_key(job_id, index);
        let frame = encode(&FrameState::Pending { attempts })?;
        let encoded = encode(&job)?;
        (&self.trees.frames, &self.trees.pending, &self.trees.jobs)
            .transaction(|(frames, pending, jobs)| {
                frames.insert(key.as_slice(), frame.as_slice())?;
                pending.insert(key.as_slice(), &[])?;
                jobs.insert(job.id.as_bytes(), encoded.as_slice())?;
                Ok(())
            })
            .map_err(transaction_error)?;
        Ok(Some(job))
    }

    /// After a restart: jobs that were running go back to the queue (their finished frames
    /// stay finished). Returns how many.
    pub(super) fn requeue_running(&self) -> Result<usize, StateError> {
        let mut requeued = 0;
        for entry in self.trees.jobs.iter() {
            let (_, value) = entry?;
            let mut job: Job = decode(&value)?;
            if job.state == JobState::Running {
                job.state = JobState::Queued;
                self.put_job(&job)?;
                requeued += 1;
            }
        }
        Ok(requeued)
    }

    pub(super) fn put_lease(&self, lease: &Lease) -> Result<(), StateError> {
        self.trees
            .leases
            .insert(lease.id.as_bytes(), encode(lease)?)?;
        Ok(())
    }

    pub(super) fn lease(&self, id: &str) -> Result<Option<Lease>, StateError> {
        decode_stored(self.trees.leases.get(id.as_bytes())?)
    }

    pub(super) fn remove_lease(&self, id: &str) -> Result<(), StateError> {
        self.trees.leases.remove(id.as_bytes())?;
        Ok(())
    }

    pub(super) fn leases(&self) -> Result<Vec<Lease>, StateError> {
        self.trees
            .leases
            .iter()
            .map(|entry| decode(&entry?.1))
            .collect()
    }

    /// A new id, unique in this database (also across restarts).
    pub(super) fn generate_id(&self) -> Result<u64, StateError> {
        Ok(self.db.generate_id()?)
    }

    /// The failed attempts recorded at a job's frames, finished or pending.
    pub(super) fn failed_attempts(&self, job_id: &str) -> Result<u64, StateError> {
        let mut failed = 0u64;
        for entry in self.trees.frames.scan_prefix(frames_prefix(job_id)) {
            let (_, value) = entry?;
            failed += u64::from(match decode::<FrameState>(&value)? {
                FrameState::Pending { attempts } => attempts,
                FrameState::Done(report) => report.failed_attempts,
            });
        }
        Ok(failed)
    }

    /// The reports of the finished frames of a job and the previews of its pending ones, by
    /// frame index.
    pub(super) fn frame_reports(&self, job_id: &str) -> Result<Vec<FrameReport>, StateError> {
        let prefix = frames_prefix(job_id);
        let mut out = Vec::new();
        for entry in self.trees.frames.scan_prefix(&prefix) {
            let (_, value) = entry?;
            if let FrameState::Done(report) = decode::<FrameState>(&value)? {
                out.push(report);
            }
        }
        let finals = out.len();
        for entry in self.trees.previews.scan_prefix(&prefix) {
            let (_, value) = entry?;
            out.push(decode::<FrameReport>(&value)?);
        }
        if out.len() > finals {
            out.sort_by_key(|report| report.index);
        }
        Ok(out)
    }
}

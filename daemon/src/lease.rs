//! Frame leases: the one way frames reach workers, the embedded worker process and remote
//! worker processes alike. A worker leases a pending frame, renders it, and hands the PNG in under
//! its lease; only the holder of a live lease can complete a frame, so a frame is never
//! stored twice.
//!
//! Leases live in sled with their expiry in wall-clock time, so a remote worker that is
//! rendering while the daemon restarts can still hand its frame in afterwards. A remote lease
//! that is not renewed by heartbeats expires: the frame goes back to the queue and the attempt
//! counts toward `max_frame_attempts`, so a frame that kills every worker fails its job
//! instead of looping. The embedded worker is a child process of the daemon: when it exits
//! its leases count an attempt at once, and those found at start-up (the child died with the
//! previous daemon) count one too. A failure the worker reports as permanent (the dataset
//! cannot be read, the request cannot render) fails the job at once.
//!
//! A worker is leased only frames it can render: of jobs whose chains let them run (each job
//! they run after has succeeded, `chains`), whose requirements (tags, a GPU) it meets, whose
//! images are no larger than it draws (`capabilities`), and that have not
//! blocklisted it. A worker that fails `worker_failures_before_blocklist` frames of a job
//! (reported failures and leases that ran out; not leases lost because the daemon stopped)
//! gets no more of that job's frames, as Flamenco and Deadline do: the count is stored with
//! the job. The frames' own attempts (`max_frame_attempts`) count as before, so a frame that
//! fails everywhere still fails its job.
//!
//! Every change to leases, frames and job states made here happens under one scheduling lock,
//! so two workers never get the same frame and a cancel never races a completion.

use std::collections::HashSet;

use crate::capabilities::WorkerCapabilities;
use crate::error::DaemonError;
use crate::lease_record::Lease;
use crate::model::{now_unix_ms, FrameReport, FrameState, Job, JobState};
use crate::service::Daemon;

mod lost;
mod store_waits;
mod task;

use store_waits::StoreWaits;

pub use task::{
    FailureKind, FrameOutcome, FrameTask, HeartbeatAnswer, PublishedStore, TaskDataset, TaskFile,
};

impl Daemon {
    fn lease_timeout_ms(&self) -> i64 {
        self.config.lease_timeout.as_millis() as i64
    }

    /// Leases the next frame (highest priority, oldest job, lowest index) that `worker`, with
    /// `capabilities`, can render and has not been blocklisted for, or None when there is
    /// nothing for it to render. A frame waiting for its dataset's store is passed over
    /// (`store_waits`).
    pub fn lease_frame(
        &self,
        worker: &str,
        embedded: bool,
        capabilities: &WorkerCapabilities,
    ) -> Result<Option<FrameTask>, DaemonError> {
        let _scheduling = self.scheduling()?;
        if let Some(outage) = self.state.outage() {
            return Err(DaemonError::ResourceExhausted(outage));
        }
        self.expire_leases_locked()?;
        let leased: HashSet<(String, u32)> = self
            .state
            .leases()?
            .into_iter()
            .map(|l| (l.job_id, l.index))
            .collect();
        let waits = StoreWaits::new(self);
        let usable = |job: &Job| {
            job.state != JobState::Paused
                && !job.blocklist.contains(worker)
                && self.unmet_prerequisite(job).is_none()
                && capabilities
                    .refusal(&job.spec.requirements, &job.spec.request)
                    .is_none()
                && !waits.holds_final_frames(job)
        };
        let turn = |job: &Job, drawn: Option<u32>| waits.turn(job, drawn);
        loop {
            let Some((job, index)) = self.state.next_task(&leased, &usable, &turn)? else {
                return Ok(None);
            };
            let Some(dataset) = self.state.dataset(&job.spec.dataset_id)? else {
                self.fail_job_locked(
                    &job.id,
                    format!("dataset {} no longer exists", job.spec.dataset_id),
                    0,
                )?;
                continue;
            };
            // The part of the dataset its frames see while the whole store is not ready.
            let dataset = self.stores.leased(&job, &dataset);
            let failed_attempts = match self.state.frame(&job.id, index)? {
                Some(FrameState::Pending { attempts }) => attempts,
                _ => 0,
            };
            let preview_version = if job.spec.preview {
                match (
                    self.state.preview_version(&job.id, index)?,
                    waits.building(&job),
                ) {
                    (None, current) => Some(current.unwrap_or(0)),
                    (Some(drawn), Some(current)) if drawn < current => Some(current),
                    _ => None,
                }
            } else {
                None
            };
            let job = if job.state == JobState::Queued {
                let running = self
                    .state
                    .update_job(&job.id, |j| j.state = JobState::Running)?
                    .unwrap_or(job);
                self.publish(&running, None);
                running
            } else {
                job
            };
            let lease = Lease {
                id: Lease::new_id(),
                job_id: job.id.clone(),
                index,
                worker: worker.to_string(),
                embedded,
                expires_unix_ms: now_unix_ms() + self.lease_timeout_ms(),
                preview_version,
            };
            // Durable before the worker starts: a crash of the daemon while the frame renders
            // then still counts the attempt at the next start.
            let recorded = self
                .state
                .put_lease(&lease)
                .and_then(|()| self.state.flush());
            self.unless_disk_refused(&lease, recorded.map_err(DaemonError::from))?;
            tracing::debug!(job = %job.id, frame = index, lease = %lease.id, worker, "frame leased");
            return Ok(Some(FrameTask {
                lease,
                lease_timeout: self.config.lease_timeout,
                dataset: TaskDataset {
                    files: match dataset.remote {
                        Some(_) => Vec::new(),
                        None => dataset
                            .files()
                            .into_iter()
                            .map(|file| TaskFile {
                                sha256: file.sha256,
                                size_bytes: file.size_bytes,
                            })
                            .collect(),
                    },
                    published: self.stores.published(&dataset.sha256),
                    remote: dataset.remote,
                    id: dataset.id,
                    sha256: dataset.sha256,
                    size_bytes: dataset.size_bytes,
                },
                request: job.spec.request.clone(),
                failed_attempts,
            }));
        }
    }

    /// The lease `lease_id` and its job, if the lease is still held and the job still wants
    /// the frame; FailedPrecondition otherwise (a lease of an ended job is dropped).
    fn held_lease_locked(&self, lease_id: &str) -> Result<(Lease, Job), DaemonError> {
        let lease = self.state.lease(lease_id)?.ok_or_else(|| {
            DaemonError::FailedPrecondition(format!(
                "lease {lease_id} is not held (it expired, or its frame was given to another worker)"
            ))
        })?;
        let job = self.state.job(&lease.job_id)?;
        match job {
            Some(job) if !job.state.is_terminal() => Ok((lease, job)),
            other => {
                self.state.remove_lease(lease_id)?;
                let state = other.map(|j| j.state.name());
                Err(DaemonError::FailedPrecondition(format!(
                    "job {} has ended ({}); frame {} is no longer wanted",
                    lease.job_id,
                    state.unwrap_or("deleted"),
                    lease.index
                )))
            }
        }
    }

    /// Checks that `lease_id` is held, and returns it with the frame size its job expects.
    pub fn held_lease(&self, lease_id: &str) -> Result<(Lease, u32, u32), DaemonError> {
        let _scheduling = self.scheduling()?;
        self.expire_leases_locked()?;
        let (lease, job) = self.held_lease_locked(lease_id)?;
        Ok((lease, job.spec.request.width, job.spec.request.height))
    }

    /// Extends a lease, or says why the worker should drop its frame.
    pub fn heartbeat(&self, lease_id: &str) -> Result<HeartbeatAnswer, DaemonError> {
        let _scheduling = self.scheduling()?;
        self.expire_leases_locked()?;
        match self.held_lease_locked(lease_id) {
            Ok((mut lease, _)) => {
                self.workers.heard_from_named(&lease.worker);
                lease.expires_unix_ms = now_unix_ms() + self.lease_timeout_ms();
                // The disk takes no renewal now; every lease is renewed when it takes writes
                // again, so the holder renders on.
                if self.state.outage().is_none() {
                    self.state.put_lease(&lease)?;
                }
                Ok(HeartbeatAnswer::Continue {
                    expires_unix_ms: lease.expires_unix_ms,
                })
            }
            Err(DaemonError::FailedPrecondition(reason)) => Ok(HeartbeatAnswer::Stop(reason)),
            Err(e) => Err(e),
        }
    }

    /// Stores the PNG of a leased frame and marks the frame done. Refused (FailedPrecondition)
    /// when the lease is no longer held; then nothing is written over. When the disk refuses
    /// the PNG or the state (ResourceExhausted), the frame goes back to the queue without an
    /// attempt counted and no partial file is left.
    pub fn complete_frame(
        &self,
        lease_id: &str,
        png: &[u8],
        outcome: FrameOutcome,
    ) -> Result<Job, DaemonError> {
        let (lease, width, height) = self.held_lease(lease_id)?;
        check_png(png, width, height)?;
        if outcome.preview.is_some() && !self.job_asks_previews(&lease.job_id)? {
            return Err(DaemonError::invalid(
                "result.preview",
                format!("job {} asked for no previews", lease.job_id),
            ));
        }
        // Written outside the lock under a name of this lease; renamed into place only if the
        // lease is still held then.
        let path = self.config.frame_path(&lease.job_id, lease.index);
        let partial = path.with_extension(format!("{lease_id}.part"));
        let written = std::fs::create_dir_all(self.config.frames_dir(&lease.job_id))
            .and_then(|()| std::fs::write(&partial, png));
        if let Err(e) = written {
            let _ = std::fs::remove_file(&partial);
            let _scheduling = self.scheduling()?;
            // A job deleted meanwhile took its folder: not the disk's fault.
            if self.remove_folder_of_deleted_job_locked(&lease.job_id)? {
                return Err(self.held_lease_locked(lease_id).err().unwrap_or_else(|| {
                    DaemonError::FailedPrecondition(format!("job {} was deleted", lease.job_id))
                }));
            }
            let refused = self.state.frame_write_refused(&e);
            return Err(self.give_back_refused_locked(&lease, refused));
        }

        let _scheduling = self.scheduling()?;
        let checked = (|| {
            self.expire_leases_locked()?;
            self.held_lease_locked(lease_id)?;
            match self.state.frame(&lease.job_id, lease.index)? {
                Some(FrameState::Pending { attempts }) => Ok(attempts),
                _ => Err(DaemonError::FailedPrecondition(format!(
                    "frame {} of job {} is already done",
                    lease.index, lease.job_id
                ))),
            }
        })();
        let failed_attempts = match checked {
            Ok(attempts) => attempts,
            Err(e) => {
                let _ = std::fs::remove_file(&partial);
                self.remove_folder_of_deleted_job_locked(&lease.job_id)?;
                return self.unless_disk_refused(&lease, Err(e));
            }
        };
        // The rename makes the frame appear whole or not at all; it is marked done only after.
        if let Err(e) = std::fs::rename(&partial, &path) {
            let _ = std::fs::remove_file(&partial);
            let refused = self.state.frame_write_refused(&e);
            return Err(self.give_back_refused_locked(&lease, refused));
        }
        let report = FrameReport {
            index: lease.index,
            timings: outcome.timings,
            dataset_cache_hit: outcome.dataset_cache_hit,
            failed_attempts,
            cut: outcome.cut,
            worker: lease.worker.clone(),
            preview: outcome.preview,
            // A preview handed in under a lease that asked for none was drawn from what the
            // worker had: counted as the chunk starts alone.
            preview_version: outcome
                .preview
                .map_or(0, |_| lease.preview_version.unwrap_or(0)),
        };
        if report.preview.is_some() {
            // A preview is kept beside the pending frame, whose final render replaces it.
            let kept = self.state.keep_preview(&lease, &report);
            let job = self
                .unless_disk_refused(&lease, kept.map_err(DaemonError::from))?
                .ok_or_else(|| DaemonError::NotFound(format!("job {}", lease.job_id)))?;
            self.work.notify();
            self.publish(&job, Some(report));
            return Ok(job);
        }
        // The output's record goes first, so that the frame's flush makes it durable too.
        if let Some(job) = self.state.job(&lease.job_id)? {
            self.enqueue_frame_output(&job, lease.index);
        }
        // A refused state write leaves the PNG in place: the write may yet have reached the
        // disk, and a frame marked done must have its image; rendered again, it is replaced.
        let finished = self.state.finish_frame(&lease, &report, |j| {
            j.frames_done += 1;
            if j.frames_done >= j.frames_total && j.ends_with_last_frame() {
                j.state = JobState::Succeeded;
            }
        });
        let job = self
            .unless_disk_refused(&lease, finished.map_err(DaemonError::from))?
            .ok_or_else(|| DaemonError::NotFound(format!("job {}", lease.job_id)))?;
        self.metrics.frame_completed(&report);
        self.tell_stores_job_moved(&job);
        if job.state == JobState::Succeeded {
            self.log_job_end(&job, 0);
        }
        self.publish(&job, Some(report));
        Ok(job)
    }

    fn job_asks_previews(&self, job_id: &str) -> Result<bool, DaemonError> {
        Ok(self.state.job(job_id)?.is_some_and(|job| job.spec.preview))
    }

    /// `result` of storing something of `lease`'s frame; when the disk refused it, the lease
    /// is given back (`give_back_refused_locked`).
    fn unless_disk_refused<T>(
        &self,
        lease: &Lease,
        result: Result<T, DaemonError>,
    ) -> Result<T, DaemonError> {
        match result {
            Err(DaemonError::ResourceExhausted(refused)) if self.state.outage().is_some() => {
                Err(self.give_back_refused_locked(lease, refused))
            }
            other => other,
        }
    }

    /// The disk refused to store the frame of `lease` (`refused` says how): not the frame's
    /// fault, so it goes back to the queue without an attempt counted. Returns the error that
    /// tells its worker to back off.
    fn give_back_refused_locked(&self, lease: &Lease, refused: String) -> DaemonError {
        if let Err(e) = self.state.give_back_lease(&lease.id) {
            // Then the lease runs out and counts an attempt: the state database cannot do better.
            tracing::warn!(lease = %lease.id, error = %e, "giving back a lease the disk refused");
        }
        tracing::debug!(job = %lease.job_id, frame = lease.index, worker = %lease.worker, "the disk refused the frame: back in the queue, no attempt counted");
        self.work.notify();
        DaemonError::ResourceExhausted(format!(
            "frame {} of job {} goes back to the queue (no attempt counted): {refused}",
            lease.index, lease.job_id
        ))
    }

    /// The holder of `lease_id` could not render its frame: the attempt counts; the job fails
    /// when the frame has used up its attempts, or at once when the failure is permanent.
    pub fn fail_frame(
        &self,
        lease_id: &str,
        reason: &str,
        kind: FailureKind,
    ) -> Result<(), DaemonError> {
        let _scheduling = self.scheduling()?;
        let (lease, _) = self.held_lease_locked(lease_id)?;
        tracing::warn!(job = %lease.job_id, frame = lease.index, worker = %lease.worker, %reason, ?kind, "frame failed");
        let counted = self
            .state
            .remove_lease(lease_id)
            .map_err(DaemonError::from)
            .and_then(|()| self.count_failure_locked(&lease, reason, kind));
        self.unless_disk_refused(&lease, counted)
    }

    fn count_failure_locked(
        &self,
        lease: &Lease,
        reason: &str,
        kind: FailureKind,
    ) -> Result<(), DaemonError> {
        self.metrics.frame_failed();
        match kind {
            FailureKind::Transient => self.count_failed_attempt_locked(lease, reason, true),
            FailureKind::Permanent => {
                let attempts = self.failed_attempts_locked(lease)? + 1;
                self.fail_job_locked(
                    &lease.job_id,
                    format!(
                        "frame {} cannot be rendered (attempt {attempts}, not retried): {reason}",
                        lease.index
                    ),
                    1,
                )
            }
        }
    }

    /// Gives a lease back without a result and without counting an attempt. Releasing a lease
    /// that is no longer held does nothing.
    pub fn release_frame(&self, lease_id: &str) -> Result<(), DaemonError> {
        let _scheduling = self.scheduling()?;
        if let Some(lease) = self.state.lease(lease_id)? {
            self.state.give_back_lease(lease_id)?;
            tracing::info!(job = %lease.job_id, frame = lease.index, worker = %lease.worker, "frame handed back");
            self.work.notify();
        }
        Ok(())
    }

    pub fn leases(&self) -> Result<Vec<Lease>, DaemonError> {
        Ok(self.state.leases()?)
    }

    /// Refuses (PermissionDenied) a call on `lease_id` from the other kind of worker than the
    /// one holding it: the embedded worker's leases are only its own, and no remote worker's
    /// are. A lease that is not held passes, for the call itself to answer.
    pub fn check_lease_holder(&self, lease_id: &str, embedded: bool) -> Result<(), DaemonError> {
        match self.state.lease(lease_id)? {
            Some(lease) if lease.embedded != embedded => {
                Err(DaemonError::PermissionDenied(format!(
                    "lease {lease_id} is held by {}",
                    if lease.embedded {
                        "the daemon's embedded worker"
                    } else {
                        "a remote worker"
                    }
                )))
            }
            _ => Ok(()),
        }
    }

    /// Whether the job of `lease` still wants its frame.
    fn is_wanted_locked(&self, lease: &Lease) -> Result<bool, DaemonError> {
        Ok(self
            .state
            .job(&lease.job_id)?
            .is_some_and(|j| !j.state.is_terminal()))
    }

    /// The failed attempts so far at the frame of `lease`.
    fn failed_attempts_locked(&self, lease: &Lease) -> Result<u32, DaemonError> {
        Ok(match self.state.frame(&lease.job_id, lease.index)? {
            Some(FrameState::Pending { attempts }) => attempts,
            _ => 0,
        })
    }

    /// Counts a failed attempt at the frame of `lease`, and when its worker is to `blame` a
    /// failed frame of the job for the worker; the job fails when the frame has used up its
    /// attempts.
    fn count_failed_attempt_locked(
        &self,
        lease: &Lease,
        reason: &str,
        blame: bool,
    ) -> Result<(), DaemonError> {
        if matches!(
            self.state.frame(&lease.job_id, lease.index)?,
            Some(FrameState::Done(_))
        ) {
            return Ok(());
        }
        let attempts = self.failed_attempts_locked(lease)? + 1;
        if attempts >= self.config.max_frame_attempts {
            return self.fail_job_locked(
                &lease.job_id,
                format!(
                    "frame {} failed {attempts} times; last: {reason}",
                    lease.index
                ),
                1,
            );
        }
        let limit = self.config.worker_failures_before_blocklist;
        let mut blocklisted = false;
        let job = self
            .state
            .count_failed_attempt(&lease.job_id, lease.index, attempts, |job| {
                if blame {
                    blocklisted = job.count_worker_failure(&lease.worker, limit);
                }
            })?;
        self.state.flush()?;
        if let Some(job) = job.filter(|_| blocklisted) {
            tracing::warn!(
                job = %job.id,
                worker = %lease.worker,
                failed_frames = limit,
                "worker blocklisted for the job: it gets no more of its frames"
            );
            self.publish(&job, None);
        }
        self.work.notify();
        Ok(())
    }

    /// Fails the job for `reason`; `unstored_attempts` failed attempts at its frame led to
    /// it and were not stored.
    fn fail_job_locked(
        &self,
        job_id: &str,
        reason: String,
        unstored_attempts: u32,
    ) -> Result<(), DaemonError> {
        let mut had_ended = false;
        if let Some(failed) = self.state.update_job(job_id, |j| {
            had_ended = j.state.is_terminal();
            j.state = JobState::Failed;
            j.error = Some(reason);
        })? {
            self.state.flush()?;
            if !had_ended {
                self.log_job_end(&failed, unstored_attempts);
            }
            self.publish(&failed, None);
        }
        Ok(())
    }
}

/// A handed-in frame must be a PNG of the job's size.
fn check_png(png: &[u8], width: u32, height: u32) -> Result<(), DaemonError> {
    let reader =
        image::ImageReader::with_format(std::io::Cursor::new(png), image::ImageFormat::Png);
    let (w, h) = reader
        .into_dimensions()
        .map_err(|e| DaemonError::invalid("png", format!("is not a readable PNG: {e}")))?;
    if (w, h) != (width, height) {
        return Err(DaemonError::invalid(
            "png",
            format!("is {w}x{h}, the job renders {width}x{height}"),
        ));
    }
    Ok(())
}

#[cfg(test)]
mod store_wait_tests;
#[cfg(test)]
mod tests;

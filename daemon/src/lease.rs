//! Frame leases: the one way frames reach workers, the embedded threads and remote worker
//! processes alike. A worker leases a pending frame, renders it, and hands the PNG in under
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
//! Every change to leases, frames and job states made here happens under one scheduling lock,
//! so two workers never get the same frame and a cancel never races a completion.

use std::collections::HashSet;
use std::time::Duration;

use pointfarm_render::request::RenderRequest;

use crate::error::DaemonError;
use crate::lease_record::Lease;
use crate::model::{now_unix_ms, FrameReport, FrameState, Job, JobState, StageTiming};
use crate::service::Daemon;

/// The dataset of a task, as a worker's cache knows it.
#[derive(Debug, Clone, PartialEq)]
pub struct TaskDataset {
    pub id: String,
    pub sha256: String,
    pub size_bytes: u64,
}

/// One leased frame with everything needed to render it.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameTask {
    pub lease: Lease,
    pub lease_timeout: Duration,
    pub dataset: TaskDataset,
    /// The job's request; the frame is `lease.index` of its camera path.
    pub request: RenderRequest,
    /// Attempts at this frame that ended without a result.
    pub failed_attempts: u32,
}

/// What a worker reports with a finished frame's PNG.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameOutcome {
    pub timings: Vec<StageTiming>,
    pub dataset_cache_hit: Option<bool>,
}

/// Whether a failed frame is worth another attempt.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FailureKind {
    /// May succeed next time: a lost GPU, an I/O error, a dead worker.
    Transient,
    /// Fails the same way every time: an unreadable dataset, a request that cannot render.
    Permanent,
}

/// The answer to a heartbeat.
#[derive(Debug, Clone, PartialEq)]
pub enum HeartbeatAnswer {
    Continue {
        expires_unix_ms: i64,
    },
    /// Drop the frame, for this reason.
    Stop(String),
}

impl Daemon {
    fn lease_timeout_ms(&self) -> i64 {
        self.config.lease_timeout.as_millis() as i64
    }

    /// Leases the next frame (highest priority, oldest job, lowest index) to `worker`, or
    /// None when there is nothing to render.
    pub fn lease_frame(
        &self,
        worker: &str,
        embedded: bool,
    ) -> Result<Option<FrameTask>, DaemonError> {
        let _scheduling = self.scheduling()?;
        self.expire_leases_locked()?;
        let leased: HashSet<(String, u32)> = self
            .store
            .leases()?
            .into_iter()
            .map(|l| (l.job_id, l.index))
            .collect();
        loop {
            let Some((job, index)) = self.store.next_task(&leased)? else {
                return Ok(None);
            };
            let Some(dataset) = self.store.dataset(&job.spec.dataset_id)? else {
                self.fail_job_locked(
                    &job.id,
                    format!("dataset {} no longer exists", job.spec.dataset_id),
                )?;
                continue;
            };
            let failed_attempts = match self.store.frame(&job.id, index)? {
                Some(FrameState::Pending { attempts }) => attempts,
                _ => 0,
            };
            let job = if job.state == JobState::Queued {
                let running = self
                    .store
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
            };
            self.store.put_lease(&lease)?;
            // Durable before the worker starts: a crash of the daemon while the frame renders
            // then still counts the attempt at the next start.
            self.store.flush()?;
            tracing::debug!(job = %job.id, frame = index, lease = %lease.id, worker, "frame leased");
            return Ok(Some(FrameTask {
                lease,
                lease_timeout: self.config.lease_timeout,
                dataset: TaskDataset {
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
        let lease = self.store.lease(lease_id)?.ok_or_else(|| {
            DaemonError::FailedPrecondition(format!(
                "lease {lease_id} is not held (it expired, or its frame was given to another worker)"
            ))
        })?;
        let job = self.store.job(&lease.job_id)?;
        match job {
            Some(job) if !job.state.is_terminal() => Ok((lease, job)),
            other => {
                self.store.remove_lease(lease_id)?;
                let state = other.map(|j| format!("{:?}", j.state).to_lowercase());
                Err(DaemonError::FailedPrecondition(format!(
                    "job {} has ended ({}); frame {} is no longer wanted",
                    lease.job_id,
                    state.as_deref().unwrap_or("deleted"),
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
                lease.expires_unix_ms = now_unix_ms() + self.lease_timeout_ms();
                self.store.put_lease(&lease)?;
                Ok(HeartbeatAnswer::Continue {
                    expires_unix_ms: lease.expires_unix_ms,
                })
            }
            Err(DaemonError::FailedPrecondition(reason)) => Ok(HeartbeatAnswer::Stop(reason)),
            Err(e) => Err(e),
        }
    }

    /// Stores the PNG of a leased frame and marks the frame done. Refused (FailedPrecondition)
    /// when the lease is no longer held; then nothing is written over.
    pub fn complete_frame(
        &self,
        lease_id: &str,
        png: &[u8],
        outcome: FrameOutcome,
    ) -> Result<Job, DaemonError> {
        let (lease, width, height) = self.held_lease(lease_id)?;
        check_png(png, width, height)?;
        // Written outside the lock under a name of this lease; renamed into place only if the
        // lease is still held then.
        let path = self.config.frame_path(&lease.job_id, lease.index);
        let partial = path.with_extension(format!("{lease_id}.part"));
        std::fs::create_dir_all(self.config.frames_dir(&lease.job_id))?;
        std::fs::write(&partial, png)?;

        let _scheduling = self.scheduling()?;
        let checked = (|| {
            self.expire_leases_locked()?;
            self.held_lease_locked(lease_id)?;
            match self.store.frame(&lease.job_id, lease.index)? {
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
                return Err(e);
            }
        };
        // The rename makes the frame appear whole or not at all; it is marked done only after.
        std::fs::rename(&partial, &path)?;
        let report = FrameReport {
            index: lease.index,
            timings: outcome.timings,
            dataset_cache_hit: outcome.dataset_cache_hit,
            failed_attempts,
        };
        self.store.set_frame(
            &lease.job_id,
            lease.index,
            &FrameState::Done(report.clone()),
        )?;
        self.store.remove_lease(lease_id)?;
        let job = self
            .store
            .update_job(&lease.job_id, |j| {
                j.frames_done += 1;
                if j.frames_done >= j.frames_total {
                    j.state = JobState::Succeeded;
                }
            })?
            .ok_or_else(|| DaemonError::NotFound(format!("job {}", lease.job_id)))?;
        self.store.flush()?;
        self.publish(&job, Some(report));
        Ok(job)
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
        self.store.remove_lease(lease_id)?;
        tracing::warn!(job = %lease.job_id, frame = lease.index, worker = %lease.worker, %reason, ?kind, "frame failed");
        match kind {
            FailureKind::Transient => self.count_failed_attempt_locked(&lease, reason),
            FailureKind::Permanent => {
                let attempts = self.failed_attempts_locked(&lease)? + 1;
                self.fail_job_locked(
                    &lease.job_id,
                    format!(
                        "frame {} cannot be rendered (attempt {attempts}, not retried): {reason}",
                        lease.index
                    ),
                )
            }
        }
    }

    /// The embedded worker `worker` exited (`how`: its exit status): each frame it held
    /// counts a failed attempt and goes back to the queue. Returns how many it held.
    pub fn embedded_worker_exited(&self, worker: &str, how: &str) -> Result<usize, DaemonError> {
        let _scheduling = self.scheduling()?;
        self.count_embedded_leases_locked(|lease| {
            (lease.worker == worker).then(|| {
                format!(
                    "worker {worker} died while rendering frame {} ({how})",
                    lease.index
                )
            })
        })
    }

    /// At start-up: the embedded worker died with the previous daemon, so each frame it held
    /// counts a failed attempt, as if it had exited now. Returns how many it held.
    pub fn count_leases_of_previous_run(&self) -> Result<usize, DaemonError> {
        let _scheduling = self.scheduling()?;
        let counted = self.count_embedded_leases_locked(|lease| {
            Some(format!(
                "worker {} died while rendering frame {} (the daemon stopped)",
                lease.worker, lease.index
            ))
        })?;
        if counted > 0 {
            tracing::warn!(
                counted,
                "the previous run's embedded worker held frames: each counts a failed attempt"
            );
        }
        Ok(counted)
    }

    /// Removes the embedded leases for which `reason` gives a reason, counting an attempt each.
    fn count_embedded_leases_locked(
        &self,
        reason: impl Fn(&Lease) -> Option<String>,
    ) -> Result<usize, DaemonError> {
        let mut counted = 0;
        for lease in self.store.leases()? {
            let Some(reason) = lease.embedded.then(|| reason(&lease)).flatten() else {
                continue;
            };
            self.store.remove_lease(&lease.id)?;
            if self.is_wanted_locked(&lease)? {
                tracing::warn!(job = %lease.job_id, frame = lease.index, %reason, "frame lost");
                self.count_failed_attempt_locked(&lease, &reason)?;
                counted += 1;
            }
        }
        self.store.flush()?;
        Ok(counted)
    }

    /// Gives a lease back without a result and without counting an attempt. Releasing a lease
    /// that is no longer held does nothing.
    pub fn release_frame(&self, lease_id: &str) -> Result<(), DaemonError> {
        let _scheduling = self.scheduling()?;
        if let Some(lease) = self.store.lease(lease_id)? {
            self.store.remove_lease(lease_id)?;
            tracing::info!(job = %lease.job_id, frame = lease.index, worker = %lease.worker, "frame handed back");
            self.work.notify();
        }
        Ok(())
    }

    pub fn leases(&self) -> Result<Vec<Lease>, DaemonError> {
        Ok(self.store.leases()?)
    }

    /// Refuses (PermissionDenied) a call on `lease_id` from the other kind of worker than the
    /// one holding it: the embedded worker's leases are only its own, and no remote worker's
    /// are. A lease that is not held passes, for the call itself to answer.
    pub fn check_lease_holder(&self, lease_id: &str, embedded: bool) -> Result<(), DaemonError> {
        match self.store.lease(lease_id)? {
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

    /// Puts the frames of expired leases back in the queue, counting the attempts. Returns how
    /// many leases expired.
    pub fn expire_leases(&self) -> Result<usize, DaemonError> {
        let _scheduling = self.scheduling()?;
        self.expire_leases_locked()
    }

    fn expire_leases_locked(&self) -> Result<usize, DaemonError> {
        let now = now_unix_ms();
        let mut expired = 0;
        for lease in self.store.leases()? {
            if lease.expires_unix_ms >= now {
                continue;
            }
            self.store.remove_lease(&lease.id)?;
            // A lease of an ended job is kept until it runs out, so that its holder's
            // heartbeat learns why to stop; its expiry counts nothing.
            if self.is_wanted_locked(&lease)? {
                tracing::warn!(
                    job = %lease.job_id,
                    frame = lease.index,
                    worker = %lease.worker,
                    "lease expired: the worker was lost; the frame goes back to the queue"
                );
                self.count_failed_attempt_locked(
                    &lease,
                    &format!(
                        "worker {} stopped renewing its lease (no heartbeat for {:?})",
                        lease.worker, self.config.lease_timeout
                    ),
                )?;
                expired += 1;
            }
        }
        Ok(expired)
    }

    /// Whether the job of `lease` still wants its frame.
    fn is_wanted_locked(&self, lease: &Lease) -> Result<bool, DaemonError> {
        Ok(self
            .store
            .job(&lease.job_id)?
            .is_some_and(|j| !j.state.is_terminal()))
    }

    /// The failed attempts so far at the frame of `lease`.
    fn failed_attempts_locked(&self, lease: &Lease) -> Result<u32, DaemonError> {
        Ok(match self.store.frame(&lease.job_id, lease.index)? {
            Some(FrameState::Pending { attempts }) => attempts,
            _ => 0,
        })
    }

    fn count_failed_attempt_locked(&self, lease: &Lease, reason: &str) -> Result<(), DaemonError> {
        if matches!(
            self.store.frame(&lease.job_id, lease.index)?,
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
            );
        }
        self.store.set_frame(
            &lease.job_id,
            lease.index,
            &FrameState::Pending { attempts },
        )?;
        self.store.flush()?;
        self.work.notify();
        Ok(())
    }

    fn fail_job_locked(&self, job_id: &str, reason: String) -> Result<(), DaemonError> {
        tracing::warn!(job = %job_id, %reason, "job failed");
        if let Some(failed) = self.store.update_job(job_id, |j| {
            j.state = JobState::Failed;
            j.error = Some(reason);
        })? {
            self.store.flush()?;
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
mod tests {
    use std::path::Path;
    use std::sync::Arc;

    use pointfarm_proto::v1 as pb;

    use super::*;
    use crate::service::DaemonConfig;

    fn open(dir: &Path) -> Arc<Daemon> {
        let mut config = DaemonConfig::new(dir.join("data"));
        config.data_roots = vec![dir.join("roots")];
        config.lease_timeout = Duration::from_secs(60);
        Daemon::open(config).expect("open")
    }

    fn png(width: u32, height: u32) -> Vec<u8> {
        let mut bytes = Vec::new();
        image::RgbaImage::new(width, height)
            .write_to(
                &mut std::io::Cursor::new(&mut bytes),
                image::ImageFormat::Png,
            )
            .expect("encode");
        bytes
    }

    /// Leases the next frame, which there must be.
    fn lease(daemon: &Daemon, worker: &str, embedded: bool) -> FrameTask {
        daemon
            .lease_frame(worker, embedded)
            .expect("lease")
            .expect("a frame to lease")
    }

    fn outcome() -> FrameOutcome {
        FrameOutcome {
            timings: Vec::new(),
            dataset_cache_hit: None,
        }
    }

    #[test]
    fn remote_leases_survive_a_restart_and_embedded_ones_count_an_attempt() {
        let (dir, daemon, job) = daemon_with_job(3);
        let remote = lease(&daemon, "remote", false);
        let embedded = lease(&daemon, "embedded", true);
        assert_eq!((remote.lease.index, embedded.lease.index), (0, 1));
        drop(daemon);

        let daemon = open(dir.path());
        let leases = daemon.leases().expect("leases");
        assert_eq!(
            leases,
            vec![remote.lease.clone()],
            "only the remote lease is left"
        );
        let again = lease(&daemon, "embedded", true);
        assert_eq!(
            (again.lease.index, again.failed_attempts),
            (1, 1),
            "the embedded frame is back, with the attempt its dead worker made"
        );
        // The remote worker that rendered through the restart hands its frame in.
        let after = daemon
            .complete_frame(&remote.lease.id, &png(8, 6), outcome())
            .expect("complete");
        assert_eq!(after.frames_done, 1);
        assert!(daemon.config.frame_path(&job.id, 0).is_file());
        let refused = daemon.complete_frame(&remote.lease.id, &png(8, 6), outcome());
        assert!(matches!(refused, Err(DaemonError::FailedPrecondition(_))));
    }

    /// A daemon in a new folder with one job of `frames` frames on a registered (never
    /// decoded) file.
    fn daemon_with_job(frames: u32) -> (tempfile::TempDir, Arc<Daemon>, crate::model::Job) {
        let folder = tempfile::tempdir().expect("tempdir");
        let dir = folder.path();
        std::fs::create_dir_all(dir.join("roots")).expect("roots");
        std::fs::write(dir.join("roots/a.las"), b"points").expect("file");
        let daemon = open(dir);
        let dataset = daemon.register_dataset("a.las", "").expect("register");
        let request = pb::SubmitJobRequest {
            dataset_id: dataset.id.clone(),
            camera_path: Some(pb::CameraPath::turntable(pb::Turntable::of_frames(frames))),
            width: 8,
            height: 6,
            ..Default::default()
        };
        let job = daemon
            .submit_job(crate::model::JobSpec::try_from(&request).expect("spec"))
            .expect("submit");
        (folder, daemon, job)
    }

    #[test]
    fn a_permanent_failure_fails_the_job_at_once_and_a_transient_one_retries() {
        let (_dir, daemon, job) = daemon_with_job(2);
        let task = lease(&daemon, "w", false);
        daemon
            .fail_frame(&task.lease.id, "GPU lost", FailureKind::Transient)
            .expect("fail");
        assert_eq!(daemon.job(&job.id).expect("job").state, JobState::Running);
        let again = lease(&daemon, "w", false);
        assert_eq!((again.lease.index, again.failed_attempts), (0, 1));
        daemon
            .fail_frame(&again.lease.id, "not a LAS file", FailureKind::Permanent)
            .expect("fail");
        let failed = daemon.job(&job.id).expect("job");
        assert_eq!(failed.state, JobState::Failed);
        assert_eq!(
            failed.error.as_deref(),
            Some("frame 0 cannot be rendered (attempt 2, not retried): not a LAS file")
        );
    }

    #[test]
    fn an_exited_embedded_worker_counts_an_attempt_for_its_frames_only() {
        let (_dir, daemon, job) = daemon_with_job(3);
        let child = lease(&daemon, "embedded", true);
        let remote = lease(&daemon, "remote", false);
        let counted = daemon
            .embedded_worker_exited("embedded", "killed by signal 9 (SIGKILL)")
            .expect("exited");
        assert_eq!(counted, 1);
        assert_eq!(daemon.leases().expect("leases"), vec![remote.lease]);
        let again = lease(&daemon, "embedded", true);
        assert_eq!(
            (again.lease.index, again.failed_attempts),
            (child.lease.index, 1)
        );
        // The last allowed attempt dies too: the job fails, saying how.
        daemon
            .embedded_worker_exited("embedded", "killed by signal 6 (SIGABRT)")
            .expect("exited");
        let third = lease(&daemon, "embedded", true);
        assert_eq!(third.failed_attempts, 2);
        daemon
            .embedded_worker_exited("embedded", "killed by signal 6 (SIGABRT)")
            .expect("exited");
        let failed = daemon.job(&job.id).expect("job");
        assert_eq!(failed.state, JobState::Failed);
        assert_eq!(
            failed.error.as_deref(),
            Some(
                "frame 0 failed 3 times; last: worker embedded died while rendering frame 0 \
                 (killed by signal 6 (SIGABRT))"
            )
        );
    }
}

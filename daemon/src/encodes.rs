//! Videos made on the farm. A job whose spec asks for a video (`JobSpec::video`) stays
//! running once its last frame is final, at its "video" stage, until a worker has made the
//! video and handed it in; then it succeeds. The video is made under an encode lease: a lease
//! of its own, never a frame's, leased only to a worker whose ffmpeg has the job's encoder,
//! renewed within the daemon's lease timeout, and leased again when its worker fails it or
//! stops renewing it, each counting one of [`MAX_ENCODE_ATTEMPTS`]; the last failure fails
//! the job with ffmpeg's words. A worker stopping gives its lease back, counting nothing. The lease and its attempts are stored with the job in sled,
//! so they outlive a restart; the video is stored beside the job's frames, in the job's
//! folder, and goes with it.
//!
//! A job that asks for a video and for previews also has a preview video: once every frame
//! has a preview (or is final) while its final frames are still rendering, one encode of
//! those images is leased the same way under a lease of its own ([`preview`]), stored as
//! `preview_video.*` beside the final video. Its failures never fail the job, and it is not
//! leased once the final frames are all done: the final video supersedes it.
//!
//! Every change happens under the scheduling lock that frame leases take, so a cancel never
//! races a handed-in video.

use std::io::Write;
use std::path::{Path, PathBuf};

pub use crate::encode_record::{EncodeLease, EncodeState, VideoKind, VideoProgress};
use crate::error::DaemonError;
use crate::lease::HeartbeatAnswer;
use crate::lease_record::Lease;
use crate::model::{now_unix_ms, Job, JobState};
use crate::service::{Daemon, DaemonConfig};
use pointfarm_render::encode::video::{VideoCodec, VideoContainer, VideoSettings};

pub mod preview;
#[cfg(test)]
mod tests;
mod waiting;

/// Attempts at a job's video before the job fails.
pub const MAX_ENCODE_ATTEMPTS: u32 = 3;
/// The largest video a worker may hand in.
pub const MAX_VIDEO_BYTES: u64 = 8 << 30;

/// Everything a worker needs to make one job's video.
#[derive(Debug, Clone, PartialEq)]
pub struct EncodeTask {
    pub lease_id: String,
    pub expires_unix_ms: i64,
    pub lease_timeout: std::time::Duration,
    pub job_id: String,
    pub frames: u32,
    pub width: u32,
    pub height: u32,
    pub video: VideoSettings,
    pub failed_attempts: u32,
    pub max_video_bytes: u64,
}

impl Job {
    /// What the job is doing: "frames", "video" once every frame is final and its video is
    /// being made, "" once it has ended.
    pub fn stage(&self) -> &'static str {
        if self.state.is_terminal() {
            ""
        } else if self.awaits_video() {
            "video"
        } else {
            "frames"
        }
    }

    /// Whether every frame is final and the video asked for is not stored yet.
    pub fn awaits_video(&self) -> bool {
        self.spec.video.is_some()
            && self.frames_done >= self.frames_total
            && self.video_size_bytes().is_none()
    }

    /// The stored video's size.
    pub fn video_size_bytes(&self) -> Option<u64> {
        self.encode.as_ref().and_then(|e| e.video.video_size_bytes)
    }

    /// Whether its final video is due and not leased.
    pub fn wants_final_encode(&self) -> bool {
        self.awaits_video() && self.encode.as_ref().is_none_or(|e| e.video.lease.is_none())
    }

    /// Its `kind` video, to change; a record without one starts it.
    pub fn video_mut(&mut self, kind: VideoKind) -> &mut VideoProgress {
        self.encode
            .get_or_insert_with(Default::default)
            .of_mut(kind)
    }

    /// Whether the job is done when its last frame is: it asks for no video.
    pub fn ends_with_last_frame(&self) -> bool {
        self.spec.video.is_none()
    }
}

impl DaemonConfig {
    /// Where job `job_id`'s video is stored: beside its frames, named by its container.
    pub fn video_path(&self, job_id: &str, container: VideoContainer) -> PathBuf {
        self.frames_dir(job_id)
            .join(format!("video.{}", container.extension()))
    }
}

/// The encoders among `listed` that the farm's videos use (each codec's, and `gif`), once
/// each: what a worker's capabilities keep of its ffmpeg's list, so its size stays bounded.
pub fn known_encoders(listed: &[String]) -> Vec<String> {
    let known = VideoCodec::ALL.map(VideoCodec::encoder);
    let mut kept: Vec<String> = Vec::new();
    for name in listed {
        let is_known = known.contains(&name.as_str()) || name == "gif";
        if is_known && !kept.contains(name) {
            kept.push(name.clone());
        }
    }
    kept
}

/// Why a worker with `encoders` cannot make the video of a job asking for `video`.
pub fn encode_refusal(encoders: &[String], video: &VideoSettings) -> Option<String> {
    let needed = video.encoder();
    if encoders.is_empty() {
        Some("the worker makes no videos (no ffmpeg, or `worker --no-videos`)".into())
    } else if !encoders.iter().any(|e| e == needed) {
        Some(format!("the worker's ffmpeg has no {needed} encoder"))
    } else {
        None
    }
}

/// A video being handed in: written under its lease's name, renamed into place when whole.
pub struct VideoUpload {
    lease_id: String,
    embedded: bool,
    job_id: String,
    declared: u64,
    written: u64,
    partial: PathBuf,
    file: std::fs::File,
}

impl VideoUpload {
    /// Moves the whole video into its place at `path`; returns its size.
    fn store_at(&self, path: &Path) -> Result<u64, DaemonError> {
        std::fs::rename(&self.partial, path)
            .map_err(|e| DaemonError::ResourceExhausted(format!("storing the video: {e}")))?;
        Ok(self.written)
    }

    /// Appends a part of the video; refused past the declared size.
    pub fn write(&mut self, bytes: &[u8]) -> Result<(), DaemonError> {
        if self.written + bytes.len() as u64 > self.declared {
            return Err(DaemonError::invalid(
                "result.size_bytes",
                format!("more than the declared {} bytes", self.declared),
            ));
        }
        self.written += bytes.len() as u64;
        self.file
            .write_all(bytes)
            .map_err(|e| DaemonError::ResourceExhausted(format!("storing the video: {e}")))
    }
}

impl Drop for VideoUpload {
    fn drop(&mut self) {
        // Renamed away when stored; anything left is a part that never became a video.
        let _ = std::fs::remove_file(&self.partial);
    }
}

impl Daemon {
    /// Leases the video of the oldest unfinished job whose frames are all final to `worker`,
    /// whose ffmpeg has `encoders`; None when there is none it can make.
    pub fn lease_encode(
        &self,
        worker: &str,
        embedded: bool,
        encoders: &[String],
    ) -> Result<Option<EncodeTask>, DaemonError> {
        let _scheduling = self.scheduling()?;
        if let Some(outage) = self.state.outage() {
            return Err(DaemonError::ResourceExhausted(outage));
        }
        self.expire_encodes_locked()?;
        let mut waiting: Vec<Job> = self
            .state
            .unfinished_jobs()?
            .into_iter()
            .filter(|job| matches!(job.state, JobState::Queued | JobState::Running))
            .filter(|job| job.wants_final_encode() || job.may_make_preview_video())
            .collect();
        waiting.sort_by_key(|job| (std::cmp::Reverse(job.spec.priority), job.created_unix_ms));
        let timeout = self.config.lease_timeout;
        for job in waiting {
            let Some(video) = job.spec.video else {
                continue;
            };
            if encode_refusal(encoders, &video).is_some() {
                continue;
            }
            let kind = if job.wants_final_encode() {
                VideoKind::Final
            } else if self.preview_video_due(&job)? {
                VideoKind::Preview
            } else {
                continue;
            };
            let now = now_unix_ms();
            let lease = EncodeLease {
                id: Lease::new_id(),
                worker: worker.to_owned(),
                embedded,
                expires_unix_ms: now + timeout.as_millis() as i64,
                leased_unix_ms: now,
            };
            let leased = lease.clone();
            let Some(job) = self.state.update_job(&job.id, |j| {
                j.state = JobState::Running;
                j.video_mut(kind).lease = Some(leased);
            })?
            else {
                continue;
            };
            self.state.flush()?;
            self.metrics.encodes.leased();
            tracing::info!(job = %job.id, worker, "{} leased", kind.name());
            self.publish(&job, None);
            return Ok(Some(EncodeTask {
                lease_id: lease.id,
                expires_unix_ms: lease.expires_unix_ms,
                lease_timeout: timeout,
                job_id: job.id.clone(),
                frames: job.frames_total,
                width: job.spec.request.width,
                height: job.spec.request.height,
                video,
                failed_attempts: job.encode.map_or(0, |e| e.of(kind).failed_attempts),
                max_video_bytes: MAX_VIDEO_BYTES,
            }));
        }
        Ok(None)
    }

    /// The job whose encode lease is `lease_id` and the video it makes, while the lease is
    /// held and the job wants that video; FailedPrecondition saying why not otherwise.
    fn encode_job_locked(
        &self,
        lease_id: &str,
        embedded: bool,
    ) -> Result<(Job, EncodeLease, VideoKind), DaemonError> {
        let not_held = || {
            DaemonError::FailedPrecondition(format!(
                "encode lease {lease_id} is not held (it expired, or the video was leased again)"
            ))
        };
        // The lease names no job, and a job holds two encode leases at most: the unfinished
        // jobs are looked through, never every job.
        let (job, kind, lease) = self
            .state
            .unfinished_jobs()?
            .into_iter()
            .find_map(|job| {
                let (kind, lease) = job
                    .encode
                    .as_ref()?
                    .leases()
                    .find(|(_, lease)| lease.id == lease_id)
                    .map(|(kind, lease)| (kind, lease.clone()))?;
                Some((job, kind, lease))
            })
            .ok_or_else(not_held)?;
        if lease.embedded != embedded {
            return Err(DaemonError::PermissionDenied(format!(
                "encode lease {lease_id} is held by another kind of worker"
            )));
        }
        // A preview video once leased is made even if the final frames end meanwhile.
        let wanted = match kind {
            VideoKind::Final => job.awaits_video(),
            VideoKind::Preview => job.spec.video.is_some(),
        };
        if !wanted || job.state == JobState::Paused {
            return Err(DaemonError::FailedPrecondition(format!(
                "job {} no longer wants its {} ({})",
                job.id,
                kind.name(),
                job.state.name()
            )));
        }
        Ok((job, lease, kind))
    }

    /// The job of a held encode lease: what the holder may fetch the frames of.
    pub fn encode_job(&self, lease_id: &str, embedded: bool) -> Result<Job, DaemonError> {
        let _scheduling = self.scheduling()?;
        self.expire_encodes_locked()?;
        Ok(self.encode_job_locked(lease_id, embedded)?.0)
    }

    /// Extends an encode lease, or says why its holder should stop.
    pub fn renew_encode(
        &self,
        lease_id: &str,
        embedded: bool,
    ) -> Result<HeartbeatAnswer, DaemonError> {
        let _scheduling = self.scheduling()?;
        self.expire_encodes_locked()?;
        let (job, lease, kind) = match self.encode_job_locked(lease_id, embedded) {
            Ok(held) => held,
            Err(DaemonError::FailedPrecondition(reason)) => {
                return Ok(HeartbeatAnswer::Stop(reason))
            }
            Err(e) => return Err(e),
        };
        self.workers.heard_from_named(&lease.worker);
        let expires_unix_ms = now_unix_ms() + self.config.lease_timeout.as_millis() as i64;
        if self.state.outage().is_none() {
            self.state.update_job(&job.id, |j| {
                if let Some(lease) = j
                    .encode
                    .as_mut()
                    .and_then(|e| e.of_mut(kind).lease.as_mut())
                {
                    lease.expires_unix_ms = expires_unix_ms;
                }
            })?;
        }
        Ok(HeartbeatAnswer::Continue { expires_unix_ms })
    }

    /// Starts taking in the video of encode lease `lease_id`, of `size_bytes`: refused when
    /// the lease is not held or the video is larger than [`MAX_VIDEO_BYTES`].
    pub fn start_video_upload(
        &self,
        lease_id: &str,
        embedded: bool,
        size_bytes: u64,
    ) -> Result<VideoUpload, DaemonError> {
        if size_bytes > MAX_VIDEO_BYTES {
            return Err(DaemonError::invalid(
                "result.size_bytes",
                format!("a video may have at most {MAX_VIDEO_BYTES} bytes, got {size_bytes}"),
            ));
        }
        if size_bytes == 0 {
            return Err(DaemonError::invalid(
                "result.size_bytes",
                "the video is empty",
            ));
        }
        let job = self.encode_job(lease_id, embedded)?;
        let folder = self.config.frames_dir(&job.id);
        let partial = folder.join(format!("video.{lease_id}.part"));
        let file = std::fs::create_dir_all(&folder)
            .and_then(|()| std::fs::File::create(&partial))
            .map_err(|e| DaemonError::ResourceExhausted(format!("storing the video: {e}")))?;
        Ok(VideoUpload {
            lease_id: lease_id.to_owned(),
            embedded,
            job_id: job.id,
            declared: size_bytes,
            written: 0,
            partial,
            file,
        })
    }

    /// Stores a whole handed-in video beside the job's frames, and with its final video the
    /// job succeeds (a preview video leaves it as it was); refused when the lease was lost
    /// meanwhile, and then nothing is stored.
    pub fn finish_video_upload(&self, upload: VideoUpload) -> Result<Job, DaemonError> {
        if upload.written != upload.declared {
            return Err(DaemonError::invalid(
                "result.size_bytes",
                format!(
                    "declared {} bytes, received {}",
                    upload.declared, upload.written
                ),
            ));
        }
        upload
            .file
            .sync_all()
            .map_err(|e| DaemonError::ResourceExhausted(format!("storing the video: {e}")))?;
        let _scheduling = self.scheduling()?;
        self.expire_encodes_locked()?;
        let (job, lease, kind) = self.encode_job_locked(&upload.lease_id, upload.embedded)?;
        let video = job.spec.video.ok_or_else(|| {
            DaemonError::Internal(format!("job {} asks for no video", upload.job_id))
        })?;
        let path = match kind {
            VideoKind::Final => self.config.video_path(&job.id, video.container),
            VideoKind::Preview => self.config.preview_video_path(&job.id, video.container),
        };
        let size = upload.store_at(&path)?;
        let job = self
            .state
            .update_job(&job.id, |j| {
                j.video_mut(kind).stored(size);
                // A preview video leaves the job as it was.
                if kind == VideoKind::Final {
                    j.state = JobState::Succeeded;
                }
            })?
            .ok_or_else(|| DaemonError::NotFound(format!("job {}", upload.job_id)))?;
        self.state.flush()?;
        self.count_stored_video(&lease);
        tracing::info!(job = %job.id, bytes = size, "{} stored", kind.name());
        if kind == VideoKind::Final {
            self.enqueue_video_output(&job, &path);
            self.log_job_end(&job, 0);
        }
        self.publish(&job, None);
        Ok(job)
    }

    /// Counts a stored video in the metrics, with how long its lease was held.
    fn count_stored_video(&self, lease: &EncodeLease) {
        // A lease stored without its start has no time to tell.
        let took = (lease.leased_unix_ms > 0)
            .then(|| (now_unix_ms() - lease.leased_unix_ms).max(0) as f64 / 1e3);
        self.metrics.encodes.succeeded(took);
    }

    /// The video could not be made: counts a failed attempt; the job fails with `reason`
    /// once the encode has used up its attempts.
    pub fn fail_encode(
        &self,
        lease_id: &str,
        embedded: bool,
        reason: &str,
    ) -> Result<(), DaemonError> {
        let _scheduling = self.scheduling()?;
        self.expire_encodes_locked()?;
        let (job, lease, kind) = self.encode_job_locked(lease_id, embedded)?;
        self.count_failed_encode_locked(&job, &lease, kind, reason)
    }

    /// Its worker is stopping: the encode lease is given back without a video and without
    /// counting an attempt, for another worker to lease at once. A lease no longer held (it
    /// expired, or the job no longer wants its video) has nothing to give back.
    pub fn release_encode(&self, lease_id: &str, embedded: bool) -> Result<(), DaemonError> {
        let _scheduling = self.scheduling()?;
        self.expire_encodes_locked()?;
        let (job, lease, kind) = match self.encode_job_locked(lease_id, embedded) {
            Ok(held) => held,
            Err(DaemonError::FailedPrecondition(_)) => return Ok(()),
            Err(e) => return Err(e),
        };
        let updated = self.state.update_job(&job.id, |j| {
            if let Some(encode) = j.encode.as_mut() {
                encode.of_mut(kind).lease = None;
            }
        })?;
        self.state.flush()?;
        tracing::info!(job = %job.id, worker = %lease.worker, "{} handed back", kind.name());
        if let Some(job) = updated {
            self.publish(&job, None);
        }
        self.work.notify();
        Ok(())
    }

    /// Takes the `kind` encode lease of `job` back, counting a failed attempt, and fails the
    /// job when that was its final video's last; after a preview video's last, the job has no
    /// preview video and goes on.
    fn count_failed_encode_locked(
        &self,
        job: &Job,
        lease: &EncodeLease,
        kind: VideoKind,
        reason: &str,
    ) -> Result<(), DaemonError> {
        let failed = job
            .encode
            .as_ref()
            .map_or(0, |e| e.of(kind).failed_attempts)
            + 1;
        tracing::warn!(job = %job.id, worker = %lease.worker, attempt = failed, reason, "{} failed", kind.name());
        let fails_job = kind == VideoKind::Final && failed >= MAX_ENCODE_ATTEMPTS;
        self.metrics.encodes.failed();
        let updated = self.state.update_job(&job.id, |j| {
            j.video_mut(kind).failed(failed);
            if fails_job {
                j.state = JobState::Failed;
                j.error = Some(format!(
                    "the video failed {failed} times; last, on worker {}: {reason}",
                    lease.worker
                ));
            }
        })?;
        self.state.flush()?;
        if let Some(job) = updated {
            if fails_job {
                self.log_job_end(&job, 0);
            }
            self.publish(&job, None);
        }
        self.work.notify();
        Ok(())
    }

    /// Runs again a failed job whose frames are all final but whose video failed: its video
    /// is leased again with its attempts counted from zero.
    pub(crate) fn retry_video_locked(&self, job: &Job) -> Result<Job, DaemonError> {
        // Through the requeue, which puts the job back in the index of unfinished jobs; it has
        // no pending frame to queue.
        let retried = self
            .state
            .requeue_unfinished_frames(&job.id, |j| {
                j.state = JobState::Running;
                j.error = None;
                // The preview video stored stays; one being made was lost with the failure.
                let preview = j.encode.take().map(|e| e.preview).unwrap_or_default();
                j.encode = Some(EncodeState {
                    preview: VideoProgress {
                        lease: None,
                        ..preview
                    },
                    ..EncodeState::default()
                });
            })?
            .ok_or_else(|| DaemonError::NotFound(format!("job {}", job.id)))?;
        self.state.flush()?;
        tracing::info!(job = %job.id, "the failed job's video is leased again");
        self.publish(&retried, None);
        self.work.notify();
        Ok(retried)
    }

    /// Takes back the encode leases whose workers stopped renewing them, each counting a
    /// failed attempt. Returns how many expired.
    pub fn expire_encodes(&self) -> Result<usize, DaemonError> {
        let _scheduling = self.scheduling()?;
        self.expire_encodes_locked()
    }

    fn expire_encodes_locked(&self) -> Result<usize, DaemonError> {
        // No holder can renew while the disk refuses writes: nothing runs out meanwhile.
        if self.state.outage().is_some() {
            return Ok(0);
        }
        let now = now_unix_ms();
        let mut expired = 0;
        for job in self.state.unfinished_jobs()? {
            for (kind, lease) in held_leases(&job) {
                if lease.expires_unix_ms >= now {
                    continue;
                }
                let reason = format!(
                    "worker {} stopped renewing its encode lease (no renewal for {:?})",
                    lease.worker, self.config.lease_timeout
                );
                // Read again: taking back one of its leases changed the job.
                let Some(job) = self.state.job(&job.id)? else {
                    break;
                };
                self.count_failed_encode_locked(&job, &lease, kind, &reason)?;
                expired += 1;
            }
        }
        Ok(expired)
    }

    /// The embedded worker `worker` exited: the video it was making is leased again, its
    /// attempt counted. Returns how many it held.
    pub fn embedded_encoder_exited(&self, worker: &str, how: &str) -> Result<usize, DaemonError> {
        let _scheduling = self.scheduling()?;
        let mut lost = 0;
        for job in self.state.unfinished_jobs()? {
            for (kind, lease) in held_leases(&job) {
                if lease.embedded && lease.worker == worker {
                    let reason = format!(
                        "worker {worker} died while making the {} ({how})",
                        kind.name()
                    );
                    let Some(job) = self.state.job(&job.id)? else {
                        break;
                    };
                    self.count_failed_encode_locked(&job, &lease, kind, &reason)?;
                    lost += 1;
                }
            }
        }
        Ok(lost)
    }

    /// Job `job_id`'s stored video: its file, size and container. FailedPrecondition while
    /// it has none, saying why.
    pub fn video(&self, job_id: &str) -> Result<(PathBuf, u64, VideoContainer), DaemonError> {
        let job = self.job(job_id)?;
        let Some(video) = job.spec.video else {
            return Err(DaemonError::FailedPrecondition(format!(
                "job {job_id} asked for no video"
            )));
        };
        match job.video_size_bytes() {
            Some(size) => Ok((
                self.config.video_path(job_id, video.container),
                size,
                video.container,
            )),
            None => Err(DaemonError::FailedPrecondition(format!(
                "job {job_id} has no video yet: it is {}{}",
                job.state.name(),
                match job.stage() {
                    "" => String::new(),
                    stage => format!(", at its {stage} stage"),
                }
            ))),
        }
    }
}

/// The encode leases `job` holds and the video each makes, copied out of it.
fn held_leases(job: &Job) -> Vec<(VideoKind, EncodeLease)> {
    job.encode.as_ref().map_or_else(Vec::new, |e| {
        e.leases()
            .map(|(kind, lease)| (kind, lease.clone()))
            .collect()
    })
}

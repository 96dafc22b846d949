//! A preview job's preview video: the images a job with previews has while its final frames
//! render, made into a video once every frame has one. Leased as the final video is, under
//! a lease of its own (at most one per job), stored beside it, and never leased once the
//! final frames are all done; its failures only end it, the job goes on.

use std::path::PathBuf;

use pointfarm_render::encode::video::VideoContainer;

use super::MAX_ENCODE_ATTEMPTS;
use crate::error::DaemonError;
use crate::model::Job;
use crate::service::{Daemon, DaemonConfig};

/// Where a job's preview video stands.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PreviewVideoState {
    /// The job asked for no previews or no video.
    NotAsked,
    /// Not every frame has an image yet.
    Waiting,
    /// A worker holds its encode lease.
    Encoding,
    /// Stored, this many bytes long.
    Ready(u64),
    /// Out of attempts; the job goes on without it.
    Failed,
    /// The final frames were all done before it was made: the final video stands for it.
    Superseded,
}

impl PreviewVideoState {
    /// How `pb::Job.preview_video` says it: empty where there is none to follow.
    pub fn name(self) -> &'static str {
        match self {
            PreviewVideoState::NotAsked | PreviewVideoState::Superseded => "",
            PreviewVideoState::Waiting => "waiting",
            PreviewVideoState::Encoding => "encoding",
            PreviewVideoState::Ready(_) => "ready",
            PreviewVideoState::Failed => "failed",
        }
    }
}

impl Job {
    /// Whether the job may yet have its preview video leased: it asks for a video and for
    /// previews, its final frames are not all done, and its preview video is neither stored,
    /// leased, nor out of attempts. Whether every frame has an image is the daemon's to say
    /// ([`Daemon::preview_video_due`]).
    pub fn may_make_preview_video(&self) -> bool {
        let preview = self.encode.as_ref().map(|e| &e.preview);
        self.spec.preview
            && self.spec.video.is_some()
            && self.frames_done < self.frames_total
            && preview.is_none_or(|p| {
                p.lease.is_none()
                    && p.video_size_bytes.is_none()
                    && p.failed_attempts < MAX_ENCODE_ATTEMPTS
            })
    }

    /// Where its preview video stands.
    pub fn preview_video_state(&self) -> PreviewVideoState {
        let preview = self.encode.as_ref().map(|e| &e.preview);
        if !(self.spec.preview && self.spec.video.is_some()) {
            PreviewVideoState::NotAsked
        } else if let Some(size) = self.preview_video_size_bytes() {
            PreviewVideoState::Ready(size)
        } else if preview.is_some_and(|p| p.lease.is_some()) {
            PreviewVideoState::Encoding
        } else if preview.is_some_and(|p| p.failed_attempts >= MAX_ENCODE_ATTEMPTS) {
            PreviewVideoState::Failed
        } else if self.frames_done >= self.frames_total {
            PreviewVideoState::Superseded
        } else {
            PreviewVideoState::Waiting
        }
    }

    /// The stored preview video's size.
    pub fn preview_video_size_bytes(&self) -> Option<u64> {
        self.encode
            .as_ref()
            .and_then(|e| e.preview.video_size_bytes)
    }
}

impl DaemonConfig {
    /// Where job `job_id`'s preview video is stored: beside its final video.
    pub fn preview_video_path(&self, job_id: &str, container: VideoContainer) -> PathBuf {
        self.frames_dir(job_id)
            .join(format!("preview_video.{}", container.extension()))
    }
}

impl Daemon {
    /// Whether `job`'s preview video is to be leased now: it may be made and every frame has
    /// an image, a preview or a final one.
    pub(crate) fn preview_video_due(&self, job: &Job) -> Result<bool, DaemonError> {
        if !job.may_make_preview_video() {
            return Ok(false);
        }
        let mut reports = self.state.frame_reports(&job.id)?;
        reports.dedup_by_key(|report| report.index);
        Ok(reports.len() >= job.frames_total as usize)
    }

    /// Job `job_id`'s stored preview video: its file, size and container. FailedPrecondition
    /// while it has none, saying why.
    pub fn preview_video(
        &self,
        job_id: &str,
    ) -> Result<(PathBuf, u64, VideoContainer), DaemonError> {
        let job = self.job(job_id)?;
        let refused = |why: String| {
            Err(DaemonError::FailedPrecondition(format!(
                "job {job_id} has no preview video: {why}"
            )))
        };
        let Some(video) = job.spec.video else {
            return refused("it asked for no video".into());
        };
        match job.preview_video_state() {
            PreviewVideoState::Ready(size) => Ok((
                self.config.preview_video_path(job_id, video.container),
                size,
                video.container,
            )),
            PreviewVideoState::NotAsked => refused("it asked for no previews".into()),
            PreviewVideoState::Encoding => refused("it is being made".into()),
            PreviewVideoState::Failed => refused(format!("it failed {MAX_ENCODE_ATTEMPTS} times")),
            PreviewVideoState::Superseded => refused(
                "its final frames were all done first; its final video supersedes it".into(),
            ),
            PreviewVideoState::Waiting => refused(format!(
                "it is {}, waiting for every frame to have a preview",
                job.state.name()
            )),
        }
    }
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;
    use std::time::Duration;

    use pointfarm_proto::v1 as pb;

    use crate::error::DaemonError;
    use crate::lease::FrameOutcome;
    use crate::model::{Job, JobState};
    use crate::service::Daemon;
    use crate::test_daemon;

    fn submit_previewed_with_video(daemon: &Daemon, frames: u32) -> Job {
        test_daemon::submit(daemon, frames, |request| {
            request.preview = true;
            request.video = Some(pb::VideoSpec {
                container: "mp4".into(),
                ..Default::default()
            });
        })
    }

    fn lease_encode(daemon: &Daemon) -> Option<super::super::EncodeTask> {
        daemon
            .lease_encode("e", false, &["libx264".to_owned()])
            .expect("lease")
    }

    /// Hands in the preview of the next frame leased; false when none is leased.
    fn hand_in_preview(daemon: &Daemon) -> bool {
        let Some(task) = test_daemon::lease(daemon) else {
            return false;
        };
        let outcome = FrameOutcome {
            timings: Vec::new(),
            dataset_cache_hit: None,
            cut: None,
            preview: Some(0.1),
        };
        daemon
            .complete_frame(&task.lease.id, &test_daemon::png(8, 6), outcome)
            .expect("preview");
        true
    }

    #[test]
    fn the_preview_video_is_leased_once_every_frame_has_a_preview_and_keeps_the_job_going() {
        let dir = tempfile::tempdir().expect("tempdir");
        let daemon = test_daemon::open(dir.path(), Duration::from_secs(60));
        let job = submit_previewed_with_video(&daemon, 2);
        let sha256 = daemon
            .state
            .dataset(&job.spec.dataset_id)
            .expect("read")
            .expect("dataset")
            .sha256;
        let progress = Arc::new(pointfarm_render::lod::BuildProgress::new());
        daemon.stores.hold_building(&sha256, 20_000, progress);
        let shown =
            |daemon: &Daemon| pb::Job::from(&daemon.job(&job.id).expect("job")).preview_video;
        assert_eq!(shown(&daemon), "waiting");

        assert!(hand_in_preview(&daemon));
        assert!(lease_encode(&daemon).is_none(), "a frame has no preview");
        assert!(hand_in_preview(&daemon));
        assert!(!hand_in_preview(&daemon), "every frame has its preview");

        let task = lease_encode(&daemon).expect("the preview video");
        assert_eq!((task.job_id.as_str(), task.frames), (job.id.as_str(), 2));
        assert!(lease_encode(&daemon).is_none(), "one at a time");
        assert_eq!(shown(&daemon), "encoding");
        daemon
            .fail_encode(&task.lease_id, false, "ffmpeg said no")
            .expect("fail");
        let job_now = daemon.job(&job.id).expect("job");
        assert_eq!((job_now.state, job_now.error), (JobState::Running, None));

        let again = lease_encode(&daemon).expect("leased again");
        assert_eq!(again.failed_attempts, 1);
        let bytes = b"a preview video";
        let mut upload = daemon
            .start_video_upload(&again.lease_id, false, bytes.len() as u64)
            .expect("upload");
        upload.write(bytes).expect("write");
        let stored = daemon.finish_video_upload(upload).expect("stored");
        assert_eq!((stored.state, stored.frames_done), (JobState::Running, 0));
        assert_eq!(shown(&daemon), "ready");
        let (path, size, _) = daemon.preview_video(&job.id).expect("preview video");
        assert_eq!(std::fs::read(path).expect("read"), bytes);
        assert_eq!(size, bytes.len() as u64);
        assert!(matches!(
            daemon.video(&job.id),
            Err(DaemonError::FailedPrecondition(_))
        ));
        assert!(lease_encode(&daemon).is_none(), "made once");
    }

    #[test]
    fn a_preview_video_is_skipped_when_the_final_frames_come_first() {
        let dir = tempfile::tempdir().expect("tempdir");
        let daemon = test_daemon::open(dir.path(), Duration::from_secs(60));
        let job = submit_previewed_with_video(&daemon, 2);
        while let Some(task) = test_daemon::lease(&daemon) {
            test_daemon::render(&daemon, &task);
        }
        let task = lease_encode(&daemon).expect("the final video");
        assert_eq!(task.job_id, job.id);
        assert!(lease_encode(&daemon).is_none(), "no preview video");
        let refused = daemon.preview_video(&job.id).expect_err("none");
        assert!(refused.to_string().contains("supersedes"), "{refused}");
        let shown = pb::Job::from(&daemon.job(&job.id).expect("job")).preview_video;
        assert_eq!(shown, "", "none to follow");

        let plain = test_daemon::submit(&daemon, 1, |_| {});
        let refused = daemon.preview_video(&plain.id).expect_err("none");
        assert!(refused.to_string().contains("no video"), "{refused}");
    }
}

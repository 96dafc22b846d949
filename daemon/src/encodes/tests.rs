//! A job's video against a real daemon on a temporary folder: when its encode is leased and
//! to whom, what its lease lapsing or failing costs, and what a handed-in video does.

use std::path::Path;
use std::sync::Arc;
use std::time::Duration;

use pointfarm_proto::v1 as pb;

use super::*;
use crate::test_daemon;

fn open(dir: &Path, lease_timeout: Duration) -> Arc<Daemon> {
    test_daemon::open(dir, lease_timeout)
}

fn submit_with_video(daemon: &Daemon, frames: u32) -> Job {
    test_daemon::submit(daemon, frames, |request| {
        request.video = Some(pb::VideoSpec {
            container: "mp4".into(),
            ..Default::default()
        });
    })
}

/// Renders every frame there is to lease.
fn render_all(daemon: &Daemon) {
    while let Some(task) = test_daemon::lease(daemon) {
        test_daemon::render(daemon, &task);
    }
}

fn x264() -> Vec<String> {
    vec!["libx264".to_owned()]
}

/// A daemon whose one-frame job has every frame rendered and waits for its video.
fn waiting_for_its_video(dir: &Path, lease_timeout: Duration) -> (Arc<Daemon>, Job) {
    let daemon = open(dir, lease_timeout);
    let job = submit_with_video(&daemon, 1);
    render_all(&daemon);
    (daemon, job)
}

/// The encode `worker`, whose ffmpeg has libx264, is handed, if any.
fn lease_x264(daemon: &Daemon, worker: &str) -> Option<EncodeTask> {
    daemon.lease_encode(worker, false, &x264()).expect("lease")
}

fn hand_in(daemon: &Daemon, lease_id: &str, bytes: &[u8]) -> Result<Job, DaemonError> {
    let mut upload = daemon.start_video_upload(lease_id, false, bytes.len() as u64)?;
    upload.write(bytes)?;
    daemon.finish_video_upload(upload)
}

#[test]
fn the_video_is_leased_after_the_last_frame_to_a_worker_with_its_encoder() {
    let dir = tempfile::tempdir().expect("tempdir");
    let daemon = open(dir.path(), Duration::from_secs(60));
    let job = submit_with_video(&daemon, 2);
    assert_eq!(job.stage(), "frames");
    assert!(lease_x264(&daemon, "e").is_none());

    render_all(&daemon);
    let job = daemon.job(&job.id).expect("job");
    assert_eq!((job.state, job.stage()), (JobState::Running, "video"));
    let none: Vec<String> = Vec::new();
    assert!(daemon
        .lease_encode("e", false, &none)
        .expect("lease")
        .is_none());
    let vp9 = vec!["libvpx-vp9".to_owned()];
    assert!(daemon
        .lease_encode("e", false, &vp9)
        .expect("lease")
        .is_none());

    let task = lease_x264(&daemon, "e").expect("the video");
    assert_eq!((task.job_id.as_str(), task.frames), (job.id.as_str(), 2));
    assert!(lease_x264(&daemon, "f").is_none(), "one encode lease a job");
    assert!(matches!(
        daemon.renew_encode(&task.lease_id, true),
        Err(DaemonError::PermissionDenied(_))
    ));

    let video = b"not checked by the daemon".to_vec();
    let job = hand_in(&daemon, &task.lease_id, &video).expect("stored");
    assert_eq!((job.state, job.stage()), (JobState::Succeeded, ""));
    let (path, size, container) = daemon.video(&job.id).expect("video");
    assert_eq!((size, container), (video.len() as u64, VideoContainer::Mp4));
    assert_eq!(std::fs::read(path).expect("read"), video);
    assert!(
        hand_in(&daemon, &task.lease_id, &video).is_err(),
        "a video is stored once"
    );
}

#[test]
fn a_lapsed_encode_is_leased_again_the_last_failure_fails_the_job_and_a_retry_makes_it() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (daemon, job) = waiting_for_its_video(dir.path(), Duration::from_millis(50));

    let first = lease_x264(&daemon, "e").expect("the video");
    std::thread::sleep(Duration::from_millis(120));
    assert_eq!(daemon.expire_encodes().expect("expire"), 1);
    assert!(matches!(
        daemon.renew_encode(&first.lease_id, false),
        Ok(HeartbeatAnswer::Stop(_))
    ));
    let second = lease_x264(&daemon, "f").expect("leased again");
    assert_ne!(second.lease_id, first.lease_id);
    assert_eq!(second.failed_attempts, 1);

    daemon
        .fail_encode(&second.lease_id, false, "Unknown encoder 'libx264'")
        .expect("fail");
    let third = lease_x264(&daemon, "f").expect("leased a third time");
    daemon
        .fail_encode(&third.lease_id, false, "Conversion failed!")
        .expect("fail");
    let failed = daemon.job(&job.id).expect("job");
    assert_eq!(failed.state, JobState::Failed);
    let error = failed.error.expect("error");
    assert!(
        error.contains("Conversion failed!") && error.contains("3 times"),
        "{error}"
    );
    assert!(daemon.video(&job.id).is_err());

    // A retry makes the video again, its attempts from zero; the frames stay done.
    let retried = daemon.retry_job(&job.id).expect("retry");
    assert_eq!(
        (retried.state, retried.stage()),
        (JobState::Running, "video")
    );
    let again = lease_x264(&daemon, "f").expect("leased after the retry");
    assert_eq!(again.failed_attempts, 0);
    let stored = hand_in(&daemon, &again.lease_id, b"video").expect("stored");
    assert_eq!(stored.state, JobState::Succeeded);
}

#[test]
fn a_video_larger_than_the_limit_or_than_declared_is_refused() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (daemon, _) = waiting_for_its_video(dir.path(), Duration::from_secs(60));
    let task = lease_x264(&daemon, "e").expect("the video");
    let too_large = daemon
        .start_video_upload(&task.lease_id, false, MAX_VIDEO_BYTES + 1)
        .err()
        .expect("refused");
    assert!(too_large.to_string().contains("at most"), "{too_large}");
    let mut upload = daemon
        .start_video_upload(&task.lease_id, false, 4)
        .expect("upload");
    let overflow = upload.write(b"12345").expect_err("more than declared");
    assert!(overflow.to_string().contains("declared"), "{overflow}");
}

#[test]
fn a_video_handed_back_is_leased_again_at_once_counting_no_attempt() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (daemon, job) = waiting_for_its_video(dir.path(), Duration::from_secs(600));
    let first = lease_x264(&daemon, "stopping").expect("the video");
    daemon
        .release_encode(&first.lease_id, false)
        .expect("handed back");
    // Given back twice, or once it is not held, there is nothing to give.
    daemon
        .release_encode(&first.lease_id, false)
        .expect("nothing to give back");
    let again = lease_x264(&daemon, "other").expect("leased again at once");
    assert_eq!(
        (again.job_id.as_str(), again.failed_attempts),
        (job.id.as_str(), 0)
    );
    assert!(daemon
        .renew_encode(&first.lease_id, false)
        .is_ok_and(|answer| matches!(answer, HeartbeatAnswer::Stop(_))));
    let job = daemon.job(&job.id).expect("job");
    assert_eq!((job.state, job.stage()), (JobState::Running, "video"));
}

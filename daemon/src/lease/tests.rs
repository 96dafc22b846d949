//! Leases against a real store: restarts, failures, dead embedded workers, a full disk.

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

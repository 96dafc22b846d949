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
        .lease_frame(worker, embedded, &WorkerCapabilities::default())
        .expect("lease")
        .expect("a frame to lease")
}

fn outcome() -> FrameOutcome {
    FrameOutcome {
        timings: Vec::new(),
        dataset_cache_hit: None,
        cut: None,
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
    let (daemon, job) = daemon_with_job_in(folder.path(), frames);
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

/// A daemon whose data lie on `dir`, with one job of `frames` frames on a registered file.
fn daemon_with_job_in(dir: &Path, frames: u32) -> (Arc<Daemon>, crate::model::Job) {
    std::fs::create_dir_all(dir.join("roots")).expect("roots");
    std::fs::write(dir.join("roots/a.las"), b"points").expect("file");
    let daemon = open(dir);
    let dataset = daemon
        .register_dataset(&["a.las".to_string()], "")
        .expect("register");
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
    (daemon, job)
}

/// The files of the job's frames folder that are not whole frames.
fn partial_files(daemon: &Daemon, job_id: &str) -> Vec<String> {
    std::fs::read_dir(daemon.config.frames_dir(job_id))
        .map(|entries| {
            entries
                .flatten()
                .map(|e| e.file_name().to_string_lossy().into_owned())
                .filter(|name| name.ends_with(".part"))
                .collect()
        })
        .unwrap_or_default()
}

#[test]
fn a_full_disk_gives_frames_back_without_an_attempt_and_the_daemon_resumes_by_itself() {
    let Some(disk) = crate::testing::SmallDisk::mount(16) else {
        return;
    };
    let (daemon, job) = daemon_with_job_in(disk.path(), 3);
    let first = lease(&daemon, "w", false);
    daemon
        .complete_frame(&first.lease.id, &png(8, 6), outcome())
        .expect("complete before the disk fills");
    let held = lease(&daemon, "w", false);

    let filler = disk.fill("filler");
    let refused = daemon.complete_frame(&held.lease.id, &png(8, 6), outcome());
    let Err(DaemonError::ResourceExhausted(message)) = &refused else {
        panic!("a full disk is told as such: {refused:?}");
    };
    assert!(message.contains("disk is full"), "{message}");
    assert!(message.contains("no attempt counted"), "{message}");
    assert!(partial_files(&daemon, &job.id).is_empty());
    assert!(daemon.store.outage().is_some());
    assert!(daemon.leases().expect("leases").is_empty(), "given back");
    let leasing = daemon.lease_frame("w", false, &WorkerCapabilities::default());
    assert!(
        matches!(leasing, Err(DaemonError::ResourceExhausted(_))),
        "no frames are leased while the disk is full: {leasing:?}"
    );
    assert_eq!(daemon.expire_leases().expect("sweep"), 0);
    assert!(daemon.store.outage().is_some(), "the probe fails");

    std::fs::remove_file(filler).expect("free the disk");
    daemon.expire_leases().expect("sweep");
    assert!(
        daemon.store.outage().is_none(),
        "the sweep ended the outage"
    );
    let again = lease(&daemon, "w", false);
    assert_eq!(
        (again.lease.index, again.failed_attempts),
        (held.lease.index, 0),
        "the refused frame is back, with no attempt counted"
    );
    daemon
        .complete_frame(&again.lease.id, &png(8, 6), outcome())
        .expect("complete after the outage");
    let last = lease(&daemon, "w", false);
    let done = daemon
        .complete_frame(&last.lease.id, &png(8, 6), outcome())
        .expect("complete");
    assert_eq!(done.state, JobState::Succeeded);
    let reports = daemon.store.frame_reports(&job.id).expect("reports");
    assert_eq!(
        reports
            .iter()
            .map(|r| r.failed_attempts)
            .collect::<Vec<_>>(),
        [0, 0, 0]
    );
    drop(daemon);
    // All of it durable: a restart finds the job done.
    let daemon = open(disk.path());
    assert_eq!(daemon.job(&job.id).expect("job").state, JobState::Succeeded);
}

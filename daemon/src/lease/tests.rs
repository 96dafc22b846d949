//! Leases against a real state database: restarts, failures, dead embedded workers, a full
//! disk.

use std::path::Path;
use std::sync::Arc;
use std::time::Duration;

use pointfarm_proto::v1 as pb;

use super::*;
use crate::capabilities::AdapterKind;
use crate::test_daemon::{self, png};

fn open(dir: &Path) -> Arc<Daemon> {
    test_daemon::open(dir, Duration::from_secs(60))
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
        preview: None,
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
    // The transient attempt is stored at the frame; the permanent one ended the job first
    // (the job's end counts both).
    assert_eq!(daemon.state.failed_attempts(&job.id).expect("attempts"), 1);
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
    let daemon = open(dir);
    let job = test_daemon::submit(&daemon, frames, |_| {});
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
    assert!(daemon.state.outage().is_some());
    assert!(daemon.leases().expect("leases").is_empty(), "given back");
    let leasing = daemon.lease_frame("w", false, &WorkerCapabilities::default());
    assert!(
        matches!(leasing, Err(DaemonError::ResourceExhausted(_))),
        "no frames are leased while the disk is full: {leasing:?}"
    );
    assert_eq!(daemon.expire_leases().expect("sweep"), 0);
    assert!(daemon.state.outage().is_some(), "the probe fails");

    std::fs::remove_file(filler).expect("free the disk");
    daemon.expire_leases().expect("sweep");
    assert!(
        daemon.state.outage().is_none(),
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
    let reports = daemon.state.frame_reports(&job.id).expect("reports");
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

/// A worker that says what it can render.
fn worker(adapter: AdapterKind, tags: &[&str], max_frame_side: Option<u32>) -> WorkerCapabilities {
    WorkerCapabilities {
        adapter,
        adapter_name: format!("{adapter:?}"),
        max_frame_side,
        tags: tags.iter().map(|t| t.to_string()).collect(),
        ..WorkerCapabilities::default()
    }
}

/// Submits a job of one frame of `width` x `height` at `supersample` on the daemon's dataset.
fn submit_one(
    daemon: &Daemon,
    name: &str,
    (width, height, supersample): (u32, u32, u32),
    requirements: Option<pb::WorkerRequirements>,
) -> crate::model::Job {
    test_daemon::submit(daemon, 1, |request| {
        request.request_id = name.into();
        (request.width, request.height) = (width, height);
        request.render = Some(pb::RenderOptions {
            supersample: Some(supersample),
            ..Default::default()
        });
        request.requirements = requirements;
    })
}

/// What a job asks of its workers: a GPU where `gpu`, and every one of `tags`.
fn requiring(gpu: bool, tags: &[&str]) -> Option<pb::WorkerRequirements> {
    Some(pb::WorkerRequirements {
        gpu,
        tags: tags.iter().map(|&tag| tag.into()).collect(),
    })
}

/// The jobs whose frames `worker` is leased, in order, until there is none for it.
fn jobs_leased(daemon: &Daemon, name: &str, worker: &WorkerCapabilities) -> Vec<String> {
    std::iter::from_fn(|| {
        daemon
            .lease_frame(name, false, worker)
            .expect("lease")
            .map(|task| task.lease.job_id)
    })
    .collect()
}

#[test]
fn frames_are_leased_only_to_workers_that_meet_their_jobs_requirements_and_size() {
    let (_dir, daemon, plain) = daemon_with_job(1);
    let needs_gpu = submit_one(&daemon, "gpu", (8, 6, 1), requiring(true, &[]));
    let needs_tag = submit_one(&daemon, "tag", (8, 6, 1), requiring(false, &["site-x"]));
    // 2100 pixels at 2x supersampling draw 4200 a side.
    let large = submit_one(&daemon, "large", (2100, 1000, 2), None);
    let lavapipe = worker(AdapterKind::Software, &["site-x"], Some(4096));
    let a100 = worker(AdapterKind::Hardware, &[], Some(16384));
    assert_eq!(
        jobs_leased(&daemon, "lavapipe", &lavapipe),
        vec![plain.id.clone(), needs_tag.id.clone()],
        "no GPU job, no 4200-pixel frame"
    );
    assert_eq!(
        jobs_leased(&daemon, "a100", &a100),
        vec![needs_gpu.id.clone(), large.id.clone()],
        "no job that needs a tag it lacks"
    );
    // A worker that says nothing of itself renders only jobs without requirements.
    let old = WorkerCapabilities::default();
    let second_plain = submit_one(&daemon, "plain-2", (8, 6, 1), None);
    let second_gpu = submit_one(&daemon, "gpu-2", (8, 6, 1), requiring(true, &[]));
    assert_eq!(jobs_leased(&daemon, "old", &old), vec![second_plain.id]);
    assert_eq!(jobs_leased(&daemon, "a100", &a100), vec![second_gpu.id]);
}

#[test]
fn a_job_that_no_connected_worker_can_render_says_why() {
    let (_dir, daemon, plain) = daemon_with_job(1);
    let timeout = daemon.config.lease_timeout;
    let waiting = |job: &crate::model::Job| daemon.job_availability(job).waiting;
    assert_eq!(waiting(&plain).as_deref(), Some("no worker is connected"));
    let tagged = submit_one(
        &daemon,
        "tagged",
        (8, 6, 1),
        requiring(false, &["site-x", "a100"]),
    );
    let large = submit_one(&daemon, "large", (5000, 10, 1), None);
    let lavapipe = worker(AdapterKind::Software, &["site-x"], Some(4096));
    let _polling = daemon
        .workers
        .poll_named(false, "lavapipe", lavapipe, timeout);
    assert_eq!(waiting(&plain), None);
    assert_eq!(
        waiting(&tagged).as_deref(),
        Some("no connected worker has tag a100")
    );
    assert_eq!(
        daemon.job_availability(&tagged).refusals,
        vec![("lavapipe".to_string(), "no tag a100".to_string())]
    );
    assert_eq!(
        waiting(&large).as_deref(),
        Some("no connected worker draws images of 5000 pixels a side")
    );
    let a100 = worker(AdapterKind::Hardware, &["a100", "site-x"], None);
    let _also = daemon.workers.poll_named(false, "a100", a100, timeout);
    assert_eq!(waiting(&tagged), None);
    assert_eq!(waiting(&large), None);
    assert_eq!(daemon.job_availability(&large).refusals.len(), 1);
}

#[test]
fn a_worker_that_fails_three_frames_of_a_job_gets_no_more_of_them() {
    let (dir, daemon, job) = daemon_with_job(5);
    assert_eq!(daemon.config.worker_failures_before_blocklist, 3);
    let other = submit_one(&daemon, "other", (8, 6, 1), None);
    let held: Vec<FrameTask> = (0..3).map(|_| lease(&daemon, "bad", false)).collect();
    assert_eq!(
        held.iter().map(|t| t.lease.index).collect::<Vec<_>>(),
        [0, 1, 2]
    );
    for (n, task) in held.iter().enumerate() {
        daemon
            .fail_frame(&task.lease.id, "GPU lost", FailureKind::Transient)
            .expect("fail");
        let now = daemon.job(&job.id).expect("job");
        assert_eq!(now.worker_failures.get("bad"), Some(&(n as u32 + 1)));
        assert_eq!(now.blocklist.contains("bad"), n == 2);
    }
    // Each frame failed once: the job goes on, without "bad".
    let blocked = daemon.job(&job.id).expect("job");
    assert_eq!(blocked.state, JobState::Running);
    let caps = WorkerCapabilities::default();
    assert_eq!(
        jobs_leased(&daemon, "bad", &caps),
        vec![other.id.clone()],
        "the other job's frames still go to it"
    );
    let good = lease(&daemon, "good", false);
    assert_eq!((good.lease.index, good.failed_attempts), (0, 1));
    let message = pb::Job::from(&blocked);
    assert_eq!(
        message.blocklisted_workers,
        vec![pb::BlocklistedWorker {
            worker_name: "bad".into(),
            failed_frames: 3
        }]
    );
    let timeout = daemon.config.lease_timeout;
    {
        let _bad = daemon
            .workers
            .poll_named(false, "bad", caps.clone(), timeout);
        let availability = daemon.job_availability(&blocked);
        assert_eq!(
            availability.waiting.as_deref(),
            Some("every connected worker is blocklisted for this job")
        );
        assert_eq!(
            availability.refusals,
            vec![(
                "bad".to_string(),
                "blocklisted: it failed 3 frames of this job".to_string()
            )]
        );
    }
    drop(daemon);

    // Durable with the job.
    let daemon = open(dir.path());
    let reopened = daemon.job(&job.id).expect("job");
    assert_eq!(reopened.blocklist, blocked.blocklist);
    let for_bad = daemon
        .lease_frame("bad", false, &caps)
        .expect("lease")
        .map(|task| task.lease.job_id);
    assert_eq!(for_bad, None, "{reopened:?}");
}

#[test]
fn lost_leases_count_against_their_worker_except_when_the_daemon_stopped() {
    let (dir, daemon, job) = daemon_with_job(4);
    lease(&daemon, "embedded", true);
    daemon
        .embedded_worker_exited("embedded", "killed by signal 9 (SIGKILL)")
        .expect("exited");
    let counted = daemon.job(&job.id).expect("job");
    assert_eq!(counted.worker_failures.get("embedded"), Some(&1));
    lease(&daemon, "embedded", true);
    drop(daemon);
    let daemon = open(dir.path());
    let after = daemon.job(&job.id).expect("job");
    assert_eq!(
        after.worker_failures.get("embedded"),
        Some(&1),
        "the daemon's stop is not the worker's failure"
    );
    let again = lease(&daemon, "embedded", true);
    assert_eq!((again.lease.index, again.failed_attempts), (0, 2));
}

#[test]
fn no_blocklist_is_kept_when_its_limit_is_zero() {
    let folder = tempfile::tempdir().expect("tempdir");
    let (daemon, job) = daemon_with_job_in(folder.path(), 4);
    drop(daemon);
    let daemon = test_daemon::open_with(folder.path(), |config| {
        config.worker_failures_before_blocklist = 0;
    });
    let held: Vec<FrameTask> = (0..3).map(|_| lease(&daemon, "bad", false)).collect();
    for task in &held {
        daemon
            .fail_frame(&task.lease.id, "GPU lost", FailureKind::Transient)
            .expect("fail");
    }
    let now = daemon.job(&job.id).expect("job");
    assert_eq!(now.worker_failures.get("bad"), Some(&3));
    assert!(now.blocklist.is_empty());
    let again = lease(&daemon, "bad", false);
    assert_eq!((again.lease.index, again.failed_attempts), (0, 1));
}

/// A preview is kept beside its pending frame, durably; the frame is leased again for its
/// final render, which alone counts and ends the job; a job without previews refuses one.
#[test]
fn a_preview_keeps_its_frame_pending_until_the_final_frame_replaces_it() {
    let dir = tempfile::tempdir().expect("tempdir");
    let daemon = open(dir.path());
    let job = test_daemon::submit(&daemon, 1, |r| r.preview = true);
    assert!(job.spec.preview);
    let first = lease(&daemon, "w", false);
    assert_eq!(
        first.preview(),
        Some(0),
        "a frame without a preview is offered one"
    );
    let preview = FrameOutcome {
        preview: Some(0.25),
        ..outcome()
    };
    let after = daemon
        .complete_frame(&first.lease.id, &png(8, 6), preview)
        .expect("a preview");
    assert_eq!((after.frames_done, after.state), (0, JobState::Running));
    assert!(daemon.config.frame_path(&job.id, 0).is_file());
    drop(daemon);

    // As after a kill -9: the preview is in the flushed state, the frame still pending.
    let daemon = open(dir.path());
    let reports = daemon.state.frame_reports(&job.id).expect("reports");
    assert_eq!(reports.len(), 1);
    assert_eq!(reports[0].preview, Some(0.25));
    // No store is building here, so the frame is leased again at once, for its final render.
    let again = lease(&daemon, "w", false);
    assert_eq!(again.lease.index, 0);
    assert!(
        again.preview().is_none(),
        "a frame with a preview is not previewed again"
    );
    let done = daemon
        .complete_frame(&again.lease.id, &png(8, 6), outcome())
        .expect("final");
    assert_eq!((done.frames_done, done.state), (1, JobState::Succeeded));
    let reports = daemon.state.frame_reports(&job.id).expect("reports");
    assert_eq!(reports.len(), 1);
    assert_eq!(
        reports[0].preview, None,
        "the final report replaced the preview"
    );
    drop(daemon);
    // Reopened, the final frame stays final: nothing is leased again.
    let daemon = open(dir.path());
    assert_nothing_leased(&daemon, "a final frame leased again");
    assert_eq!(daemon.job(&job.id).expect("job").state, JobState::Succeeded);

    // A job without previews takes none.
    let plain = test_daemon::submit(&daemon, 1, |r| r.request_id = "plain".into());
    let task = lease(&daemon, "w", false);
    assert_eq!(task.lease.job_id, plain.id);
    assert!(task.preview().is_none());
    let refused = daemon.complete_frame(
        &task.lease.id,
        &png(8, 6),
        FrameOutcome {
            preview: Some(0.5),
            ..outcome()
        },
    );
    assert!(
        matches!(refused, Err(DaemonError::InvalidArgument { .. })),
        "{refused:?}"
    );
}

/// What a build of a small scene has stored when it ends: every tenth of its points.
fn whole_build_progress(dir: &Path) -> Arc<pointfarm_render::lod::BuildProgress> {
    use pointfarm_render::cut::StoredLod;
    use pointfarm_render::ingest::{write_las, LasWriteOptions};
    let path = dir.join("scene.las");
    let scene = pointfarm_render::sample::sample_scene(20_000, 3);
    write_las(&path, &scene, &LasWriteOptions::default()).expect("write");
    let progress = Arc::new(pointfarm_render::lod::BuildProgress::new());
    let build = pointfarm_render::cut::StoreBuild {
        folder: &dir.join("lod"),
        memory_budget: 64 << 20,
        disk_budget: None,
        on_build: &mut |_| {},
        progress: &progress,
    };
    StoredLod::open_or_build_watched(&[path], build).expect("build");
    progress
}

/// A daemon in `dir` with a previewed job of `frames` frames, and the content hash of the job's
/// dataset, whose build the preview tests hold.
fn previewed_job(dir: &Path, frames: u32) -> (Arc<Daemon>, crate::model::Job, String) {
    let daemon = open(dir);
    let job = test_daemon::submit(&daemon, frames, |r| r.preview = true);
    let sha256 = dataset_sha256(&daemon, &job);
    (daemon, job, sha256)
}

/// Hands in `task`'s frame with `outcome`, as a worker does, expecting it taken (`what` says
/// what it is).
fn hand_in(daemon: &Daemon, task: &FrameTask, outcome: FrameOutcome, what: &str) {
    daemon
        .complete_frame(&task.lease.id, &png(8, 6), outcome)
        .expect(what);
}

/// Asserts that no frame is leased now, `why` saying what that shows.
fn assert_nothing_leased(daemon: &Daemon, why: &str) {
    let none = daemon
        .lease_frame("w", false, &WorkerCapabilities::default())
        .expect("lease");
    assert!(none.is_none(), "{why}: {none:?}");
}

/// The content hash of `job`'s dataset, whose build a test holds.
fn dataset_sha256(daemon: &Daemon, job: &crate::model::Job) -> String {
    daemon
        .state
        .dataset(&job.spec.dataset_id)
        .expect("read")
        .expect("dataset")
        .sha256
}

/// Holds `sha256`'s store as building, at `progress`.
fn hold_building(
    daemon: &Daemon,
    sha256: &str,
    progress: &Arc<pointfarm_render::lod::BuildProgress>,
) {
    daemon
        .stores
        .hold_building(sha256, 20_000, Arc::clone(progress))
}

/// A preview of `completeness`, as a worker hands one in.
fn preview_of(completeness: f64) -> FrameOutcome {
    FrameOutcome {
        preview: Some(completeness),
        ..outcome()
    }
}

/// While the store builds, a frame whose preview is of the build's version waits; once the
/// build's version moves past it, the frame is offered again for a preview of the new
/// version, which is kept with it (across a restart too); a frame is leased for its final
/// render once nothing builds.
#[test]
fn a_preview_is_drawn_again_once_the_build_has_stored_more() {
    let dir = tempfile::tempdir().expect("tempdir");
    let build = tempfile::tempdir().expect("tempdir");
    let (daemon, job, sha256) = previewed_job(dir.path(), 2);
    // A build that has stored nothing yet: the chunk starts alone, version 0.
    let started = Arc::new(pointfarm_render::lod::BuildProgress::new());
    let hold = |daemon: &Daemon, progress: &Arc<pointfarm_render::lod::BuildProgress>| {
        hold_building(daemon, &sha256, progress)
    };
    hold(&daemon, &started);
    let preview = preview_of;
    for index in 0..2 {
        let task = lease(&daemon, "w", false);
        assert_eq!((task.lease.index, task.preview()), (index, Some(0)));
        hand_in(&daemon, &task, preview(0.01), "a preview");
    }
    assert_nothing_leased(&daemon, "previews of the build's version wait");

    // The build has stored every tenth: each frame is offered for a redraw at version 10.
    let stored = whole_build_progress(build.path());
    assert_eq!(stored.preview_version(), 10);
    hold(&daemon, &stored);
    let redraw = lease(&daemon, "w", false);
    assert_eq!((redraw.lease.index, redraw.preview()), (0, Some(10)));
    hand_in(&daemon, &redraw, preview(0.5), "a redrawn preview");
    let other = lease(&daemon, "w", false);
    assert_eq!(
        (other.lease.index, other.preview()),
        (1, Some(10)),
        "the redrawn frame waits, the other is redrawn"
    );
    daemon.release_frame(&other.lease.id).expect("release");
    drop(daemon);

    // As after a kill -9: the previews keep their versions; the build, counting again from
    // 0, redraws nothing until it moves past them.
    let daemon = open(dir.path());
    hold(&daemon, &started);
    assert_nothing_leased(&daemon, "nothing is previewed again");
    let reports = daemon.state.frame_reports(&job.id).expect("reports");
    let kept: Vec<(Option<f64>, u32)> = reports
        .iter()
        .map(|r| (r.preview, r.preview_version))
        .collect();
    assert_eq!(kept, [(Some(0.5), 10), (Some(0.01), 0)]);
    hold(&daemon, &stored);
    let redraw = lease(&daemon, "w", false);
    assert_eq!((redraw.lease.index, redraw.preview()), (1, Some(10)));
    hand_in(&daemon, &redraw, preview(0.5), "a redrawn preview");
    assert_nothing_leased(&daemon, "every preview is current");
    drop(daemon);

    // Nothing builds (the store is ready): every frame is leased for its final render.
    let daemon = open(dir.path());
    for index in 0..2 {
        let task = lease(&daemon, "w", false);
        assert_eq!((task.lease.index, task.preview()), (index, None));
    }
}

/// When the build's version moves, a frame without a preview is drawn first, then the frame
/// whose preview is oldest, whatever their order in the job: every frame sharpens in turn.
#[test]
fn redraws_take_the_frames_without_a_preview_then_the_oldest_previews_first() {
    let dir = tempfile::tempdir().expect("tempdir");
    let build = tempfile::tempdir().expect("tempdir");
    let (daemon, _, sha256) = previewed_job(dir.path(), 3);
    let hold = |progress: &Arc<pointfarm_render::lod::BuildProgress>| {
        hold_building(&daemon, &sha256, progress)
    };
    let preview = preview_of(0.01);
    // Version 0: frames 0 and 2 previewed, frame 1 held by another worker.
    hold(&Arc::new(pointfarm_render::lod::BuildProgress::new()));
    let first = lease(&daemon, "w", false);
    let held = lease(&daemon, "other", false);
    let third = lease(&daemon, "w", false);
    assert_eq!(
        (first.lease.index, held.lease.index, third.lease.index),
        (0, 1, 2)
    );
    for task in [&first, &third] {
        hand_in(&daemon, task, preview.clone(), "a preview");
    }
    daemon.release_frame(&held.lease.id).expect("release");

    // The build moves on: frame 1, which has no preview, comes first.
    hold(&whole_build_progress(build.path()));
    let next = lease(&daemon, "w", false);
    assert_eq!((next.lease.index, next.preview()), (1, Some(10)));
    hand_in(&daemon, &next, preview.clone(), "a preview");
    // Then the older previews, in the job's order.
    let redraws: Vec<u32> = (0..2)
        .map(|_| {
            let task = lease(&daemon, "w", false);
            hand_in(&daemon, &task, preview.clone(), "a redraw");
            task.lease.index
        })
        .collect();
    assert_eq!(redraws, [0, 2]);
    assert_nothing_leased(&daemon, "every preview is current");
}

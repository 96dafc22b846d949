//! Job chains against a real daemon on a temporary folder: what is leased while a job waits,
//! how a failure travels along a chain, and what a restart keeps.

use std::path::Path;
use std::sync::Arc;
use std::time::Duration;

use super::*;
use crate::lease::FailureKind;
use crate::test_daemon::{self, lease, render};

fn open(dir: &Path) -> Arc<Daemon> {
    test_daemon::open(dir, Duration::from_secs(60))
}

/// A daemon on a new temporary folder, deleted when the folder is dropped.
fn open_scratch() -> (tempfile::TempDir, Arc<Daemon>) {
    let dir = tempfile::tempdir().expect("tempdir");
    let daemon = open(dir.path());
    (dir, daemon)
}

/// A job of `frames` frames that runs after `after`.
fn submit_after(daemon: &Daemon, frames: u32, after: &[&Job]) -> Job {
    test_daemon::submit(daemon, frames, |request| {
        request.after_job_ids = after.iter().map(|job| job.id.clone()).collect();
    })
}

/// A job of one frame and another of one frame that runs after it.
fn one_after_another(daemon: &Daemon) -> (Job, Job) {
    let first = test_daemon::submit(daemon, 1, |_| {});
    let second = submit_after(daemon, 1, &[&first]);
    (first, second)
}

fn stored(daemon: &Daemon, job: &Job) -> Job {
    daemon.job(&job.id).expect("job")
}

#[test]
fn a_job_after_another_gets_no_frame_leased_until_it_has_succeeded() {
    let (_dir, daemon) = open_scratch();
    let (first, second) = one_after_another(&daemon);
    assert_eq!(second.spec.after, vec![first.id.clone()]);

    let task = lease(&daemon).expect("the first job's frame");
    assert_eq!(task.lease.job_id, first.id);
    assert!(
        lease(&daemon).is_none(),
        "the second job waits while the first renders"
    );
    assert_eq!(
        daemon.job_availability(&second).waiting,
        Some(format!("waiting for job {} to succeed", first.id))
    );

    assert_eq!(render(&daemon, &task).state, JobState::Succeeded);
    let task = lease(&daemon).expect("the second job's frame, now");
    assert_eq!(task.lease.job_id, second.id);
    assert_eq!(render(&daemon, &task).state, JobState::Succeeded);
}

#[test]
fn a_failure_or_a_cancel_fails_every_job_along_the_chain() {
    let (_dir, daemon) = open_scratch();
    let (failing, after_failing) = one_after_another(&daemon);
    let (cancelled, after_cancelled) = one_after_another(&daemon);
    let further = submit_after(&daemon, 1, &[&after_cancelled, &failing]);

    daemon.cancel_job(&cancelled.id).expect("cancel");
    let failed = stored(&daemon, &after_cancelled);
    assert_eq!(failed.state, JobState::Failed);
    assert_eq!(
        failed.error,
        Some(format!("job {} was cancelled", cancelled.id))
    );
    let failed = stored(&daemon, &further);
    assert_eq!(
        (failed.state, failed.error),
        (
            JobState::Failed,
            Some(format!("job {} failed", after_cancelled.id))
        ),
        "the failure goes on along the chain"
    );

    let task = lease(&daemon).expect("the failing job's frame");
    assert_eq!(task.lease.job_id, failing.id);
    daemon
        .fail_frame(&task.lease.id, "not a LAS file", FailureKind::Permanent)
        .expect("fail");
    let failed = stored(&daemon, &after_failing);
    assert_eq!(
        (failed.state, failed.error),
        (JobState::Failed, Some(format!("job {} failed", failing.id)))
    );
    assert!(lease(&daemon).is_none(), "nothing is left to render");

    let late = submit_after(&daemon, 1, &[&failing]);
    assert_eq!(
        (late.state, late.error),
        (JobState::Failed, Some(format!("job {} failed", failing.id))),
        "a job after one that already failed fails at once"
    );
}

#[test]
fn a_submission_names_existing_jobs_each_once_and_not_too_many() {
    let (_dir, daemon) = open_scratch();
    let first = test_daemon::submit(&daemon, 1, |_| {});
    let twice = submit_after(&daemon, 1, &[&first, &first]);
    assert_eq!(twice.spec.after, vec![first.id.clone()]);

    let unknown = vec![first.id.clone(), "job-999999999999".to_string()];
    match daemon.checked_after(&unknown) {
        Err(DaemonError::NotFound(what)) => assert_eq!(what, "job job-999999999999"),
        other => panic!("an unknown job is not found: {other:?}"),
    }
    let many: Vec<JobId> = (0..=MAX_AFTER_JOBS).map(|n| format!("job-{n}")).collect();
    match daemon.checked_after(&many) {
        Err(DaemonError::InvalidArgument { field, .. }) => assert_eq!(field, "after_job_ids"),
        other => panic!("{} jobs are too many: {other:?}", many.len()),
    }
    let jobs = daemon.list_jobs(None, 10, "").expect("jobs").items;
    assert_eq!(jobs.len(), 2, "refused submissions store nothing");
}

#[test]
fn a_restart_keeps_the_chain_and_fails_one_left_broken() {
    let (dir, daemon) = open_scratch();
    let (first, waiting) = one_after_another(&daemon);
    let (broken_first, broken) = one_after_another(&daemon);
    // A crash between a job's end and the failure of the jobs after it: the end is stored,
    // nothing else.
    daemon
        .state
        .update_job(&broken_first.id, |job| job.state = JobState::Failed)
        .expect("store the end");
    daemon.state.flush().expect("flush");
    drop(daemon);

    let daemon = open(dir.path());
    assert_eq!(stored(&daemon, &waiting).spec.after, vec![first.id.clone()]);
    let failed = stored(&daemon, &broken);
    assert_eq!(
        (failed.state, failed.error),
        (
            JobState::Failed,
            Some(format!("job {} failed", broken_first.id))
        )
    );
    let task = lease(&daemon).expect("the first job's frame");
    assert_eq!(task.lease.job_id, first.id);
    assert!(lease(&daemon).is_none(), "the chain still holds");
    render(&daemon, &task);
    assert_eq!(
        lease(&daemon)
            .expect("the waiting job's frame")
            .lease
            .job_id,
        waiting.id
    );
}

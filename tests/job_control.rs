//! Job control through real daemons and real `pointfarm worker` processes: names and labels
//! found by `jobs ls`, kept with priorities and pauses across a restart; a failed job retried;
//! a paused job that leases nothing until resumed; the higher priority leased first; jobs
//! deleted, with the chain after them; and ended jobs removed by the retention sweep. Each
//! command is run as users run it, and each refusal is checked for what it says.

use std::path::Path;
use std::process::Output;
use std::time::{Duration, Instant};

use pointfarm_daemon::access::Access;
use pointfarm_daemon::service::DaemonConfig;
use pointfarm_proto::v1 as pb;
use pointfarm_tests::service::{
    clients, get_job, left_the_queue_at, list_leases, queued_farm, submit, turntable_job,
    watch_to_end, watch_to_success, DetachedFarm, TestDaemon,
};
use pointfarm_tests::{assert_fails_saying, pointfarm, stdout, WorkerProcess};

/// `pointfarm jobs ARGS --server SERVER`.
fn jobs_command(server: &str, args: &[&str]) -> Output {
    let mut all = vec!["jobs"];
    all.extend_from_slice(args);
    all.extend(["--server", server]);
    pointfarm(&all)
}

/// [`jobs_command`], which must succeed; its standard output.
fn jobs_ok(server: &str, args: &[&str]) -> String {
    let output = jobs_command(server, args);
    assert!(output.status.success(), "jobs {args:?}: {output:?}");
    stdout(&output)
}

/// [`jobs_command`], which must fail saying `needle`.
fn jobs_refused(server: &str, args: &[&str], needle: &str) {
    assert_fails_saying(&jobs_command(server, args), needle);
}

/// A real worker process for `daemon`, its cache in `scratch`.
fn start_worker(daemon: &TestDaemon, scratch: &Path, name: &str) -> WorkerProcess {
    WorkerProcess::start(&daemon.url(), &scratch.join(name), name)
}

fn code_of<T: std::fmt::Debug>(result: Result<T, tonic::Status>) -> (tonic::Code, String) {
    let status = result.expect_err("refused");
    (status.code(), status.message().to_owned())
}

#[test]
fn names_labels_priorities_and_pauses_are_found_checked_and_kept_across_a_restart() {
    // No worker: the jobs stay queued.
    let mut farm = DetachedFarm::start(5_000, 11);
    let address = farm.address.clone();
    let hall = farm.render(&[
        "--name",
        "hall, east wing",
        "--label",
        "shot=010",
        "--label",
        "team=lidar",
        "--priority",
        "-5",
    ]);
    assert!(hall.status.success(), "{hall:?}");
    let hall = stdout(&hall).trim().to_owned();
    let other = farm.render(&["--label", "shot=020"]);
    assert!(other.status.success(), "{other:?}");
    let other = stdout(&other).trim().to_owned();
    assert_fails_saying(
        &farm.render(&["--label", "Shot=1"]),
        "is not 1 to 63 characters of a-z",
    );
    assert_fails_saying(&farm.render(&["--priority", "101"]), "outside -100..=100");

    let listed = jobs_ok(&address, &["ls", "--label", "shot=010"]);
    assert!(
        listed.contains(&hall) && listed.contains("hall, east wing"),
        "{listed}"
    );
    assert!(!listed.contains(&other), "{listed}");
    let both = jobs_ok(
        &address,
        &["ls", "--label", "team=lidar", "--state", "queued"],
    );
    assert_eq!(both.lines().count(), 2, "a header and the one job: {both}");
    assert!(
        jobs_ok(&address, &["ls", "--state", "paused"])
            .lines()
            .count()
            == 1
    );
    assert!(jobs_ok(&address, &["pause", &hall]).contains("paused"));
    let paused = jobs_ok(&address, &["ls", "--state", "paused"]);
    assert!(
        paused.contains(&hall) && !paused.contains(&other),
        "{paused}"
    );

    let runtime = tokio::runtime::Runtime::new().expect("runtime");
    runtime.block_on(async {
        let (_, mut jobs) = clients(&address).await;
        let dataset_id = get_job(&mut jobs, &hall).await.dataset_id;
        let long_name = pb::SubmitJobRequest {
            name: "n".repeat(129),
            ..turntable_job("long", &dataset_id, 2, 32, 24)
        };
        let (code, message) = code_of(jobs.submit_job(long_name).await);
        assert_eq!(code, tonic::Code::InvalidArgument);
        assert!(
            message.contains("name: is 129 characters long"),
            "{message}"
        );
        let bad_filter = pb::ListJobsRequest {
            labels: [("no spaces".to_string(), "x".to_string())].into(),
            ..Default::default()
        };
        let (code, _) = code_of(jobs.list_jobs(bad_filter).await);
        assert_eq!(code, tonic::Code::InvalidArgument);
    });

    // Killed and started again: the name, labels, priority and pause are all kept.
    farm.restart(&["--no-embedded-worker"]);
    runtime.block_on(async {
        let (_, mut jobs) = clients(&address).await;
        let kept = get_job(&mut jobs, &hall).await;
        assert_eq!(kept.name, "hall, east wing");
        assert_eq!(kept.labels.get("shot").map(String::as_str), Some("010"));
        assert_eq!(kept.labels.get("team").map(String::as_str), Some("lidar"));
        assert_eq!(kept.priority, -5);
        assert_eq!(
            kept.state,
            pb::JobState::Paused as i32,
            "{}",
            farm.server.log()
        );
        assert!(
            kept.waiting_reason.starts_with("paused"),
            "{}",
            kept.waiting_reason
        );
    });
    let shown = jobs_ok(&address, &["show", &hall]);
    assert!(shown.contains("name: hall, east wing"), "{shown}");
    assert!(shown.contains("labels: shot=010, team=lidar"), "{shown}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_failed_job_is_retried_with_fresh_attempts_and_renders() {
    let (daemon, dataset, mut jobs) =
        queued_farm(|config| config.max_frame_attempts = 1, 5_000, 12).await;
    let scratch = tempfile::tempdir().expect("tempdir");
    let job = submit(&mut jobs, turntable_job("retried", &dataset.id, 2, 32, 24)).await;
    let url = daemon.url();
    let (code, message) = code_of(
        jobs.retry_job(pb::RetryJobRequest { id: job.id.clone() })
            .await,
    );
    assert_eq!(code, tonic::Code::FailedPrecondition);
    assert_eq!(
        message,
        format!("job {} is queued; only a failed job can be retried", job.id)
    );

    // A worker that fails its frame: with one attempt allowed, the job fails.
    let mut workers = daemon.workers().await;
    let lease = pb::LeaseFrameRequest {
        worker_name: "flaky".into(),
        wait_ms: 0,
        capabilities: None,
    };
    let task = workers
        .lease_frame(lease)
        .await
        .expect("lease")
        .into_inner()
        .task
        .expect("a frame");
    workers
        .fail_frame(pb::FailFrameRequest {
            lease_id: task.lease_id,
            reason: "the GPU was lost".into(),
            kind: pb::FailureKind::Transient as i32,
        })
        .await
        .expect("fail");
    let failed = get_job(&mut jobs, &job.id).await;
    assert_eq!(failed.state, pb::JobState::Failed as i32);

    let said = jobs_ok(&url, &["retry", &job.id]);
    assert_eq!(
        said.trim(),
        format!("job {} running again (running)", job.id)
    );
    let retried = get_job(&mut jobs, &job.id).await;
    assert_eq!(
        (retried.state, retried.error.as_str()),
        (pb::JobState::Running as i32, "")
    );
    let worker = start_worker(&daemon, scratch.path(), "steady");
    let (done, frames) = watch_to_success(&mut jobs, &job.id, || worker.log()).await;
    assert_eq!((done.frames_done, frames.len()), (2, 2));
    jobs_refused(
        &url,
        &["retry", &job.id],
        "is succeeded; only a failed job can be retried",
    );
    // No worker from here on, so the job below stays queued until it is paused.
    drop(worker);

    // Cancel twice: the second returns the cancelled job as it is.
    let idle = submit(&mut jobs, turntable_job("idle", &dataset.id, 1, 32, 24)).await;
    jobs.pause_job(pb::PauseJobRequest {
        id: idle.id.clone(),
    })
    .await
    .expect("pause");
    let cancel = || pb::CancelJobRequest {
        id: idle.id.clone(),
    };
    let cancelled = jobs
        .cancel_job(cancel())
        .await
        .expect("cancel")
        .into_inner();
    assert_eq!(cancelled.state, pb::JobState::Cancelled as i32);
    let again = jobs
        .cancel_job(cancel())
        .await
        .expect("cancel again")
        .into_inner();
    assert_eq!(again, cancelled);
    jobs_refused(
        &url,
        &["retry", &idle.id],
        "was cancelled; only a failed job can be retried",
    );
    daemon.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_paused_job_leases_nothing_until_it_is_resumed() {
    let (daemon, dataset, mut jobs) = queued_farm(|_| {}, 5_000, 13).await;
    let scratch = tempfile::tempdir().expect("tempdir");
    let job = submit(&mut jobs, turntable_job("paused", &dataset.id, 3, 32, 24)).await;
    let url = daemon.url();
    assert_eq!(
        jobs_ok(&url, &["pause", &job.id]).trim(),
        format!("job {} paused (paused)", job.id)
    );
    assert!(
        jobs_ok(&url, &["pause", &job.id]).contains("(paused)"),
        "idempotent"
    );

    let worker = start_worker(&daemon, scratch.path(), "w");
    // The worker asks for work all along; a paused job gives it none.
    let waited = Instant::now();
    while waited.elapsed() < Duration::from_secs(3) {
        let workers = jobs
            .list_workers(pb::ListWorkersRequest {})
            .await
            .expect("workers")
            .into_inner()
            .workers;
        if !workers.is_empty() {
            break;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    tokio::time::sleep(Duration::from_secs(1)).await;
    let paused = get_job(&mut jobs, &job.id).await;
    assert_eq!(
        (paused.state, paused.frames_done),
        (pb::JobState::Paused as i32, 0),
        "{}",
        worker.log()
    );
    assert_eq!(
        paused.waiting_reason,
        "paused: no frame of it is leased until it is resumed"
    );
    let leases = list_leases(&mut jobs).await;
    assert!(leases.is_empty(), "{leases:?}");

    assert!(jobs_ok(&url, &["resume", &job.id]).contains("resumed"));
    let (done, frames) = watch_to_success(&mut jobs, &job.id, || worker.log()).await;
    assert_eq!((done.frames_done, frames.len()), (3, 3));
    jobs_refused(
        &url,
        &["pause", &job.id],
        "already succeeded; only a queued or running job can be paused",
    );
    daemon.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_frames_of_the_higher_priority_are_leased_first() {
    let (daemon, dataset, mut jobs) = queued_farm(|_| {}, 5_000, 14).await;
    let scratch = tempfile::tempdir().expect("tempdir");
    let older = submit(&mut jobs, turntable_job("older", &dataset.id, 2, 32, 24)).await;
    let younger = submit(&mut jobs, turntable_job("younger", &dataset.id, 2, 32, 24)).await;
    let url = daemon.url();
    assert!(jobs_ok(&url, &["priority", &younger.id, "50"]).contains("priority 50"));
    jobs_refused(&url, &["priority", &older.id, "-101"], "outside -100..=100");

    let (mut watcher, id) = (jobs.clone(), older.id.clone());
    let older_started = tokio::spawn(async move { left_the_queue_at(&mut watcher, &id).await });
    // Started after both submissions: it leases the younger job's frames first.
    let worker = start_worker(&daemon, scratch.path(), "w");
    let (younger_done, _) = watch_to_success(&mut jobs, &younger.id, || worker.log()).await;
    let older_started = older_started.await.expect("the older job's watch");
    assert!(
        older_started >= younger_done.updated_unix_ms,
        "the older job left the queue at {older_started}, before the younger one of higher \
         priority ended at {}",
        younger_done.updated_unix_ms
    );
    watch_to_success(&mut jobs, &older.id, || worker.log()).await;
    jobs_refused(
        &url,
        &["priority", &older.id, "3"],
        "already succeeded; its priority no longer matters",
    );
    daemon.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn deleted_jobs_go_with_their_frames_and_fail_the_jobs_after_them() {
    let daemon = TestDaemon::start(|_| {}, Access::default()).await;
    let (daemon, dataset, mut jobs) = daemon.with_sample(5_000, 15).await;
    let done = submit(&mut jobs, turntable_job("done", &dataset.id, 2, 32, 24)).await;
    watch_to_success(&mut jobs, &done.id, String::new).await;
    let frames = daemon.data_dir.path().join("jobs").join(&done.id);
    assert!(frames.join("frame_00001.png").exists());
    // Frames leased before the pause still finish, and a job whose last frame does ends: enough
    // frames that the worker cannot render them all before the pause lands.
    let held = submit(&mut jobs, turntable_job("held", &dataset.id, 60, 32, 24)).await;
    let paused = jobs
        .pause_job(pb::PauseJobRequest {
            id: held.id.clone(),
        })
        .await
        .expect("pause")
        .into_inner();
    assert_eq!(paused.state, pb::JobState::Paused as i32);
    let after = pb::SubmitJobRequest {
        after_job_ids: vec![done.id.clone(), held.id.clone()],
        ..turntable_job("after", &dataset.id, 2, 32, 24)
    };
    let after = submit(&mut jobs, after).await;
    let url = daemon.url();

    assert!(jobs_ok(&url, &["rm", &done.id]).contains("deleted (succeeded)"));
    let (code, _) = code_of(
        jobs.get_job(pb::GetJobRequest {
            id: done.id.clone(),
        })
        .await,
    );
    assert_eq!(code, tonic::Code::NotFound);
    assert!(!frames.exists(), "its frames are gone");
    let (failed, _) = watch_to_end(&mut jobs, &after.id).await;
    assert_eq!(failed.state, pb::JobState::Failed as i32);
    assert_eq!(
        failed.error,
        format!("job {} it runs after was deleted", done.id)
    );

    jobs_refused(
        &url,
        &["rm", &held.id],
        "is paused; cancel it first, or delete it with force",
    );
    assert!(jobs_ok(&url, &["rm", &held.id, "--force"]).contains("deleted (cancelled)"));
    let (code, _) = code_of(
        jobs.get_job(pb::GetJobRequest {
            id: held.id.clone(),
        })
        .await,
    );
    assert_eq!(code, tonic::Code::NotFound);
    let listed = jobs_ok(&url, &["ls"]);
    let rows: Vec<&str> = listed
        .lines()
        .filter_map(|line| line.split(' ').next())
        .collect();
    assert_eq!(rows, ["id", after.id.as_str()], "{listed}");
    daemon.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_retention_sweep_removes_jobs_that_ended_long_enough_ago() {
    let retention = |config: &mut DaemonConfig| {
        config.job_retention = Some(Duration::from_secs(1));
        config.retention_sweep_period = Duration::from_millis(100);
    };
    let daemon = TestDaemon::start(retention, Access::default()).await;
    let (daemon, dataset, mut jobs) = daemon.with_sample(5_000, 16).await;
    let job = submit(
        &mut jobs,
        turntable_job("kept-a-second", &dataset.id, 2, 32, 24),
    )
    .await;
    // Enough frames that those leased before the pause cannot end it.
    let held = submit(&mut jobs, turntable_job("held", &dataset.id, 60, 32, 24)).await;
    jobs.pause_job(pb::PauseJobRequest {
        id: held.id.clone(),
    })
    .await
    .expect("pause");
    watch_to_success(&mut jobs, &job.id, String::new).await;
    let frames = daemon.data_dir.path().join("jobs").join(&job.id);
    let removed = Instant::now();
    loop {
        let found = jobs.get_job(pb::GetJobRequest { id: job.id.clone() }).await;
        match found {
            Err(status) if status.code() == tonic::Code::NotFound => break,
            Ok(_) => {}
            Err(status) => panic!("{status}"),
        }
        assert!(
            removed.elapsed() < Duration::from_secs(20),
            "the job was never removed"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    assert!(!frames.exists(), "its frames went with it");
    // A job that has not ended stays, however old.
    tokio::time::sleep(Duration::from_millis(1500)).await;
    assert_eq!(
        get_job(&mut jobs, &held.id).await.state,
        pb::JobState::Paused as i32
    );
    daemon.stop().await;
}

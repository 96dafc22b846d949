//! A full disk under the daemon's data: the frames it refuses go back to the queue without an
//! attempt counted, the worker waits instead of spinning, health is NOT_SERVING and the
//! daemon says so once; when space returns the job finishes, without a restart. A job
//! submitted to the full disk is refused before it is written: no one ever sees it listed.
//! A real tmpfs filled to its last byte, a real daemon and a real `pointfarm worker` process.

use std::time::Duration;

use pointfarm_daemon::testing::SmallDisk;
use pointfarm_proto::v1 as pb;
use pointfarm_proto::v1::job_service_client::JobServiceClient;
use pointfarm_tests::health::{wait_for_health, JOB_SERVICE};
use pointfarm_tests::service::{
    clients, connect, get_job, list_leases, scratch_sample, submit, turntable_job, upload_file,
    watch_to_success,
};
use pointfarm_tests::{free_address, wait_for, ServeProcess, WorkerProcess};
use tonic::transport::Channel;
use tonic_health::pb::health_check_response::ServingStatus;

/// Waits up to 30 s until `JobService` on the daemon at `address` reports `status`.
async fn job_service_reports(address: &str, status: ServingStatus) {
    wait_for_health(address, &[JOB_SERVICE], status, Duration::from_secs(30)).await;
}

/// A daemon without an embedded worker whose data lies on a small tmpfs, which both tests fill.
struct DaemonOnSmallDisk {
    server: ServeProcess,
    address: String,
    /// Where the daemon's log lies, off the full disk, so that what it says there is kept.
    outside: tempfile::TempDir,
    disk: SmallDisk,
}

impl DaemonOnSmallDisk {
    /// Mounts the disk and starts the daemon on it with `args`; None, said on stderr, where no
    /// tmpfs can be mounted.
    fn start(args: &[&str]) -> Option<Self> {
        let Some(disk) = SmallDisk::mount(64) else {
            eprintln!("skipped: no tmpfs could be mounted (see above)");
            return None;
        };
        let outside = tempfile::tempdir().expect("tempdir");
        let address = free_address();
        let args: Vec<&str> = ["--no-embedded-worker"]
            .iter()
            .chain(args)
            .copied()
            .collect();
        let server = ServeProcess::start_logging_to(
            &address,
            &disk.path().join("data"),
            &outside.path().join("serve.log"),
            &args,
        );
        Some(Self {
            server,
            address,
            outside,
            disk,
        })
    }
}

/// A small sample uploaded to the daemon at `address`, with a job client of it.
async fn sample_dataset(address: &str) -> (pb::Dataset, JobServiceClient<Channel>) {
    let (mut datasets, jobs) = clients(address).await;
    let (_scratch, file) = scratch_sample("s.las", 20_000, 7);
    (upload_file(&mut datasets, "s.las", &file).await, jobs)
}

/// The jobs ListJobs answers, so a test sees which the daemon took.
async fn listed_jobs(jobs: &mut JobServiceClient<Channel>) -> Vec<pb::Job> {
    jobs.list_jobs(pb::ListJobsRequest::default())
        .await
        .expect("list")
        .into_inner()
        .jobs
}

/// How many lines of `log` say `message`.
fn count(log: &str, message: &str) -> usize {
    log.lines().filter(|l| l.contains(message)).count()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_full_disk_holds_frames_back_and_the_daemon_resumes_when_space_returns() {
    // Declared first, so dropped last: the worker on the disk stops before it is unmounted.
    let Some(mut farm) = DaemonOnSmallDisk::start(&["--lease-timeout", "5"]) else {
        return;
    };
    let (dataset, mut jobs) = sample_dataset(&farm.address).await;
    let job = submit(&mut jobs, turntable_job("full", &dataset.id, 4, 64, 48)).await;

    let filler = farm.disk.fill("filler");
    // The worker's own cache is elsewhere: only the daemon's disk is full.
    let worker = WorkerProcess::start(
        &format!("http://{}", farm.address),
        &farm.outside.path().join("worker"),
        "w",
    );
    wait_for(Duration::from_secs(120), "disk-full report", || {
        farm.server
            .log()
            .contains("the daemon's disk is full")
            .then_some(())
    });
    job_service_reports(&farm.address, ServingStatus::NotServing).await;
    // A few rounds of the worker's backoff while the disk stays full.
    tokio::time::sleep(Duration::from_secs(4)).await;
    let held_back = get_job(&mut jobs, &job.id).await;
    assert_eq!(held_back.frames_done, 0, "{}", farm.server.log());
    let leases = list_leases(&mut JobServiceClient::new(connect(&farm.address).await)).await;
    assert!(
        leases.is_empty(),
        "refused frames are given back: {leases:?}"
    );
    let frames_dir = farm.disk.path().join("data/jobs").join(&job.id);
    let partial: Vec<_> = std::fs::read_dir(&frames_dir)
        .map(|entries| entries.flatten().map(|e| e.file_name()).collect())
        .unwrap_or_default();
    assert!(partial.is_empty(), "files left behind: {partial:?}");
    let log = farm.server.log();
    assert_eq!(
        count(&log, "the daemon's disk is full"),
        1,
        "said once, not per frame:\n{log}"
    );
    let worker_log = worker.log();
    assert!(
        count(&worker_log, "the daemon cannot store frames now") <= 1
            && count(&worker_log, "could not store the frame") <= 1,
        "the worker says it waits once, not per try:\n{worker_log}"
    );

    std::fs::remove_file(filler).expect("free the disk");
    let (_, frames) = watch_to_success(&mut jobs, &job.id, || {
        format!("{}\n{}", farm.server.log(), worker.log())
    })
    .await;
    let attempts: Vec<(u32, u32)> = frames
        .iter()
        .map(|f| (f.index, f.failed_attempts))
        .collect();
    assert_eq!(
        attempts,
        [(0, 0), (1, 0), (2, 0), (3, 0)],
        "every frame once, no attempt counted against any"
    );
    assert!(farm.server.is_running(), "no restart");
    assert!(
        farm.server.log().contains("takes writes again"),
        "{}",
        farm.server.log()
    );
    job_service_reports(&farm.address, ServingStatus::Serving).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_job_submitted_to_a_full_disk_is_refused_before_anyone_sees_it() {
    let Some(farm) = DaemonOnSmallDisk::start(&[]) else {
        return;
    };
    let (dataset, mut jobs) = sample_dataset(&farm.address).await;

    let filler = farm.disk.fill("filler");
    let refused = jobs
        .submit_job(turntable_job("on-a-full-disk", &dataset.id, 4, 64, 48))
        .await
        .expect_err("no room for the job");
    assert_eq!(refused.code(), tonic::Code::ResourceExhausted, "{refused}");
    assert!(
        refused.message().contains("the daemon's disk is full"),
        "{refused}"
    );
    let listed = listed_jobs(&mut jobs).await;
    assert!(listed.is_empty(), "the refused job is listed: {listed:?}");

    // Once the daemon's probe finds room again, the same submission makes the job.
    std::fs::remove_file(filler).expect("free the disk");
    let deadline = tokio::time::Instant::now() + Duration::from_secs(30);
    let job = loop {
        let submitted = jobs
            .submit_job(turntable_job("on-a-full-disk", &dataset.id, 4, 64, 48))
            .await;
        match submitted {
            Ok(job) => break job.into_inner(),
            Err(status) if status.code() == tonic::Code::ResourceExhausted => {
                assert!(
                    tokio::time::Instant::now() < deadline,
                    "still refused 30 s after space returned: {status}"
                );
                tokio::time::sleep(Duration::from_millis(200)).await;
            }
            Err(status) => panic!("{status}"),
        }
    };
    let listed = listed_jobs(&mut jobs).await;
    assert_eq!(
        listed.iter().map(|j| j.id.as_str()).collect::<Vec<_>>(),
        [job.id.as_str()],
        "{}",
        farm.server.log()
    );
}

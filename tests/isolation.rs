//! A bad frame never stops the farm: the embedded worker is a child process of the daemon, so a
//! worker killed mid-frame is restarted and the frame rendered once by its successor; a frame
//! that crashes its worker every time fails its job after its attempts, also across daemon
//! restarts; health says whether any worker can render. (That an unreadable dataset fails its
//! job at once is tested in `service.rs`.)

use std::time::Duration;

use pointfarm_daemon::access::Access;
use pointfarm_proto::v1 as pb;
use pointfarm_proto::v1::job_service_client::JobServiceClient;
use pointfarm_tests::health::{health, wait_for_health, JOB_SERVICE};
use pointfarm_tests::service::{
    clients, connect, list_leases, scratch_sample, submit, turntable_job, upload_file,
    watch_to_end, watch_to_success, TestDaemon,
};
use pointfarm_tests::WorkerProcess;
use pointfarm_tests::{process_is_gone, signal, wait_for, write_dense_laz, ServeProcess};
use tonic_health::pb::health_check_response::ServingStatus;

/// The leases the daemon at `address` holds now.
async fn leases(address: &str) -> Vec<pb::Lease> {
    list_leases(&mut JobServiceClient::new(connect(address).await)).await
}

/// Waits until the embedded worker holds a frame of `job_id`; returns its index.
async fn embedded_lease_of(address: &str, job_id: &str) -> u32 {
    let deadline = tokio::time::Instant::now() + Duration::from_secs(120);
    loop {
        let held = leases(address).await;
        if let Some(lease) = held.iter().find(|l| l.embedded && l.job_id == job_id) {
            return lease.frame_index;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "the embedded worker never leased a frame of {job_id}"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

/// Waits up to 10 s for the process `pid` to end.
fn assert_gone_soon(pid: u32, what: &str) {
    wait_for(Duration::from_secs(10), what, || {
        process_is_gone(pid).then_some(())
    });
}

/// Lines of `log` that say `message`.
fn lines_saying<'a>(log: &'a str, message: &str) -> Vec<&'a str> {
    log.lines().filter(|l| l.contains(message)).collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_worker_killed_mid_frame_is_restarted_and_the_frame_rendered_once() {
    let data = tempfile::tempdir().expect("tempdir");
    // Large enough that loading it keeps the first frame's lease for a while.
    let (_scratch, file) = scratch_sample("scan.laz", 1_500_000, 5);
    let mut server = ServeProcess::start_with(&data.path().join("data"), &[]);
    let (mut datasets, mut jobs) = clients(&server.address).await;
    let dataset = upload_file(&mut datasets, "scan.laz", &file).await;
    let job = submit(&mut jobs, turntable_job("killed", &dataset.id, 3, 64, 48)).await;

    let index = embedded_lease_of(&server.address, &job.id).await;
    let first = server.embedded_worker_pid();
    signal(first, "KILL");

    let (_, frames) = watch_to_success(&mut jobs, &job.id, || server.log()).await;
    assert!(server.is_running(), "the daemon survives its worker");
    let log = server.log();
    let pids = server.embedded_worker_pids();
    assert_eq!(pids.len(), 2, "restarted once:\n{log}");
    assert_eq!(pids[0], first);
    assert!(
        lines_saying(&log, "embedded worker exited")
            .iter()
            .any(|l| l.contains("killed by signal 9 (SIGKILL)")),
        "{log}"
    );
    let attempts: Vec<(u32, u32)> = frames
        .iter()
        .map(|f| (f.index, f.failed_attempts))
        .collect();
    let expected: Vec<(u32, u32)> = (0..3).map(|i| (i, u32::from(i == index))).collect();
    assert_eq!(attempts, expected, "the killed frame's attempt counts");
    let rendered = lines_saying(&log, "frame rendered");
    let killed_frame = format!("frame={index} ");
    assert_eq!(
        rendered
            .iter()
            .filter(|l| l.contains(&killed_frame))
            .count(),
        1,
        "frame {index} rendered exactly once, by the new worker:\n{log}"
    );

    // Stopping lets the worker finish and leaves no process behind.
    let second = pids[1];
    let status = server.terminate(Duration::from_secs(60));
    assert!(status.is_some_and(|s| s.success()), "{status:?}\n{log}");
    assert_gone_soon(
        second,
        "exit of the embedded worker after the daemon stopped",
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_frame_that_crashes_its_worker_fails_its_job_also_across_daemon_restarts() {
    let data = tempfile::tempdir().expect("tempdir");
    let data_dir = data.path().join("data");
    let scratch = tempfile::tempdir().expect("tempdir");
    // Decoding needs well over the worker's memory limit, so the worker aborts every time: a
    // dataset small enough to be rendered resident (a larger one would be rendered from
    // levels of detail, within the limit).
    let poison_file = scratch.path().join("poison.laz");
    const POISON_POINTS: usize = 19_500_000;
    assert!(POISON_POINTS as u64 <= pointfarm_render::cut::RESIDENT_MAX_POINTS);
    write_dense_laz(&poison_file, POISON_POINTS);
    let (_good_scratch, good_file) = scratch_sample("good.laz", 20_000, 6);
    let args = [
        "--worker-max-memory-mib",
        "384",
        "--max-frame-attempts",
        "2",
    ];
    let mut server = ServeProcess::start_with(&data_dir, &args);
    let address = server.address.clone();
    let (mut datasets, mut jobs) = clients(&address).await;
    let poison = upload_file(&mut datasets, "poison.laz", &poison_file).await;
    let good = upload_file(&mut datasets, "good.laz", &good_file).await;

    let poisoned = submit(&mut jobs, turntable_job("poison-1", &poison.id, 1, 64, 48)).await;
    let next = submit(&mut jobs, turntable_job("good-1", &good.id, 1, 64, 48)).await;
    let (failed, _) = watch_to_end(&mut jobs, &poisoned.id).await;
    let log = server.log();
    assert_eq!(failed.state, pb::JobState::Failed as i32, "{log}");
    assert!(
        failed.error.starts_with("frame 0 failed 2 times; last: worker embedded died while rendering frame 0 (killed by signal"),
        "reason: {}\n{log}",
        failed.error
    );
    watch_to_success(&mut jobs, &next.id, || server.log()).await;
    assert!(server.is_running());

    // The daemon itself dies while its worker holds the poison frame: the worker goes with
    // it, and the restarted daemon counts that attempt instead of rendering the frame anew.
    let again = submit(&mut jobs, turntable_job("poison-2", &poison.id, 1, 64, 48)).await;
    embedded_lease_of(&address, &again.id).await;
    let worker = server.embedded_worker_pid();
    server.kill();
    assert_gone_soon(
        worker,
        "exit of the embedded worker after the daemon was killed",
    );
    drop(server);

    let before_restart = std::fs::read_to_string(data_dir.join("serve.log")).expect("log");
    let server = ServeProcess::start_with_args(&address, &data_dir, &args);
    let (_, mut jobs) = clients(&address).await;
    let (failed, _) = watch_to_end(&mut jobs, &again.id).await;
    let log = server.log();
    let after_restart = &log[before_restart.len()..];
    assert_eq!(failed.state, pb::JobState::Failed as i32, "{after_restart}");
    assert!(
        failed.error.starts_with("frame 0 failed 2 times;"),
        "reason: {}",
        failed.error
    );
    assert_eq!(
        lines_saying(after_restart, "embedded worker exited").len(),
        1,
        "one crash after the restart, the other attempt counted from the killed run:\n{after_restart}"
    );
    let last = submit(&mut jobs, turntable_job("good-2", &good.id, 1, 64, 48)).await;
    watch_to_success(&mut jobs, &last.id, || server.log()).await;
}

/// The daemon as a whole and its `JobService`: what says whether a worker can render.
const RENDERING: [&str; 2] = ["", JOB_SERVICE];

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn health_says_whether_a_worker_can_render() {
    let daemon = TestDaemon::start_without_worker(
        |config| config.lease_timeout = Duration::from_secs(1),
        Access::default(),
    )
    .await;
    let address = daemon.address.to_string();
    let rendering = |status, seconds| {
        wait_for_health(&address, &RENDERING, status, Duration::from_secs(seconds))
    };
    rendering(ServingStatus::NotServing, 5).await;
    // Uploads and workers are served all the same.
    for service in ["pointfarm.v1.DatasetService", "pointfarm.v1.WorkerService"] {
        assert_eq!(
            health(&address, service).await,
            ServingStatus::Serving as i32
        );
    }

    let cache = tempfile::tempdir().expect("tempdir");
    let mut worker = WorkerProcess::start(&daemon.url(), &cache.path().join("w"), "w");
    rendering(ServingStatus::Serving, 120).await;
    worker.kill();
    rendering(ServingStatus::NotServing, 10).await;
    let _back = WorkerProcess::start(&daemon.url(), &cache.path().join("w"), "w");
    rendering(ServingStatus::Serving, 120).await;
    daemon.stop().await;
}

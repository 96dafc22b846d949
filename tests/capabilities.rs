//! Worker capabilities and the per-job blocklist with real `pointfarm worker` processes: two
//! workers of different frame limits and tags each get only the frames they can render, a job
//! no connected worker can render says why, a worker whose frames keep failing is blocklisted
//! for that job while another finishes it, and `--adapter-index` out of range lists the
//! adapters.

use std::path::Path;
use std::time::Duration;

use pointfarm_daemon::access::Access;
use pointfarm_proto::v1 as pb;
use pointfarm_proto::v1::job_service_client::JobServiceClient;
use pointfarm_tests::datasets::register_path;
use pointfarm_tests::service::{
    cancel, get_job, scratch_sample, submit, turntable_job, upload_sample, watch_to_success,
    TestDaemon,
};
use pointfarm_tests::{assert_fails_saying, pointfarm, stdout, wait_for, WorkerProcess};
use tonic::transport::Channel;

/// `pointfarm jobs show ID` against `url`, as text.
async fn jobs_show(url: &str, id: &str) -> String {
    let (url, id) = (url.to_owned(), id.to_owned());
    let output =
        tokio::task::spawn_blocking(move || pointfarm(&["jobs", "show", &id, "--server", &url]))
            .await
            .expect("jobs show");
    assert!(output.status.success(), "{output:?}");
    stdout(&output)
}

/// Waits (up to 2 minutes) until GetJob of `id` satisfies `done`; returns that job.
async fn job_when(
    jobs: &mut JobServiceClient<Channel>,
    id: &str,
    what: &str,
    done: impl Fn(&pb::Job) -> bool,
    context: impl Fn() -> String,
) -> pb::Job {
    let deadline = tokio::time::Instant::now() + Duration::from_secs(120);
    loop {
        let job = get_job(jobs, id).await;
        if done(&job) {
            return job;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "{what}: {job:?}\n{}",
            context()
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

/// Waits until the worker has its GPU and asks for frames.
fn wait_started(worker: &WorkerProcess) {
    wait_for(Duration::from_secs(120), "worker start", || {
        worker.log().contains("worker started").then_some(())
    });
}

fn with_requirements(
    mut request: pb::SubmitJobRequest,
    gpu: bool,
    tags: &[&str],
) -> pb::SubmitJobRequest {
    request.requirements = Some(pb::WorkerRequirements {
        gpu,
        tags: tags.iter().map(|t| t.to_string()).collect(),
    });
    request
}

/// The names of the workers that rendered `frames`, each once, sorted.
fn workers_of(frames: &[pb::FrameFinished]) -> Vec<String> {
    let mut names: Vec<String> = frames.iter().map(|f| f.worker_name.clone()).collect();
    names.sort();
    names.dedup();
    names
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn frames_go_only_to_workers_that_can_render_them() {
    let daemon = TestDaemon::start_without_worker(|_| {}, Access::default()).await;
    let scratch = tempfile::tempdir().expect("tempdir");
    let dataset = upload_sample(&mut daemon.datasets().await, 20_000, 11).await;
    let mut jobs = daemon.jobs().await;
    // The same adapter (lavapipe here), two operator settings: a small frame limit and one
    // tag, or the adapter's own limit and another tag.
    let small = WorkerProcess::start_with(
        &daemon.url(),
        &scratch.path().join("small"),
        "small",
        &[
            "--max-frame-side",
            "100",
            "--tag",
            "site-x",
            "--adapter-index",
            "0",
        ],
    );
    let large = WorkerProcess::start_with(
        &daemon.url(),
        &scratch.path().join("large"),
        "large",
        &["--tag", "big-frames"],
    );
    let logs = || format!("small:\n{}\nlarge:\n{}", small.log(), large.log());
    wait_started(&small);
    wait_started(&large);

    // A job no connected worker can render waits, saying why.
    let gpu_only = submit(
        &mut jobs,
        with_requirements(turntable_job("gpu", &dataset.id, 1, 32, 24), true, &[]),
    )
    .await;
    let waiting = job_when(
        &mut jobs,
        &gpu_only.id,
        "both workers connected and refusing",
        |job| job.refusals.len() == 2,
        logs,
    )
    .await;
    assert_eq!(waiting.waiting_reason, "no connected worker has a GPU");
    assert_eq!(waiting.state, pb::JobState::Queued as i32);
    let shown = jobs_show(&daemon.url(), &gpu_only.id).await;
    assert!(shown.contains("requires: a GPU"), "{shown}");
    assert!(
        shown.contains("waiting: no connected worker has a GPU"),
        "{shown}"
    );
    assert!(
        shown.contains("worker small cannot render it: the job requires a GPU; the worker has a software adapter"),
        "{shown}"
    );
    // What each connected worker advertises.
    let mut listed = jobs
        .list_workers(pb::ListWorkersRequest {})
        .await
        .expect("list workers")
        .into_inner()
        .workers;
    listed.sort_by(|a, b| a.worker_name.cmp(&b.worker_name));
    let advertised: Vec<(String, u32, Vec<String>)> = listed
        .iter()
        .map(|w| {
            let caps = w.capabilities.clone().unwrap_or_default();
            (w.worker_name.clone(), caps.max_frame_side, caps.tags)
        })
        .collect();
    assert_eq!(
        advertised,
        vec![
            ("large".to_string(), 16384, vec!["big-frames".to_string()]),
            ("small".to_string(), 100, vec!["site-x".to_string()]),
        ]
    );
    let url = daemon.url();
    let table =
        tokio::task::spawn_blocking(move || pointfarm(&["jobs", "workers", "--server", &url]))
            .await
            .expect("jobs workers");
    let table = stdout(&table);
    assert!(
        table
            .lines()
            .any(|l| l.starts_with("small") && l.contains(" 100 ") && l.ends_with("site-x")),
        "{table}"
    );
    cancel(&mut jobs, &gpu_only.id).await;

    // Tagged frames go to the tagged worker; frames larger than the small one draws go to the
    // other, also at the head of the queue.
    let large_frames = submit(
        &mut jobs,
        pb::SubmitJobRequest {
            priority: 1,
            ..turntable_job("large", &dataset.id, 3, 160, 120)
        },
    )
    .await;
    let tagged = submit(
        &mut jobs,
        with_requirements(
            turntable_job("tagged", &dataset.id, 3, 64, 48),
            false,
            &["site-x"],
        ),
    )
    .await;
    let (_, tagged_frames) = watch_to_success(&mut jobs, &tagged.id, logs).await;
    let (_, big_frames) = watch_to_success(&mut jobs, &large_frames.id, logs).await;
    assert_eq!(workers_of(&tagged_frames), vec!["small"], "{}", logs());
    assert_eq!(workers_of(&big_frames), vec!["large"], "{}", logs());
    let shown = jobs_show(&daemon.url(), &tagged.id).await;
    assert!(shown.contains("requires: tags site-x"), "{shown}");
    assert!(shown.contains("frames by worker: small 3"), "{shown}");
    assert!(!shown.contains("waiting"), "{shown}");
    daemon.stop().await;
}

/// Overwrites the middle of `path` with other bytes of the same length: a file changed after
/// it was registered, whose download no worker can check.
fn change_in_place(path: &Path) -> Vec<u8> {
    let original = std::fs::read(path).expect("read");
    let mut changed = original.clone();
    let middle = changed.len() / 2;
    for byte in &mut changed[middle..middle + 64] {
        *byte ^= 0xA5;
    }
    std::fs::write(path, &changed).expect("write");
    original
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_worker_that_fails_three_frames_of_a_job_is_blocklisted_for_it() {
    let (roots, file) = scratch_sample("scan.las", 20_000, 12);
    let root = roots.path().to_path_buf();
    let daemon = TestDaemon::start_without_worker(
        move |config| {
            config.data_roots = vec![root];
            // The failing worker retries the frame at the head of the queue: enough attempts
            // that the blocklist (3), not the frame's attempts, stops it.
            config.max_frame_attempts = 10;
        },
        Access::default(),
    )
    .await;
    let dataset = register_path(&mut daemon.datasets().await, "scan.las").await;
    let mut jobs = daemon.jobs().await;
    let scratch = tempfile::tempdir().expect("tempdir");

    // The registered file changes on the server: every download of it fails its checksum,
    // a transient failure (the file may be restored), so the frame is retried.
    let original = change_in_place(&file);
    let job = submit(&mut jobs, turntable_job("blocked", &dataset.id, 4, 64, 48)).await;
    let flaky = WorkerProcess::start(&daemon.url(), &scratch.path().join("flaky"), "flaky");
    let blocked = job_when(
        &mut jobs,
        &job.id,
        "the failing worker blocklisted",
        |job| !job.blocklisted_workers.is_empty(),
        || flaky.log(),
    )
    .await;
    assert_eq!(
        blocked.blocklisted_workers,
        vec![pb::BlocklistedWorker {
            worker_name: "flaky".into(),
            failed_frames: 3
        }]
    );
    assert_eq!(
        blocked.state,
        pb::JobState::Running as i32,
        "{}",
        blocked.error
    );
    let waiting = job_when(
        &mut jobs,
        &job.id,
        "the blocklisted worker connected and refused",
        |job| !job.waiting_reason.is_empty(),
        || flaky.log(),
    )
    .await;
    assert_eq!(
        waiting.waiting_reason,
        "every connected worker is blocklisted for this job"
    );
    let shown = jobs_show(&daemon.url(), &job.id).await;
    assert!(
        shown.contains("blocklisted workers: flaky (3 failed frames)"),
        "{shown}"
    );
    assert!(
        shown.contains("waiting: every connected worker is blocklisted for this job"),
        "{shown}"
    );

    // The file is back; the blocklisted worker, still asking, gets none of the job's frames,
    // and another worker renders them all.
    std::fs::write(&file, original).expect("restore");
    let steady = WorkerProcess::start(&daemon.url(), &scratch.path().join("steady"), "steady");
    let logs = || format!("flaky:\n{}\nsteady:\n{}", flaky.log(), steady.log());
    let (finished, frames) = watch_to_success(&mut jobs, &job.id, logs).await;
    assert_eq!(finished.frames_done, 4);
    assert_eq!(workers_of(&frames), vec!["steady"], "{}", logs());
    let retried: Vec<(u32, u32)> = frames
        .iter()
        .filter(|f| f.failed_attempts > 0)
        .map(|f| (f.index, f.failed_attempts))
        .collect();
    assert_eq!(retried, vec![(0, 3)], "the failing worker retried frame 0");
    assert_eq!(
        flaky.log().matches("frame failed").count(),
        3,
        "{}",
        flaky.log()
    );
    let shown = jobs_show(&daemon.url(), &job.id).await;
    assert!(shown.contains("frames by worker: steady 4"), "{shown}");
    assert!(
        shown.contains("blocklisted workers: flaky (3 failed frames)"),
        "{shown}"
    );
    drop(steady);
    drop(flaky);
    daemon.stop().await;
}

#[test]
fn an_adapter_index_out_of_range_lists_the_adapters() {
    let scratch = tempfile::tempdir().expect("tempdir");
    let cache = scratch.path().join("cache");
    let output = pointfarm(&[
        "worker",
        "--server",
        "http://127.0.0.1:9",
        "--cache-dir",
        cache.to_str().expect("utf-8"),
        "--adapter-index",
        "5",
    ]);
    assert_fails_saying(&output, "adapter index 5 is out of range");
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(stderr.contains("0: "), "the adapters are listed: {stderr}");
    // Requirements choose a server's workers: a local render refuses them.
    let out = scratch.path().join("local.png");
    let local = pointfarm(&[
        "render",
        "missing.las",
        "--require-gpu",
        "--out",
        out.to_str().expect("utf-8"),
    ]);
    assert_fails_saying(&local, "they need --server");
    let bad_tag = pointfarm(&[
        "worker",
        "--tag",
        "two words",
        "--server",
        "http://127.0.0.1:9",
    ]);
    assert_fails_saying(&bad_tag, "--tag");
}

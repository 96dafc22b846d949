//! Workers as separate processes: a daemon without an embedded worker, real `pointfarm worker`
//! processes leasing frames over loopback gRPC, a worker killed mid-frame, and the lease rules
//! (expiry, stale completions, cancel) spoken directly over the WorkerService.

use std::path::PathBuf;
use std::time::Duration;

use pointfarm_daemon::access::Access;
use pointfarm_daemon::service::DaemonConfig;
use pointfarm_proto::v1 as pb;
use pointfarm_proto::v1::job_service_client::JobServiceClient;
use pointfarm_proto::v1::worker_service_client::WorkerServiceClient;
use pointfarm_tests::service::{
    assert_equal_to_direct_renders, clients, fetch_images, get_job, lease_at_once, list_leases,
    scan, scratch_sample, submit, turntable_job, upload, watch_to_success, TestDaemon,
};
use pointfarm_tests::WorkerProcess;
use tonic::metadata::{Ascii, MetadataValue};
use tonic::service::interceptor::InterceptedService;
use tonic::transport::Channel;
use tonic::Code;

/// Adds `authorization: Bearer <token>` when there is a token.
#[derive(Clone)]
struct Token(Option<MetadataValue<Ascii>>);

impl tonic::service::Interceptor for Token {
    fn call(
        &mut self,
        mut request: tonic::Request<()>,
    ) -> Result<tonic::Request<()>, tonic::Status> {
        if let Some(value) = &self.0 {
            request
                .metadata_mut()
                .insert("authorization", value.clone());
        }
        Ok(request)
    }
}

impl Token {
    fn new(token: Option<&str>) -> Self {
        Self(token.map(|t| format!("Bearer {t}").parse().expect("header value")))
    }
}

type Workers = WorkerServiceClient<InterceptedService<Channel, Token>>;
type Jobs = JobServiceClient<InterceptedService<Channel, Token>>;

/// A daemon without an embedded worker, with `scan` uploaded to it.
struct DaemonWithScan {
    daemon: TestDaemon,
    /// Holds the scan when it was generated, and the workers' caches.
    scratch: tempfile::TempDir,
    file: PathBuf,
    dataset: pb::Dataset,
}

impl DaemonWithScan {
    async fn start(configure: impl FnOnce(&mut DaemonConfig)) -> Self {
        let daemon = TestDaemon::start_without_worker(configure, Access::default()).await;
        let scratch = tempfile::tempdir().expect("tempdir");
        let file = scan(scratch.path());
        let mut datasets = daemon.datasets().await;
        let dataset = upload(
            &mut datasets,
            "scan.laz",
            &std::fs::read(&file).expect("read scan"),
        )
        .await;
        Self {
            daemon,
            scratch,
            file,
            dataset,
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_worker_process_renders_a_turntable_like_the_renderer() {
    let DaemonWithScan {
        daemon,
        scratch,
        file,
        dataset,
    } = DaemonWithScan::start(|_| {}).await;
    let mut jobs = daemon.jobs().await;
    let job = submit(&mut jobs, turntable_job("remote", &dataset.id, 4, 160, 120)).await;

    let mut worker = WorkerProcess::start(&daemon.url(), &scratch.path().join("cache"), "w1");
    let (_, frames) = watch_to_success(&mut jobs, &job.id, || worker.log()).await;
    assert_eq!(frames.len(), 4);
    // The worker downloaded and decoded the dataset once, and kept it on the GPU for the
    // other frames.
    let loads: Vec<Option<bool>> = frames.iter().map(|f| f.dataset_cache_hit).collect();
    assert_eq!(
        loads.iter().filter(|l| l.is_some()).count(),
        1,
        "one load: {loads:?}"
    );
    assert!(loads.contains(&Some(false)), "{loads:?}");
    for frame in &frames {
        let stages: Vec<&str> = frame.timings.iter().map(|t| t.stage.as_str()).collect();
        assert!(
            stages.contains(&"rasterize") && stages.contains(&"encode"),
            "{stages:?}"
        );
        assert_eq!(frame.failed_attempts, 0);
    }
    let fetched = fetch_images(&mut jobs, &job.id, 0).await;
    assert_equal_to_direct_renders(&file, 4, (160, 120), &fetched);

    // SIGTERM while waiting for work: the worker exits cleanly.
    let status = worker
        .terminate(Duration::from_secs(10))
        .expect("the worker stops within 10 s of SIGTERM");
    assert!(status.success(), "exit status {status}\n{}", worker.log());
    daemon.stop().await;
}

/// `kill -9` of a worker holding a lease: the daemon goes on, the frame returns to the queue
/// when the lease expires, and a second worker finishes the job with every frame exactly once.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_worker_killed_mid_frame_loses_nothing() {
    let DaemonWithScan {
        daemon,
        scratch,
        file,
        dataset,
    } = DaemonWithScan::start(|config| config.lease_timeout = Duration::from_secs(2)).await;
    let mut jobs = daemon.jobs().await;
    let mut lister = daemon.jobs().await;
    let job = submit(&mut jobs, turntable_job("killed", &dataset.id, 4, 160, 120)).await;

    let mut first = WorkerProcess::start(&daemon.url(), &scratch.path().join("cache-1"), "first");
    // The first lease of a fresh worker covers downloading and decoding the dataset: the
    // worker is killed while it holds that lease.
    let held = wait_for_lease(&mut lister, &job.id, || first.log()).await;
    first.kill();
    assert_eq!(held.worker_name, "first");
    assert!(
        list_leases(&mut lister)
            .await
            .iter()
            .any(|l| l.lease_id == held.lease_id),
        "the worker handed its frame in before the kill; the test needs it mid-frame"
    );
    // The daemon keeps serving.
    let now = get_job(&mut jobs, &job.id).await;
    assert_eq!(now.state, pb::JobState::Running as i32);

    let second = WorkerProcess::start(&daemon.url(), &scratch.path().join("cache-2"), "second");
    let (finished, frames) = watch_to_success(&mut jobs, &job.id, || second.log()).await;
    assert_eq!(finished.frames_done, 4);
    let mut indices: Vec<u32> = frames.iter().map(|f| f.index).collect();
    indices.sort();
    assert_eq!(
        indices,
        vec![0, 1, 2, 3],
        "every frame finished exactly once"
    );
    for frame in &frames {
        let expected = u32::from(frame.index == held.frame_index);
        assert_eq!(
            frame.failed_attempts, expected,
            "frame {} (the killed worker held frame {})",
            frame.index, held.frame_index
        );
    }
    let fetched = fetch_images(&mut jobs, &job.id, 0).await;
    assert_equal_to_direct_renders(&file, 4, (160, 120), &fetched);
    assert!(list_leases(&mut lister).await.is_empty());
    daemon.stop().await;
}

async fn lease(workers: &mut Workers) -> Option<pb::FrameTask> {
    workers
        .lease_frame(lease_at_once("test"))
        .await
        .expect("lease")
        .into_inner()
        .task
}

/// The job `id` as GetJob shows it to a client with a token.
async fn shown_job(jobs: &mut Jobs, id: &str) -> pb::Job {
    jobs.get_job(pb::GetJobRequest { id: id.into() })
        .await
        .expect("get")
        .into_inner()
}

async fn heartbeat(workers: &mut Workers, task: &pb::FrameTask) -> pb::HeartbeatResponse {
    workers
        .heartbeat(pb::HeartbeatRequest {
            lease_id: task.lease_id.clone(),
        })
        .await
        .expect("heartbeat")
        .into_inner()
}

fn png(width: u32, height: u32) -> Vec<u8> {
    let mut bytes = Vec::new();
    image::RgbaImage::from_pixel(width, height, image::Rgba([10, 20, 30, 255]))
        .write_to(
            &mut std::io::Cursor::new(&mut bytes),
            image::ImageFormat::Png,
        )
        .expect("encode");
    bytes
}

async fn complete(
    workers: &mut Workers,
    task: &pb::FrameTask,
    png: Vec<u8>,
) -> Result<(), tonic::Status> {
    let result = pb::CompleteFrameRequest {
        part: Some(pb::complete_frame_request::Part::Result(pb::FrameResult {
            lease_id: task.lease_id.clone(),
            png_size_bytes: png.len() as u64,
            timings: vec![pb::StageTiming {
                stage: "rasterize".into(),
                ms: 1.0,
                gpu_clock: false,
            }],
            dataset_cache_hit: None,
            cut: None,
            preview: false,
            completeness: 0.0,
        })),
    };
    let chunks: Vec<pb::CompleteFrameRequest> = png
        .chunks(1000)
        .map(|c| pb::CompleteFrameRequest {
            part: Some(pb::complete_frame_request::Part::Png(c.to_vec())),
        })
        .collect();
    workers
        .complete_frame(tokio_stream::iter(std::iter::once(result).chain(chunks)))
        .await
        .map(|_| ())
}

/// The lease rules over the wire: one holder per frame, expiry counts an attempt and refuses
/// the late completion, release does not count, cancel says stop, a frame whose leases keep
/// expiring fails its job.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn stale_and_cancelled_leases_are_refused() {
    let lease_timeout = Duration::from_secs(1);
    let daemon = TestDaemon::start_without_worker(
        |config| {
            config.lease_timeout = lease_timeout;
            config.max_frame_attempts = 2;
        },
        Access::new(Some("c1ient"), Some("s3cret")),
    )
    .await;
    let channel = daemon.channel().await;
    let refused = WorkerServiceClient::new(channel.clone())
        .lease_frame(pb::LeaseFrameRequest::default())
        .await
        .expect_err("no token");
    assert_eq!(refused.code(), Code::Unauthenticated);
    let (worker_token, client_token) = (Token::new(Some("s3cret")), Token::new(Some("c1ient")));
    let mut workers = WorkerServiceClient::with_interceptor(channel.clone(), worker_token);
    let mut datasets =
        pointfarm_proto::v1::dataset_service_client::DatasetServiceClient::with_interceptor(
            channel.clone(),
            client_token.clone(),
        );
    let mut jobs = JobServiceClient::with_interceptor(channel.clone(), client_token.clone());
    // Each role's token opens only its own services.
    let denied = WorkerServiceClient::with_interceptor(channel.clone(), client_token)
        .lease_frame(pb::LeaseFrameRequest::default())
        .await
        .expect_err("a client token on the worker service");
    assert_eq!(
        denied.code(),
        Code::PermissionDenied,
        "{}",
        denied.message()
    );
    let denied = JobServiceClient::with_interceptor(channel, Token::new(Some("s3cret")))
        .list_leases(pb::ListLeasesRequest {})
        .await
        .expect_err("a worker token on the job service");
    assert_eq!(
        denied.code(),
        Code::PermissionDenied,
        "{}",
        denied.message()
    );

    let (_scratch, file) = scratch_sample("s.laz", 2_000, 7);
    let bytes = std::fs::read(&file).expect("read");
    let dataset = datasets
        .upload_dataset(tokio_stream::iter(
            pointfarm_tests::service::upload_messages("s.laz", &bytes),
        ))
        .await
        .expect("upload")
        .into_inner();
    let job = jobs
        .submit_job(turntable_job("leases", &dataset.id, 2, 32, 24))
        .await
        .expect("submit")
        .into_inner();

    // One holder per frame.
    let first = lease(&mut workers).await.expect("frame 0");
    let second = lease(&mut workers).await.expect("frame 1");
    assert_eq!((first.frame_index, second.frame_index), (0, 1));
    assert!(
        lease(&mut workers).await.is_none(),
        "both frames are leased"
    );
    assert_eq!(
        first.dataset.as_ref().map(|d| d.sha256.as_str()),
        Some(dataset.sha256.as_str())
    );
    assert_eq!((first.width, first.height), (32, 24));
    assert_eq!(
        heartbeat(&mut workers, &first).await.action,
        pb::LeaseAction::Continue as i32
    );

    // The dataset's bytes, for a worker without them.
    let mut stream = workers
        .fetch_dataset(pb::FetchDatasetRequest {
            dataset_id: dataset.id.clone(),
            file_index: 0,
        })
        .await
        .expect("fetch dataset")
        .into_inner();
    let mut fetched = Vec::new();
    while let Some(chunk) = stream.message().await.expect("chunk") {
        fetched.extend_from_slice(&chunk.data);
    }
    assert!(fetched == bytes, "the dataset's bytes come back unchanged");

    // A release gives the frame back without counting; an expiry counts.
    workers
        .release_frame(pb::ReleaseFrameRequest {
            lease_id: second.lease_id.clone(),
        })
        .await
        .expect("release");
    tokio::time::sleep(lease_timeout * 5 / 2).await;
    assert!(
        jobs.list_leases(pb::ListLeasesRequest {})
            .await
            .expect("list leases")
            .into_inner()
            .leases
            .is_empty(),
        "the lease expired"
    );
    let late = complete(&mut workers, &first, png(32, 24))
        .await
        .expect_err("a completion under an expired lease");
    assert_eq!(late.code(), Code::FailedPrecondition, "{late:?}");
    assert_eq!(
        heartbeat(&mut workers, &first).await.action,
        pb::LeaseAction::Stop as i32
    );
    let shown = shown_job(&mut jobs, &job.id).await;
    assert_eq!(shown.frames_done, 0, "the late frame was not stored");

    let again = lease(&mut workers).await.expect("frame 0 again");
    assert_eq!((again.frame_index, again.failed_attempts), (0, 1));
    let other = lease(&mut workers).await.expect("frame 1 again");
    assert_eq!((other.frame_index, other.failed_attempts), (1, 0));
    let wrong_size = complete(&mut workers, &again, png(16, 16))
        .await
        .expect_err("a frame of the wrong size");
    assert_eq!(wrong_size.code(), Code::InvalidArgument);
    complete(&mut workers, &again, png(32, 24))
        .await
        .expect("complete frame 0");
    let twice = complete(&mut workers, &again, png(32, 24))
        .await
        .expect_err("a second completion");
    assert_eq!(twice.code(), Code::FailedPrecondition);

    // Cancel: the holder is told to stop, and its frame is refused.
    jobs.cancel_job(pb::CancelJobRequest { id: job.id.clone() })
        .await
        .expect("cancel");
    let stop = heartbeat(&mut workers, &other).await;
    assert_eq!(stop.action, pb::LeaseAction::Stop as i32);
    assert!(stop.reason.contains("cancelled"), "{}", stop.reason);
    let cancelled = complete(&mut workers, &other, png(32, 24))
        .await
        .expect_err("a frame of a cancelled job");
    assert_eq!(cancelled.code(), Code::FailedPrecondition);
    let shown = shown_job(&mut jobs, &job.id).await;
    assert_eq!(shown.frames_done, 1);
    assert_eq!(shown.frames.len(), 1);
    assert_eq!(shown.frames[0].failed_attempts, 1);

    // A frame whose workers keep dying fails its job after max_frame_attempts (2).
    let poison = jobs
        .submit_job(turntable_job("poison", &dataset.id, 1, 32, 24))
        .await
        .expect("submit")
        .into_inner();
    for attempt in 0..2 {
        let task = lease(&mut workers).await.expect("the poison frame");
        assert_eq!(
            (task.job_id.as_str(), task.failed_attempts),
            (poison.id.as_str(), attempt)
        );
        tokio::time::sleep(lease_timeout * 5 / 2).await;
    }
    let failed = shown_job(&mut jobs, &poison.id).await;
    assert_eq!(failed.state, pb::JobState::Failed as i32);
    assert!(failed.error.contains("failed 2 times"), "{}", failed.error);
    assert!(
        failed.error.contains("renewing its lease"),
        "{}",
        failed.error
    );
    assert!(lease(&mut workers).await.is_none());
    daemon.stop().await;
}

/// Waits until a worker holds a lease on a frame of `job_id`, and returns it.
async fn wait_for_lease(
    jobs: &mut JobServiceClient<Channel>,
    job_id: &str,
    log: impl Fn() -> String,
) -> pb::Lease {
    for _ in 0..6000 {
        let leases = list_leases(jobs).await;
        if let Some(lease) = leases.into_iter().find(|l| l.job_id == job_id) {
            return lease;
        }
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    panic!("no lease within 30 s\n{}", log());
}

/// SIGTERM while a frame is in flight: the worker finishes it, hands it in, and exits.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigterm_lets_a_worker_hand_in_its_frame_before_it_exits() {
    let DaemonWithScan {
        daemon,
        scratch,
        file: _,
        dataset,
    } = DaemonWithScan::start(|_| {}).await;
    let mut jobs = daemon.jobs().await;
    let mut lister = daemon.jobs().await;
    let job = submit(
        &mut jobs,
        turntable_job("sigterm", &dataset.id, 8, 160, 120),
    )
    .await;
    let mut worker = WorkerProcess::start(&daemon.url(), &scratch.path().join("cache"), "w");
    let held = wait_for_lease(&mut lister, &job.id, || worker.log()).await;
    // The worker has the lease in hand (not merely on its way) before the signal.
    for _ in 0..3000 {
        if worker.log().contains("frame leased") {
            break;
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    assert!(worker.log().contains("frame leased"), "{}", worker.log());
    let status = worker
        .terminate(Duration::from_secs(30))
        .expect("the worker stops after its frame");
    assert!(status.success(), "exit status {status}\n{}", worker.log());
    let shown = get_job(&mut jobs, &job.id).await;
    assert!(
        shown
            .frames
            .iter()
            .any(|f| f.index == held.frame_index && f.failed_attempts == 0),
        "the frame in flight was handed in: {:?}\n{}",
        shown.frames,
        worker.log()
    );
    assert!(
        list_leases(&mut lister).await.is_empty(),
        "no frame left leased"
    );
    assert!(
        shown.frames_done < 3,
        "the worker took no new frame after SIGTERM"
    );
    daemon.stop().await;
}

/// A daemon that restarts (here: `kill -9`) while a worker waits for work: the worker
/// reconnects by itself and renders the next job.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_worker_reconnects_after_the_daemon_restarts() {
    let data = tempfile::tempdir().expect("tempdir");
    let (scratch, file) = scratch_sample("s.laz", 20_000, 9);
    let mut server =
        pointfarm_tests::ServeProcess::start_with(data.path(), &["--no-embedded-worker"]);
    let address = server.address.clone();
    let worker = WorkerProcess::start(
        &format!("http://{address}"),
        &scratch.path().join("cache"),
        "steady",
    );
    // The worker is connected and long-polling (its GPU set-up may take a while on a busy
    // machine).
    pointfarm_tests::wait_for(Duration::from_secs(60), "worker start", || {
        worker.log().contains("worker started").then_some(())
    });
    tokio::time::sleep(Duration::from_millis(500)).await;
    server.kill();
    tokio::time::sleep(Duration::from_millis(500)).await;
    let _server = pointfarm_tests::ServeProcess::start_at(&address, data.path());
    let (mut datasets, mut jobs) = clients(&address).await;
    let dataset = upload(&mut datasets, "s.laz", &std::fs::read(&file).expect("read")).await;
    let job = submit(
        &mut jobs,
        turntable_job("after-restart", &dataset.id, 2, 64, 48),
    )
    .await;
    let (_, frames) = watch_to_success(&mut jobs, &job.id, || worker.log()).await;
    assert_eq!(frames.len(), 2);
    assert!(worker.log().contains("unreachable"), "{}", worker.log());
}

/// The daemon's stores over the wire: nodes are served only from a store that was opened,
/// requests for nodes are checked, and a client token does not open them.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_daemons_stores_are_opened_before_their_nodes_are_served() {
    let DaemonWithScan {
        daemon, dataset, ..
    } = DaemonWithScan::start(|_| {}).await;
    let mut workers = daemon.workers().await;
    let node = |level, x| pb::NodeKey {
        level,
        x,
        y: 0,
        z: 0,
    };
    let fetch = |nodes: Vec<pb::NodeKey>| pb::FetchNodesRequest {
        dataset_id: dataset.id.clone(),
        nodes,
        coarse: false,
    };
    let refused = workers
        .fetch_nodes(fetch(vec![node(0, 0)]))
        .await
        .expect_err("not opened");
    assert_eq!(refused.code(), Code::FailedPrecondition, "{refused:?}");
    let unknown = workers
        .open_dataset_store(pb::OpenDatasetStoreRequest {
            dataset_id: "ds-0000".into(),
            levels_of_detail: true,
        })
        .await
        .expect_err("no such dataset");
    assert_eq!(unknown.code(), Code::NotFound, "{unknown:?}");

    // Asked for levels of detail, the store is built, then served.
    let open = pb::OpenDatasetStoreRequest {
        dataset_id: dataset.id.clone(),
        levels_of_detail: true,
    };
    let started = std::time::Instant::now();
    let ready = loop {
        let answer = workers
            .open_dataset_store(open.clone())
            .await
            .expect("open")
            .into_inner();
        if answer.state == pb::open_dataset_store_response::State::Ready as i32 {
            break answer;
        }
        assert!(started.elapsed() < Duration::from_secs(120), "never built");
        tokio::time::sleep(Duration::from_millis(100)).await;
    };
    assert!(
        ready.point_count > 0 && ready.hierarchy_bytes > 0,
        "{ready:?}"
    );
    let mut root = workers
        .fetch_nodes(fetch(vec![node(0, 0)]))
        .await
        .expect("the root")
        .into_inner();
    let record = root.message().await.expect("stream").expect("a record");
    assert!(!record.data.is_empty());
    assert!(
        root.message().await.expect("stream").is_none(),
        "one node asked, one sent"
    );
    // Asked coarse, the record's coarse section: its first bytes, and fewer of them.
    let mut coarse = workers
        .fetch_nodes(pb::FetchNodesRequest {
            coarse: true,
            ..fetch(vec![node(0, 0)])
        })
        .await
        .expect("the root, coarse")
        .into_inner();
    let section = coarse.message().await.expect("stream").expect("a record");
    assert!(
        !section.data.is_empty() && section.data.len() < record.data.len(),
        "{} of {} bytes",
        section.data.len(),
        record.data.len()
    );
    assert!(record.data.starts_with(&section.data));

    for (nodes, field) in [
        (vec![node(25, 0)], "level"),
        (vec![node(1, 2)], "outside level 1"),
        (vec![node(0, 0); 257], "at most 256"),
    ] {
        let error = workers
            .fetch_nodes(fetch(nodes))
            .await
            .expect_err("a bad request");
        assert_eq!(error.code(), Code::InvalidArgument, "{error:?}");
        assert!(error.message().contains(field), "{}", error.message());
    }
    daemon.stop().await;
}

//! The bounds a daemon keeps against what clients send, over real gRPC on loopback: names and
//! ids bounded, error messages that do not echo unbounded input, uploads refused from their
//! header or first bytes without leaving anything behind, the upload quota, the in-use check
//! over every job, and a watcher too slow for the event buffer that still gets every frame.

use std::time::Duration;

use pointfarm_daemon::access::Access;
use pointfarm_proto::v1 as pb;
use pointfarm_tests::service::{
    scratch_sample, submit, turntable_job, upload, upload_messages, TestDaemon,
};
use tonic::Code;

fn refused<T>(result: Result<tonic::Response<T>, tonic::Status>) -> tonic::Status {
    match result {
        Ok(_) => panic!("the request was accepted"),
        Err(status) => status,
    }
}

/// A small LAS file's bytes.
fn sample_bytes(points: usize, seed: u64) -> Vec<u8> {
    let (_scratch, file) = scratch_sample("s.las", points, seed);
    std::fs::read(file).expect("read sample")
}

/// The files in the daemon's dataset folder (uploads and their `.part` files).
fn dataset_files(daemon: &TestDaemon) -> Vec<String> {
    let mut names: Vec<String> = std::fs::read_dir(daemon.data_dir.path().join("datasets"))
        .expect("datasets folder")
        .flatten()
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    names
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn long_names_and_ids_are_refused_and_never_echoed() {
    let daemon = TestDaemon::start_without_worker(|_| {}, Access::default()).await;
    let (mut datasets, mut jobs) = (daemon.datasets().await, daemon.jobs().await);
    let huge = "x".repeat(1 << 20);

    let status = refused(
        datasets
            .upload_dataset(tokio_stream::iter(upload_messages(
                &format!("{huge}.las"),
                b"LASF",
            )))
            .await,
    );
    assert_eq!(status.code(), Code::InvalidArgument);
    assert!(
        status.message().starts_with("header.name:"),
        "{}",
        status.message()
    );

    let dataset = upload(&mut datasets, "s.las", &sample_bytes(500, 1)).await;
    let status = refused(
        jobs.submit_job(turntable_job(&huge, &dataset.id, 1, 8, 8))
            .await,
    );
    assert_eq!(status.code(), Code::InvalidArgument);
    assert!(status.message().starts_with("request_id:"));

    // Lookups of ids of any length answer briefly, with a message that does not carry them.
    let status = refused(jobs.get_job(pb::GetJobRequest { id: huge.clone() }).await);
    assert_eq!(status.code(), Code::InvalidArgument);
    let status = refused(
        datasets
            .get_dataset(pb::GetDatasetRequest { id: huge.clone() })
            .await,
    );
    assert_eq!(status.code(), Code::InvalidArgument);
    assert!(status.message().len() < 200, "{}", status.message());

    let mut workers = daemon.workers().await;
    let request = pb::LeaseFrameRequest {
        worker_name: huge.clone(),
        wait_ms: 0,
        capabilities: None,
    };
    let status = refused(workers.lease_frame(request).await);
    assert_eq!(status.code(), Code::InvalidArgument);
    assert!(status.message().starts_with("worker_name:"));
    let status = refused(
        workers
            .heartbeat(pb::HeartbeatRequest { lease_id: huge })
            .await,
    );
    assert!(
        status.message().len() <= 2048,
        "{} bytes",
        status.message().len()
    );

    // Nothing of the refused requests was stored: listings answer as before.
    let listed = datasets
        .list_datasets(pb::ListDatasetsRequest::default())
        .await
        .expect("list datasets")
        .into_inner();
    assert_eq!(listed.datasets.len(), 1);
    let listed = jobs
        .list_jobs(pb::ListJobsRequest::default())
        .await
        .expect("list jobs")
        .into_inner();
    assert!(listed.jobs.is_empty());
    daemon.stop().await;
}

/// Sends `first` and then holds the upload stream open: an answer that arrives anyway was
/// given without the rest of the body.
async fn upload_held_open(
    daemon: &TestDaemon,
    first: Vec<pb::UploadDatasetRequest>,
) -> tonic::Status {
    let (sender, receiver) = tokio::sync::mpsc::channel(first.len().max(1));
    for message in first {
        sender.send(message).await.expect("queue message");
    }
    let mut datasets = daemon.datasets().await;
    let answer = tokio::time::timeout(
        Duration::from_secs(30),
        datasets.upload_dataset(tokio_stream::wrappers::ReceiverStream::new(receiver)),
    )
    .await
    .expect("the daemon answers before the upload's body ends");
    drop(sender);
    refused(answer)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn uploads_are_refused_from_their_header_or_first_bytes_and_leave_nothing() {
    let bytes = sample_bytes(2000, 2);
    let quota = 3 * bytes.len() as u64 / 2;
    let daemon = TestDaemon::start_without_worker(
        move |c| {
            c.max_upload_bytes = 1 << 20;
            c.upload_quota_bytes = Some(quota);
        },
        Access::default(),
    )
    .await;

    // The name, from the header alone.
    let header = upload_messages("notes.txt", &bytes).remove(0);
    let status = upload_held_open(&daemon, vec![header]).await;
    assert_eq!(status.code(), Code::InvalidArgument);
    assert!(
        status.message().contains(".las or .laz"),
        "{}",
        status.message()
    );

    // The declared size against --max-upload-bytes, from the header alone.
    let big = vec![0u8; (1 << 20) + 1];
    let header = upload_messages("big.las", &big).remove(0);
    let status = upload_held_open(&daemon, vec![header]).await;
    assert_eq!(
        status.code(),
        Code::ResourceExhausted,
        "{}",
        status.message()
    );

    // The LAS signature, from the first data message.
    let mut not_las = bytes.clone();
    not_las[..4].copy_from_slice(b"PK\x03\x04");
    let first_two = upload_messages("zipped.las", &not_las)
        .into_iter()
        .take(2)
        .collect();
    let status = upload_held_open(&daemon, first_two).await;
    assert_eq!(status.code(), Code::InvalidArgument);
    assert!(status.message().contains("LASF"), "{}", status.message());
    assert!(
        dataset_files(&daemon).is_empty(),
        "{:?}",
        dataset_files(&daemon)
    );

    // The quota: the first upload fits, a second one of other content does not.
    let mut datasets = daemon.datasets().await;
    let kept = upload(&mut datasets, "first.las", &bytes).await;
    let mut other = bytes.clone();
    let last = other.len() - 1;
    other[last] ^= 0xff;
    let status = refused(
        datasets
            .upload_dataset(tokio_stream::iter(upload_messages("second.las", &other)))
            .await,
    );
    assert_eq!(status.code(), Code::ResourceExhausted);
    assert!(status.message().contains("quota"), "{}", status.message());
    assert_eq!(dataset_files(&daemon), [format!("{}.las", kept.id)]);
    daemon.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_dataset_used_by_any_unfinished_job_cannot_be_deleted() {
    let daemon = TestDaemon::start_without_worker(|_| {}, Access::default()).await;
    let (mut datasets, mut jobs) = (daemon.datasets().await, daemon.jobs().await);
    let busy = upload(&mut datasets, "busy.las", &sample_bytes(500, 3)).await;
    let used = upload(&mut datasets, "used.las", &sample_bytes(500, 4)).await;
    // More queued jobs than one page of a listing holds come first.
    for i in 0..1100 {
        submit(
            &mut jobs,
            turntable_job(&format!("b{i}"), &busy.id, 1, 8, 8),
        )
        .await;
    }
    submit(&mut jobs, turntable_job("u", &used.id, 1, 8, 8)).await;
    let status = refused(
        datasets
            .delete_dataset(pb::DeleteDatasetRequest {
                id: used.id.clone(),
            })
            .await,
    );
    assert_eq!(
        status.code(),
        Code::FailedPrecondition,
        "{}",
        status.message()
    );
    daemon.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_watcher_that_pauses_still_receives_every_frame_once() {
    // A tiny event buffer, so that the paused watcher falls behind it.
    let daemon = TestDaemon::start(|c| c.event_buffer = 4, Access::default()).await;
    let (mut datasets, mut jobs) = (daemon.datasets().await, daemon.jobs().await);
    let dataset = upload(&mut datasets, "s.las", &sample_bytes(300, 5)).await;
    let frames = 600;
    let job = submit(&mut jobs, turntable_job("w", &dataset.id, frames, 8, 8)).await;
    // The watcher's connection takes in little before it reads, so that the daemon cannot
    // send ahead of it into buffers.
    let narrow = tonic::transport::Endpoint::from_shared(daemon.url())
        .expect("url")
        .initial_stream_window_size(Some(4096))
        .initial_connection_window_size(Some(4096))
        .connect()
        .await
        .expect("connect");
    let mut stream = pb::job_service_client::JobServiceClient::new(narrow)
        .watch_job(pb::WatchJobRequest { id: job.id.clone() })
        .await
        .expect("watch")
        .into_inner();
    // The watcher reads nothing until the job has ended.
    let deadline = tokio::time::Instant::now() + Duration::from_secs(300);
    loop {
        let state = jobs
            .get_job(pb::GetJobRequest { id: job.id.clone() })
            .await
            .expect("get")
            .into_inner()
            .state;
        if state == pb::JobState::Succeeded as i32 {
            break;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "the job did not end"
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    let mut seen = Vec::new();
    let mut last_state = None;
    while let Some(event) = stream.message().await.expect("event") {
        if let Some(job) = &event.job {
            seen.extend(job.frames.iter().map(|f| f.index));
            last_state = Some(job.state);
        }
        seen.extend(event.frame.iter().map(|f| f.index));
    }
    seen.sort_unstable();
    assert_eq!(seen, (0..frames).collect::<Vec<_>>(), "every frame once");
    assert_eq!(last_state, Some(pb::JobState::Succeeded as i32));
    daemon.stop().await;
}

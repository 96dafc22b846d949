//! The render service end to end: real gRPC over loopback sockets, a real sled state on disk,
//! the embedded worker rendering on lavapipe.

use std::time::Duration;

use pointfarm_daemon::access::Access;
use pointfarm_proto::v1 as pb;
use pointfarm_tests::datasets::register_path;
use pointfarm_tests::service::{
    assert_equal_to_direct_renders, clients, fetch_images, get_job, scan, scratch_sample, submit,
    turntable_job, upload, upload_messages, watch_to_end, watch_to_success, write_sample,
    TestDaemon,
};
use pointfarm_tests::ServeProcess;
use tonic::Code;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_turntable_job_renders_the_same_frames_as_the_renderer() {
    let daemon = TestDaemon::start(|_| {}, Access::default()).await;
    let scratch = tempfile::tempdir().expect("tempdir");
    let file = scan(scratch.path());
    let bytes = std::fs::read(&file).expect("read scan");
    let mut datasets = daemon.datasets().await;
    let dataset = upload(&mut datasets, "scan.laz", &bytes).await;
    // The same content gives the same id, and is not stored twice.
    assert_eq!(
        upload(&mut datasets, "again.laz", &bytes).await.id,
        dataset.id
    );

    let mut jobs = daemon.jobs().await;
    let request = turntable_job("turntable-1", &dataset.id, 3, 160, 120);
    let job = submit(&mut jobs, request.clone()).await;
    let again = submit(&mut jobs, request).await;
    assert_eq!(
        again.id, job.id,
        "a repeated request id returns the same job"
    );

    let (_, frames) = watch_to_success(&mut jobs, &job.id, String::new).await;
    assert_eq!(
        frames.iter().map(|f| f.index).collect::<Vec<_>>(),
        vec![0, 1, 2],
        "each frame reported once"
    );
    // A watcher that comes after the end learns of every frame from its first event.
    let (_, late_frames) = watch_to_success(&mut jobs, &job.id, String::new).await;
    let stages_of = |frames: &[pb::FrameFinished]| -> Vec<(u32, Vec<String>)> {
        frames
            .iter()
            .map(|f| (f.index, f.timings.iter().map(|t| t.stage.clone()).collect()))
            .collect()
    };
    assert_eq!(stages_of(&late_frames), stages_of(&frames));
    for frame in &frames {
        let stages: Vec<&str> = frame.timings.iter().map(|t| t.stage.as_str()).collect();
        assert!(
            stages.contains(&"rasterize") && stages.contains(&"encode"),
            "{stages:?}"
        );
    }

    // The frames equal what the renderer draws directly with the same cameras.
    let fetched = fetch_images(&mut jobs, &job.id, 0).await;
    assert_equal_to_direct_renders(&file, 3, (160, 120), &fetched);
    // Resuming a download from a frame index.
    assert_eq!(fetch_images(&mut jobs, &job.id, 2).await.len(), 1);

    let shown = get_job(&mut jobs, &job.id).await;
    assert_eq!(
        shown.frames.len(),
        3,
        "GetJob lists the finished frames with timings"
    );

    // The first job decoded the file; a second job that needs the points again (another
    // color mode) gets them from the worker's cache, without decoding.
    let load_ms = |frame: &pb::FrameFinished| {
        frame
            .timings
            .iter()
            .find(|t| t.stage == "load")
            .map(|t| t.ms)
    };
    let first_frame = frames
        .iter()
        .find(|f| f.dataset_cache_hit.is_some())
        .expect("a frame reports the load");
    assert_eq!(first_frame.dataset_cache_hit, Some(false));
    let mut second = turntable_job("turntable-2", &dataset.id, 1, 160, 120);
    second.render = Some(pb::RenderOptions {
        color_mode: pb::ColorMode::Elevation as i32,
        ..Default::default()
    });
    let second = submit(&mut jobs, second).await;
    let (_, second_frames) = watch_to_success(&mut jobs, &second.id, String::new).await;
    assert_eq!(
        second_frames[0].dataset_cache_hit,
        Some(true),
        "the second job hits the worker cache"
    );
    eprintln!(
        "{}: load {:.1} ms decoding, {:.1} ms from the worker cache",
        file.display(),
        load_ms(first_frame).unwrap_or(f64::NAN),
        load_ms(&second_frames[0]).unwrap_or(f64::NAN)
    );
    daemon.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn invalid_requests_get_their_status_codes() {
    let roots = tempfile::tempdir().expect("tempdir");
    std::fs::write(roots.path().join("inside.las"), b"LASF").expect("write");
    let root = roots.path().to_path_buf();
    let daemon = TestDaemon::start(
        move |c| {
            c.max_image_side = 1024;
            c.max_upload_bytes = 4096;
            c.data_roots = vec![root];
        },
        Access::default(),
    )
    .await;
    let mut jobs = daemon.jobs().await;
    let mut datasets = daemon.datasets().await;

    let code_and_message = |result: Result<tonic::Response<pb::Job>, tonic::Status>| match result {
        Ok(_) => panic!("the request was accepted"),
        Err(status) => (status.code(), status.message().to_string()),
    };

    // Unknown dataset.
    let (code, message) = code_and_message(
        jobs.submit_job(turntable_job("a", "ds-unknown", 2, 64, 64))
            .await,
    );
    assert_eq!(code, Code::NotFound, "{message}");

    // A real dataset for the rest.
    let file = roots.path().join("tiny.las");
    write_sample(&file, 2_000, 1);
    let registered = register_path(&mut datasets, "tiny.las").await;

    let (code, message) = code_and_message(
        jobs.submit_job(turntable_job("b", &registered.id, 0, 64, 64))
            .await,
    );
    assert_eq!(code, Code::InvalidArgument);
    assert!(
        message.contains("camera_path.turntable.frames"),
        "{message}"
    );

    let mut nan = turntable_job("c", &registered.id, 2, 64, 64);
    nan.camera_path = Some(pb::CameraPath::turntable(pb::Turntable {
        frames: 2,
        center: Some(pb::Vec3 {
            x: 1.0,
            y: f64::NAN,
            z: 0.0,
        }),
        ..Default::default()
    }));
    let (code, message) = code_and_message(jobs.submit_job(nan).await);
    assert_eq!(code, Code::InvalidArgument);
    assert!(
        message.contains("camera_path.turntable.center"),
        "{message}"
    );

    let (code, message) = code_and_message(
        jobs.submit_job(turntable_job("d", &registered.id, 2, 100_000, 100_000))
            .await,
    );
    assert_eq!(code, Code::InvalidArgument);
    assert!(
        message.contains("width") && message.contains("1024"),
        "{message}"
    );

    // Finished jobs cannot be cancelled, and the answer says why.
    let job = submit(&mut jobs, turntable_job("e", &registered.id, 1, 32, 32)).await;
    watch_to_success(&mut jobs, &job.id, String::new).await;
    let (code, message) = code_and_message(
        jobs.cancel_job(pb::CancelJobRequest { id: job.id.clone() })
            .await,
    );
    assert_eq!(code, Code::FailedPrecondition);
    assert_eq!(
        message,
        format!("job {} already succeeded; nothing to cancel", job.id)
    );

    // Uploads over the size limit.
    let big = vec![7u8; 10_000];
    let status = datasets
        .upload_dataset(tokio_stream::iter(upload_messages("big.las", &big)))
        .await
        .expect_err("too big");
    assert_eq!(
        status.code(),
        Code::ResourceExhausted,
        "{}",
        status.message()
    );

    // Paths outside the data roots, and traversal out of them.
    for path in ["/etc/passwd", "../../../../etc/passwd"] {
        let status = datasets
            .register_dataset(pb::RegisterDatasetRequest {
                path: path.into(),
                ..Default::default()
            })
            .await
            .expect_err("outside the roots");
        assert_eq!(
            status.code(),
            Code::InvalidArgument,
            "{path}: {}",
            status.message()
        );
    }
    daemon.stop().await;

    // A server with a token refuses calls without it.
    let guarded = TestDaemon::start(|_| {}, Access::new(Some("s3cret"), None)).await;
    let status = guarded
        .jobs()
        .await
        .get_job(pb::GetJobRequest { id: "x".into() })
        .await
        .expect_err("no token");
    assert_eq!(status.code(), Code::Unauthenticated);
    let mut request = tonic::Request::new(pb::GetJobRequest { id: "x".into() });
    request
        .metadata_mut()
        .insert("authorization", "Bearer s3cret".parse().expect("header"));
    let status = guarded
        .jobs()
        .await
        .get_job(request)
        .await
        .expect_err("no such job");
    assert_eq!(status.code(), Code::NotFound, "the token is accepted");
    guarded.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_corrupt_dataset_fails_its_job_while_another_completes() {
    let daemon = TestDaemon::start(|_| {}, Access::default()).await;
    let (_scratch, good_file) = scratch_sample("good.las", 5_000, 2);
    let good_bytes = std::fs::read(&good_file).expect("read");
    // The same file cut short: its header promises more points than it holds.
    let corrupt_bytes = good_bytes[..good_bytes.len() / 2].to_vec();

    let mut datasets = daemon.datasets().await;
    let corrupt = upload(&mut datasets, "corrupt.las", &corrupt_bytes).await;
    let good = upload(&mut datasets, "good.las", &good_bytes).await;
    let mut jobs = daemon.jobs().await;
    let bad_job = submit(&mut jobs, turntable_job("bad", &corrupt.id, 2, 64, 48)).await;
    let good_job = submit(&mut jobs, turntable_job("good", &good.id, 2, 64, 48)).await;

    // An ingest error fails the job at once, on its first attempt, with the error's text.
    let (bad_end, _) = watch_to_end(&mut jobs, &bad_job.id).await;
    assert_eq!(bad_end.state, pb::JobState::Failed as i32);
    let expected = format!(
        "frame 0 cannot be rendered (attempt 1, not retried): dataset {}: ",
        corrupt.id
    );
    assert!(
        bad_end.error.starts_with(&expected) && bad_end.error.contains("truncated"),
        "reason: {}",
        bad_end.error
    );
    let (good_end, frames) = watch_to_success(&mut jobs, &good_job.id, String::new).await;
    assert_eq!(
        frames.len() as u32 + good_end.frames_done - frames.len() as u32,
        2
    );

    // Health checking answers for the services.
    let mut health = tonic_health::pb::health_client::HealthClient::new(daemon.channel().await);
    let serving = health
        .check(tonic_health::pb::HealthCheckRequest {
            service: "pointfarm.v1.JobService".into(),
        })
        .await
        .expect("health")
        .into_inner();
    assert_eq!(
        serving.status,
        tonic_health::pb::health_check_response::ServingStatus::Serving as i32
    );
    daemon.stop().await;
}

/// `kill -9` in the middle of a job: after a restart the job completes and the frames that
/// were finished before are not rendered again.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_killed_daemon_resumes_its_jobs_without_rerendering_finished_frames() {
    let data = tempfile::tempdir().expect("tempdir");
    let (_scratch, file) = scratch_sample("sample.laz", 100_000, 4);
    let mut server = ServeProcess::start(data.path());
    let address = server.address.clone();
    let (mut datasets, mut jobs) = clients(&address).await;
    let dataset = upload(
        &mut datasets,
        "sample.laz",
        &std::fs::read(&file).expect("read"),
    )
    .await;
    // Slow frames (large, high quality, shaded) so the kill lands mid-job.
    let mut request = turntable_job("resume", &dataset.id, 24, 1024, 768);
    request.render = Some(pb::RenderOptions {
        quality: pb::Quality::High as i32,
        shading: pb::Shading::Edl as i32,
        point_size: 2,
        ..Default::default()
    });
    let job = submit(&mut jobs, request).await;

    let frames_dir = data.path().join("jobs").join(&job.id);
    let mut before = Vec::new();
    for _ in 0..600 {
        let current = get_job(&mut jobs, &job.id).await;
        if current.frames_done >= 3 {
            before = current.frames.iter().map(|f| f.index).collect();
            break;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    assert!(before.len() >= 3, "frames were rendered before the kill");
    server.kill();
    let modified: Vec<(u32, std::time::SystemTime)> = before
        .iter()
        .map(|&i| {
            let path = frames_dir.join(format!("frame_{i:05}.png"));
            (
                i,
                std::fs::metadata(&path)
                    .and_then(|m| m.modified())
                    .expect("finished frame on disk"),
            )
        })
        .collect();

    let _server = ServeProcess::start_at(&address, data.path());
    let (_, mut jobs) = clients(&address).await;
    let (finished, _) = watch_to_success(&mut jobs, &job.id, String::new).await;
    assert_eq!(finished.frames_done, 24);
    for (index, time) in modified {
        let path = frames_dir.join(format!("frame_{index:05}.png"));
        let now = std::fs::metadata(&path)
            .and_then(|m| m.modified())
            .expect("frame");
        assert_eq!(
            now, time,
            "frame {index} was rendered again after the restart"
        );
    }
    assert_eq!(
        std::fs::read_dir(&frames_dir)
            .expect("frames")
            .filter(|e| e
                .as_ref()
                .is_ok_and(|e| e.path().extension().is_some_and(|x| x == "png")))
            .count(),
        24
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn higher_priority_jobs_run_first() {
    let daemon = TestDaemon::start(|_| {}, Access::default()).await;
    let (_scratch, file) = scratch_sample("s.laz", 50_000, 5);
    let mut datasets = daemon.datasets().await;
    let dataset = upload(&mut datasets, "s.laz", &std::fs::read(&file).expect("read")).await;
    let mut jobs = daemon.jobs().await;
    let mut low = turntable_job("low", &dataset.id, 20, 640, 480);
    low.render = Some(pb::RenderOptions {
        quality: pb::Quality::High as i32,
        ..Default::default()
    });
    let low = submit(&mut jobs, low).await;
    let mut high = turntable_job("high", &dataset.id, 1, 64, 48);
    high.priority = 10;
    let high = submit(&mut jobs, high).await;
    watch_to_success(&mut jobs, &high.id, String::new).await;
    let low_now = get_job(&mut jobs, &low.id).await;
    assert!(
        low_now.frames_done < 20,
        "the high-priority job waited for the whole low-priority job"
    );
    // Cancelling stops the rest promptly.
    jobs.cancel_job(pb::CancelJobRequest { id: low.id.clone() })
        .await
        .expect("cancel");
    tokio::time::sleep(Duration::from_millis(500)).await;
    let cancelled = get_job(&mut jobs, &low.id).await;
    assert_eq!(cancelled.state, pb::JobState::Cancelled as i32);
    assert!(cancelled.frames_done < 20);
    daemon.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigterm_shuts_the_daemon_down_cleanly() {
    let data = tempfile::tempdir().expect("tempdir");
    let mut server = ServeProcess::start(data.path());
    let killed = std::process::Command::new("kill")
        .args(["-TERM", &server.pid().to_string()])
        .status()
        .expect("kill -TERM");
    assert!(killed.success());
    let status = server
        .wait_for_exit(Duration::from_secs(10))
        .expect("the daemon stops within 10 s of SIGTERM");
    assert!(status.success(), "exit status {status}");
}

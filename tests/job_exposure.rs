//! One exposure per job through the service: a `pointfarm worker` process whose first lease of
//! a job is not frame 0 measures the job's gain on frame 0, so the frames it hands in are a
//! local turntable's pixel for pixel.

use std::time::Duration;

use image::RgbaImage;
use pointfarm_daemon::access::Access;
use pointfarm_proto::v1 as pb;
use pointfarm_render::raster::Renderer;
use pointfarm_render::request::{CameraPath, Lens, RenderOptions, RenderRequest, Turntable};
use pointfarm_render::source::{quiet, FrameSource};
use pointfarm_tests::service::{
    fetch_images, get_job, gpu, lease_at_once, submit, turntable_job, upload_file,
    watch_to_success, TestDaemon,
};
use pointfarm_tests::{shared_data, WorkerProcess};

const FRAMES: u32 = 4;
const SIZE: (u32, u32) = (160, 120);

/// The turntable `turntable_job` submits, as a local render draws it.
fn turntable() -> RenderRequest {
    RenderRequest {
        width: SIZE.0,
        height: SIZE.1,
        camera_path: CameraPath::Turntable(Turntable::around_the_cloud(FRAMES)),
        lens: Lens::default(),
        render: RenderOptions::default(),
    }
}

/// The frames of `request` from `file`, resident: in order as `pointfarm render` draws them
/// when `alone` is false, else each as the first frame of a source of its own (measuring its
/// own gain).
fn render_here(file: &std::path::Path, request: &RenderRequest, alone: bool) -> Vec<RgbaImage> {
    let files = [file.to_path_buf()];
    let open = |renderer| {
        FrameSource::resident(renderer, &files, None, &request.render, &quiet).expect("resident")
    };
    let mut source = open(Renderer::new(gpu()));
    let mut images = Vec::new();
    for index in 0..request.frames() {
        if alone {
            source = open(source.into_renderer());
        }
        let settings = source.frame_settings(request, index);
        images.push(
            source
                .render(&settings, &quiet)
                .expect("render")
                .frame
                .image,
        );
    }
    images
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_worker_starting_a_job_past_frame_0_exposes_it_as_a_local_turntable() {
    // A real scan: its turntable's views measure gains apart, which a generated scene's
    // need not.
    let Some(file) = shared_data("autzen_trim.laz") else {
        return;
    };
    // Built before frame 0 is leased, which a slow build would let expire.
    pointfarm_tests::pointfarm_bin();
    let daemon = TestDaemon::start_without_worker(|_| {}, Access::default()).await;
    let scratch = tempfile::tempdir().expect("tempdir");
    let dataset = upload_file(&mut daemon.datasets().await, "scan.laz", &file).await;
    let mut jobs = daemon.jobs().await;
    let job = submit(
        &mut jobs,
        turntable_job("exposure", &dataset.id, FRAMES, SIZE.0, SIZE.1),
    )
    .await;

    // Frame 0 is held here, so the worker's first lease of the job is frame 1.
    let mut workers = daemon.workers().await;
    let held = workers
        .lease_frame(lease_at_once("holder"))
        .await
        .expect("lease")
        .into_inner()
        .task
        .expect("a frame to lease");
    assert_eq!(held.frame_index, 0);
    let worker = WorkerProcess::start(&daemon.url(), &scratch.path().join("cache"), "w1");
    let mut done = 0;
    for _ in 0..2400 {
        done = get_job(&mut jobs, &job.id).await.frames_done;
        if done == FRAMES - 1 {
            break;
        }
        let beat = workers
            .heartbeat(pb::HeartbeatRequest {
                lease_id: held.lease_id.clone(),
            })
            .await
            .expect("heartbeat")
            .into_inner();
        assert_eq!(beat.action, pb::LeaseAction::Continue as i32);
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    assert_eq!(
        done,
        FRAMES - 1,
        "frames 1 to {} within 2 minutes\n{}",
        FRAMES - 1,
        worker.log()
    );
    // Frame 0 goes back to the queue, to the worker that has rendered the others.
    workers
        .release_frame(pb::ReleaseFrameRequest {
            lease_id: held.lease_id.clone(),
        })
        .await
        .expect("release frame 0");
    watch_to_success(&mut jobs, &job.id, || worker.log()).await;
    let fetched = fetch_images(&mut jobs, &job.id, 0).await;
    assert_eq!(fetched.len(), FRAMES as usize);

    let request = turntable();
    let here = render_here(&file, &request, false);
    for ((index, there), here) in fetched.iter().zip(&here) {
        assert!(
            there == here,
            "frame {index} from the worker differs from the local turntable's"
        );
    }
    // Each frame exposed with its own gain is another picture: the check above bites.
    let own = render_here(&file, &request, true);
    assert!(own[0] == here[0], "frame 0 is measured alike");
    assert!(
        own.iter().zip(&here).skip(1).any(|(own, held)| own != held),
        "every frame measures frame 0's gain: the test shows nothing"
    );
    daemon.stop().await;
}

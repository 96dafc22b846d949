//! Previews through the service: a job with `preview` on a dataset of LAZ tiles whose store
//! the daemon is still building (its build held at a gate) renders every frame at once from
//! the daemon's chunk-start sample, reported as previews with their completeness and drawn
//! as a local `render --preview` draws them; as the build stores the points (its end held at
//! a second gate) the frames are drawn again with the nodes stored so far, more complete;
//! once the store is ready the same job renders the frames again as final frames, equal to
//! a job without previews. A real daemon killed (`kill -9`) while the store builds keeps its
//! previews, draws them again only as the new build stores more, and finishes the job.

use std::path::{Path, PathBuf};
use std::time::Duration;

use pointfarm_daemon::access::Access;
use pointfarm_daemon::stores::StoreBuildGate;
use pointfarm_proto::v1 as pb;
use pointfarm_render::raster::Renderer;
use pointfarm_render::request::{CameraPath, Lens, RenderOptions, RenderRequest, Turntable};
use pointfarm_render::source::{quiet, ChunkStarts, FrameSource};
use pointfarm_render::testing::write_scene_tiles;
use pointfarm_tests::datasets::register_path;
use pointfarm_tests::service::{
    clients, fetch_images, get_job, gpu, lod_turntable_job, submit, watch, TestDaemon,
};
use pointfarm_tests::ServeProcess;
use tonic::transport::Channel;

const FRAMES: u32 = 3;
const SIZE: (u32, u32) = (160, 120);

/// Three LAZ tiles of three 50,000-point chunks each (a generated scene per seed).
fn tiles(dir: &Path) -> Vec<PathBuf> {
    write_scene_tiles(dir, 120_000, 3)
}

/// A turntable from levels of detail (the dataset needs a store), with or without previews.
fn job(name: &str, dataset_id: &str, preview: bool) -> pb::SubmitJobRequest {
    pb::SubmitJobRequest {
        preview,
        ..lod_turntable_job(name, dataset_id, FRAMES, SIZE, 0.5)
    }
}

/// What `render --preview` draws of `files`, through the frame source it draws with: their
/// chunk starts colored, resident, framed by the files' header bounds.
fn local_previews(files: &[PathBuf]) -> Vec<image::RgbaImage> {
    let chunk_starts = ChunkStarts::read(files).expect("chunk starts");
    let request = RenderRequest {
        width: SIZE.0,
        height: SIZE.1,
        camera_path: CameraPath::Turntable(Turntable::around_the_cloud(FRAMES)),
        lens: Lens::default(),
        render: RenderOptions {
            lod_error: Some(0.5),
            ..RenderOptions::default()
        },
    };
    let mut source = FrameSource::preview(
        Renderer::new(gpu()),
        chunk_starts.with_nodes(&[]),
        &request.render,
        &quiet,
    )
    .expect("a preview");
    (0..FRAMES)
        .map(|index| {
            let settings = source.frame_settings(&request, index);
            let rendered = source.render(&settings, &quiet).expect("render");
            assert!(rendered.preview.is_some(), "a preview's frame");
            rendered.frame.image
        })
        .collect()
}

/// Whether every frame has a preview among `frames` that `counts`.
fn every_frame_previewed(
    frames: &[pb::FrameFinished],
    counts: impl Fn(&pb::FrameFinished) -> bool,
) -> bool {
    (0..FRAMES).all(|index| {
        frames
            .iter()
            .any(|f| f.index == index && f.preview && counts(f))
    })
}

/// Events of job `id` until `enough` says the frames seen are enough; returns those frames.
async fn watch_until(
    jobs: &mut pointfarm_proto::v1::job_service_client::JobServiceClient<Channel>,
    id: &str,
    enough: impl Fn(&[pb::FrameFinished]) -> bool,
) -> Vec<pb::FrameFinished> {
    let mut stream = watch(jobs, id).await;
    let mut frames = Vec::new();
    let deadline = tokio::time::Instant::now() + Duration::from_secs(300);
    while !enough(&frames) {
        let event = tokio::time::timeout_at(deadline, stream.message())
            .await
            .expect("frames within 5 minutes")
            .expect("an event")
            .expect("the watch goes on");
        if let Some(job) = &event.job {
            frames.extend(job.frames.iter().cloned());
            assert_ne!(job.state, pb::JobState::Failed as i32, "{}", job.error);
        }
        frames.extend(event.frame);
    }
    frames
}

#[tokio::test(flavor = "multi_thread")]
async fn a_preview_job_renders_chunk_starts_while_the_store_builds_then_final_frames() {
    let scratch = tempfile::tempdir().expect("tempdir");
    let files = tiles(scratch.path());
    let gate = StoreBuildGate::closed();
    let ready = StoreBuildGate::closed();
    let roots = scratch.path().to_path_buf();
    let (held, held_ready) = (gate.clone(), ready.clone());
    let daemon = TestDaemon::start(
        move |config| {
            config.data_roots = vec![roots];
            config.store_build_gate = Some(held);
            config.store_ready_gate = Some(held_ready);
        },
        Access::default(),
    )
    .await;
    let root = scratch.path().display().to_string();
    let dataset = register_path(&mut daemon.datasets().await, &root).await;
    assert_eq!(dataset.files.len(), 3);
    let mut jobs = daemon.jobs().await;
    let previewed = submit(&mut jobs, job("previewed", &dataset.id, true)).await;

    // The build waits at the gate: every frame comes as a preview.
    let previews = watch_until(&mut jobs, &previewed.id, |frames| {
        every_frame_previewed(frames, |_| true)
    })
    .await;
    for frame in &previews {
        assert!(frame.preview, "{frame:?}");
        // Nine chunk starts at most of 360,000 points.
        assert!(
            frame.completeness > 0.0 && frame.completeness <= 9.0 / 360_000.0,
            "{frame:?}"
        );
        assert!(frame.cut.is_none(), "{frame:?}");
    }
    let shown = get_job(&mut jobs, &previewed.id).await;
    assert_eq!(shown.state, pb::JobState::Running as i32, "{shown:?}");
    assert_eq!(shown.frames_done, 0, "previews are not final: {shown:?}");
    assert_eq!(shown.frames.len(), FRAMES as usize);
    assert!(shown.frames.iter().all(|f| f.preview), "{shown:?}");
    // The latest images are the previews, as `render --preview` draws them here.
    let fetched = fetch_images(&mut jobs, &previewed.id, 0).await;
    assert_eq!(fetched.len(), FRAMES as usize);
    for ((index, image), local) in fetched.iter().zip(local_previews(&files)) {
        assert!(
            *image == local,
            "preview {index} differs from the local preview"
        );
    }

    // A job without previews on the same dataset waits for the store meanwhile.
    let normal = submit(&mut jobs, job("normal", &dataset.id, false)).await;
    tokio::time::sleep(Duration::from_secs(2)).await;
    let waiting = get_job(&mut jobs, &normal.id).await;
    assert!(waiting.frames.is_empty(), "{waiting:?}");

    // The build stores every node and waits at its end, still building: each frame is drawn
    // again from the chunk starts and the nodes stored so far, more complete.
    gate.open();
    let chunk_starts_share = 9.0 / 360_000.0;
    let redrawn = watch_until(&mut jobs, &previewed.id, |frames| {
        every_frame_previewed(frames, |f| f.completeness > chunk_starts_share)
    })
    .await;
    for frame in redrawn
        .iter()
        .filter(|f| f.completeness > chunk_starts_share)
    {
        assert!(frame.preview && frame.cut.is_none(), "{frame:?}");
        assert!(frame.completeness <= 1.0, "{frame:?}");
    }
    let shown = get_job(&mut jobs, &previewed.id).await;
    assert_eq!(shown.frames_done, 0, "redraws are not final: {shown:?}");
    let waiting = get_job(&mut jobs, &normal.id).await;
    assert!(waiting.frames.is_empty(), "{waiting:?}");

    ready.open();
    let (finished, frames) =
        pointfarm_tests::service::watch_to_success(&mut jobs, &previewed.id, String::new).await;
    assert_eq!(finished.frames_done, FRAMES);
    let finals: Vec<_> = frames.iter().filter(|f| !f.preview).collect();
    assert_eq!(finals.len(), FRAMES as usize, "{frames:?}");
    for frame in &finals {
        assert_eq!(frame.completeness, 0.0);
        assert!(frame.cut.is_some(), "{frame:?}");
    }
    let shown = get_job(&mut jobs, &previewed.id).await;
    assert!(shown.frames.iter().all(|f| !f.preview), "{shown:?}");

    // The normal job: no previews, and its frames are the previewed job's final ones.
    let (_, normal_frames) =
        pointfarm_tests::service::watch_to_success(&mut jobs, &normal.id, String::new).await;
    assert!(normal_frames
        .iter()
        .all(|f| !f.preview && f.completeness == 0.0));
    let final_images = fetch_images(&mut jobs, &previewed.id, 0).await;
    let normal_images = fetch_images(&mut jobs, &normal.id, 0).await;
    assert_eq!(final_images.len(), FRAMES as usize);
    for ((index, final_image), (_, normal)) in final_images.iter().zip(&normal_images) {
        assert!(
            final_image == normal,
            "final frame {index} differs from the job's without previews"
        );
    }
    for ((index, image), local) in final_images.iter().zip(local_previews(&files)) {
        assert!(*image != local, "frame {index} is still the preview");
    }
    daemon.stop().await;
}

/// `kill -9` of a real daemon while a preview job's store builds: after the restart the
/// previews are still the job's frames, none is previewed again while the store builds anew,
/// and the job ends with every frame final.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_killed_daemon_keeps_its_previews_and_finishes_the_job() {
    let scratch = tempfile::tempdir().expect("tempdir");
    // Eight tiles of 1M points: a build that outlasts three small previews by seconds.
    write_scene_tiles(scratch.path(), 1_000_000, 8);
    let root = scratch.path().display().to_string();
    let data = tempfile::tempdir().expect("data");
    let mut server = ServeProcess::start_with(data.path(), &["--data-root", &root]);
    let address = server.address.clone();
    let (mut datasets, mut jobs) = clients(&address).await;
    let dataset = register_path(&mut datasets, &root).await;
    let job = submit(&mut jobs, job("killed", &dataset.id, true)).await;
    watch_until(&mut jobs, &job.id, |frames| {
        every_frame_previewed(frames, |_| true)
    })
    .await;
    let before = get_job(&mut jobs, &job.id).await;
    assert_eq!(
        before.frames_done, 0,
        "the store was built too soon: {before:?}"
    );
    server.kill();

    let server = ServeProcess::start_with_args(&address, data.path(), &["--data-root", &root]);
    let (_, mut jobs) = clients(&address).await;
    let after = get_job(&mut jobs, &job.id).await;
    assert_eq!(after.frames.len(), FRAMES as usize, "{after:?}");
    assert!(after.frames.iter().all(|f| f.preview), "{after:?}");

    let mut stream = watch(&mut jobs, &job.id).await;
    let mut rendered = Vec::new();
    let mut state = None;
    let deadline = tokio::time::Instant::now() + Duration::from_secs(300);
    while let Some(event) = tokio::time::timeout_at(deadline, stream.message())
        .await
        .expect("the job ends within 5 minutes")
        .expect("the watch goes on")
    {
        rendered.extend(event.frame);
        state = event.job.map(|j| (j.state, j.error)).or(state);
    }
    let (state, error) = state.expect("a job event");
    assert_eq!(
        state,
        pb::JobState::Succeeded as i32,
        "{error}\n{}",
        server.log()
    );
    // The new build counts its tenths from 0 again: a frame is drawn again only once it has
    // stored one, with stored nodes, never from the chunk starts alone (160 of 8M points).
    let chunk_starts_share = 160.0 / 8_000_000.0;
    assert!(
        rendered
            .iter()
            .all(|f| !f.preview || f.completeness > chunk_starts_share),
        "previewed again from the chunk starts: {rendered:?}"
    );
    let mut finals: Vec<u32> = rendered
        .iter()
        .filter(|f| !f.preview)
        .map(|f| f.index)
        .collect();
    finals.sort_unstable();
    assert_eq!(
        finals,
        (0..FRAMES).collect::<Vec<_>>(),
        "each frame final once"
    );
}

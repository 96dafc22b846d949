//! Videos made by the farm, through a real daemon and real worker processes: a job's video is
//! made once its last frame is final, by a worker whose ffmpeg has the encoder, never by one
//! without ffmpeg; `ffprobe` checks what is stored and fetched. A bad video spec is refused,
//! a worker killed while its ffmpeg runs has the video leased again, one stopped hands it
//! back for another at once, and `pointfarm render --server --video` and `jobs video`
//! download it. A preview job's previews make a preview video before its final video.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use pointfarm_daemon::access::Access;
use pointfarm_daemon::stores::StoreBuildGate;
use pointfarm_proto::v1 as pb;
use pointfarm_proto::v1::job_service_client::JobServiceClient;
use pointfarm_render::testing::write_scene_tiles;
use pointfarm_tests::datasets::register_path;
use pointfarm_tests::service::{
    get_job, lod_turntable_job, scratch_sample, submit, turntable_job, upload_sample, watch,
    watch_to_success, TestDaemon,
};
use pointfarm_tests::{pointfarm, pointfarm_bin, stdout, wait_for, WorkerProcess};
use tonic::transport::Channel;

/// A `pointfarm worker` with `path` as its whole PATH (to hide or fake ffmpeg); killed when
/// dropped.
struct PathWorker {
    child: Child,
    log: PathBuf,
}

impl PathWorker {
    fn start(server: &str, cache_dir: &Path, name: &str, path: &Path) -> Self {
        let log = cache_dir.with_extension("log");
        let log_file = std::fs::File::create(&log).expect("worker log");
        let child = Command::new(pointfarm_bin())
            .args(["-v", "worker", "--server", server, "--name", name])
            .arg("--cache-dir")
            .arg(cache_dir)
            .env("PATH", path)
            .stdout(Stdio::null())
            .stderr(log_file)
            .spawn()
            .expect("start pointfarm worker");
        Self { child, log }
    }

    fn log(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }

    fn kill(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }

    /// Stops the worker as an operator does (SIGTERM) and waits for it to exit.
    fn terminate(&mut self) -> std::process::ExitStatus {
        let sent = Command::new("kill")
            .args(["-TERM", &self.child.id().to_string()])
            .status()
            .expect("kill -TERM");
        assert!(sent.success());
        wait_for(Duration::from_secs(30), "the worker to exit", || {
            self.child.try_wait().expect("try_wait")
        })
    }
}

impl Drop for PathWorker {
    fn drop(&mut self) {
        self.kill();
    }
}

fn with_video(request: pb::SubmitJobRequest, container: &str, codec: &str) -> pb::SubmitJobRequest {
    pb::SubmitJobRequest {
        video: Some(pb::VideoSpec {
            container: container.into(),
            codec: codec.into(),
            fps: 12,
            quality: Some(30),
            ..Default::default()
        }),
        ..request
    }
}

/// `pointfarm` with `args`, run off the test's runtime, which serves the daemon meanwhile.
async fn pointfarm_off_runtime(args: Vec<String>) -> std::process::Output {
    tokio::task::spawn_blocking(move || {
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        pointfarm(&args)
    })
    .await
    .expect("pointfarm")
}

/// What ffprobe says of a video's first stream: codec, width, height and frames counted.
fn probe(video: &Path) -> (String, u32, u32, u32) {
    let output = Command::new("ffprobe")
        .args(["-v", "error", "-select_streams", "v:0", "-count_frames"])
        .args([
            "-show_entries",
            "stream=codec_name,width,height,nb_read_frames",
        ])
        .args(["-of", "csv=p=0"])
        .arg(video)
        .output()
        .expect("ffprobe");
    assert!(output.status.success(), "ffprobe: {output:?}");
    let line = String::from_utf8_lossy(&output.stdout).trim().to_owned();
    let fields: Vec<&str> = line.split(',').collect();
    let number = |i: usize| {
        fields[i]
            .parse::<u32>()
            .unwrap_or_else(|_| panic!("{line}"))
    };
    (fields[0].to_owned(), number(1), number(2), number(3))
}

/// FetchVideo of job `id`'s video, or of its preview video with `preview`: the stream of its
/// chunks, or the refusal.
async fn ask_for_video(
    jobs: &mut JobServiceClient<Channel>,
    id: &str,
    preview: bool,
) -> Result<tonic::Streaming<pb::VideoChunk>, tonic::Status> {
    let request = pb::FetchVideoRequest {
        job_id: id.into(),
        preview,
    };
    jobs.fetch_video(request)
        .await
        .map(tonic::Response::into_inner)
}

/// Reads a FetchVideo stream to its end into `path`: the first chunk, without its data.
async fn save_video(
    mut stream: tonic::Streaming<pb::VideoChunk>,
    path: &Path,
) -> Option<pb::VideoChunk> {
    let mut bytes = Vec::new();
    let mut first = None;
    while let Some(chunk) = stream.message().await.expect("chunk") {
        bytes.extend_from_slice(&chunk.data);
        first.get_or_insert(pb::VideoChunk {
            data: Vec::new(),
            ..chunk
        });
    }
    std::fs::write(path, &bytes).expect("write video");
    if let Some(first) = &first {
        assert_eq!(first.size_bytes, bytes.len() as u64);
    }
    first
}

/// Downloads job `id`'s video through FetchVideo into `path`.
async fn fetch_video(
    jobs: &mut JobServiceClient<Channel>,
    id: &str,
    path: &Path,
) -> pb::VideoChunk {
    let stream = ask_for_video(jobs, id, false).await.expect("fetch video");
    save_video(stream, path).await.expect("a chunk")
}

/// `pointfarm jobs video ID --out PATH --server URL`, with `--preview` where `preview`,
/// expected to succeed: its output.
async fn fetch_video_with_cli(
    daemon: &TestDaemon,
    id: &str,
    path: &Path,
    preview: bool,
) -> std::process::Output {
    let mut args = vec!["jobs".into(), "video".into(), id.to_owned()];
    if preview {
        args.push("--preview".into());
    }
    args.extend(["--out".into(), path.display().to_string()]);
    args.extend(["--server".into(), daemon.url()]);
    let fetched = pointfarm_off_runtime(args).await;
    assert!(fetched.status.success(), "{fetched:?}");
    fetched
}

/// Waits until job `id` has every frame final and is making its video.
async fn wait_for_video_stage(jobs: &mut JobServiceClient<Channel>, id: &str) -> pb::Job {
    let deadline = Instant::now() + Duration::from_secs(120);
    loop {
        let job = get_job(jobs, id).await;
        if job.stage == "video" {
            return job;
        }
        assert!(
            Instant::now() < deadline && job.state != pb::JobState::Failed as i32,
            "job {id} never reached its video: {job:?}"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_jobs_video_is_made_by_a_worker_with_ffmpeg_and_never_by_one_without() {
    let daemon = TestDaemon::start_without_worker(|_| {}, Access::default()).await;
    let dataset = upload_sample(&mut daemon.datasets().await, 20_000, 3).await;
    let mut jobs = daemon.jobs().await;
    let scratch = tempfile::tempdir().expect("tempdir");
    let empty_path = scratch.path().join("bin");
    std::fs::create_dir_all(&empty_path).expect("bin");
    let blind = PathWorker::start(
        &daemon.url(),
        &scratch.path().join("blind"),
        "blind",
        &empty_path,
    );
    let job = submit(
        &mut jobs,
        with_video(turntable_job("spin", &dataset.id, 6, 64, 48), "mp4", ""),
    )
    .await;
    assert_eq!(job.stage, "frames");
    let waiting = wait_for_video_stage(&mut jobs, &job.id).await;
    assert_eq!(waiting.state, pb::JobState::Running as i32);
    assert_eq!(waiting.frames_done, 6);
    // The worker without ffmpeg keeps asking for frames and is never handed the video.
    tokio::time::sleep(Duration::from_secs(2)).await;
    let still = get_job(&mut jobs, &job.id).await;
    assert_eq!((still.stage.as_str(), still.video_size_bytes), ("video", 0));
    // It says so in its capabilities, and the job says what it waits for.
    assert_eq!(
        still.waiting_reason,
        "waiting for a worker whose ffmpeg has libx264 to make the video"
    );
    assert_eq!(still.refusals.len(), 1, "{:?}", still.refusals);
    assert_eq!(still.refusals[0].worker_name, "blind");
    assert!(blind.log().contains("makes no videos"), "{}", blind.log());
    let refused = ask_for_video(&mut jobs, &job.id, false)
        .await
        .expect_err("no video yet");
    assert_eq!(refused.code(), tonic::Code::FailedPrecondition);

    let encoder = WorkerProcess::start(&daemon.url(), &scratch.path().join("encoder"), "encoder");
    let (done, _) = watch_to_success(&mut jobs, &job.id, || encoder.log()).await;
    assert_eq!(done.stage, "");
    assert!(done.video_size_bytes > 0);
    let fetched = scratch.path().join("spin.mp4");
    let first = fetch_video(&mut jobs, &job.id, &fetched).await;
    assert_eq!(first.container, "mp4");
    assert_eq!(probe(&fetched), ("h264".to_owned(), 64, 48, 6));
    // Stored with the frames, so it goes with the job's folder.
    let stored = daemon
        .data_dir
        .path()
        .join("jobs")
        .join(&job.id)
        .join("video.mp4");
    assert_eq!(
        std::fs::metadata(&stored).expect("stored").len(),
        done.video_size_bytes
    );
    daemon.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_bad_video_spec_is_refused_naming_its_field() {
    let daemon = TestDaemon::start_without_worker(|_| {}, Access::default()).await;
    let dataset = upload_sample(&mut daemon.datasets().await, 5_000, 4).await;
    let mut jobs = daemon.jobs().await;
    let base = || turntable_job("bad", &dataset.id, 4, 32, 24);
    let fps = |fps| pb::SubmitJobRequest {
        video: Some(pb::VideoSpec {
            container: "mp4".into(),
            fps,
            ..Default::default()
        }),
        ..base()
    };
    let quality = pb::SubmitJobRequest {
        video: Some(pb::VideoSpec {
            container: "mkv".into(),
            quality: Some(52),
            ..Default::default()
        }),
        ..base()
    };
    let preset = pb::SubmitJobRequest {
        video: Some(pb::VideoSpec {
            container: "mp4".into(),
            preset: "placebo".into(),
            ..Default::default()
        }),
        ..base()
    };
    let cases = [
        (preset, "video.preset"),
        (with_video(base(), "avi", ""), "video.container"),
        (with_video(base(), "webm", "h264"), "video.codec"),
        (with_video(base(), "gif", "vp9"), "video.codec"),
        (with_video(base(), "mp4", "mpeg2"), "video.codec"),
        (fps(241), "video.fps"),
        (quality, "video.quality"),
    ];
    for (request, field) in cases {
        let status = jobs.submit_job(request).await.expect_err(field);
        assert_eq!(status.code(), tonic::Code::InvalidArgument, "{status:?}");
        assert!(
            status.message().contains(field),
            "{field}: {}",
            status.message()
        );
    }
    daemon.stop().await;
}

/// An `ffmpeg` that says it has libx264 and, asked to encode, reads the frames and then waits
/// as long as its worker lives: an encode that is always mid-way.
fn stalling_ffmpeg(dir: &Path) {
    let script = "#!/bin/sh\n\
        case \"$*\" in\n\
          -version) echo 'ffmpeg version stalling'; exit 0;;\n\
          *-encoders*) echo ' V....D libx264  H.264'; exit 0;;\n\
        esac\n\
        cat >/dev/null\n\
        while kill -0 $PPID 2>/dev/null; do sleep 0.1; done\n";
    let path = dir.join("ffmpeg");
    std::fs::write(&path, script).expect("script");
    let made = Command::new("chmod")
        .arg("+x")
        .arg(&path)
        .status()
        .expect("chmod");
    assert!(made.success());
    for tool in ["cat", "sleep", "kill"] {
        let found = ["/usr/bin", "/bin"]
            .iter()
            .map(|d| Path::new(d).join(tool))
            .find(|p| p.exists())
            .expect(tool);
        let _ = std::os::unix::fs::symlink(found, dir.join(tool));
    }
}

/// A daemon leasing for `lease_timeout`, and a four-frame job `request_id` with a video that
/// a worker whose ffmpeg stalls has leased (its log says so).
struct StalledVideo {
    daemon: TestDaemon,
    jobs: JobServiceClient<Channel>,
    scratch: tempfile::TempDir,
    stalling: PathWorker,
    job: pb::Job,
}

async fn video_stalled_in_a_worker(lease_timeout: Duration, request_id: &str) -> StalledVideo {
    let daemon = TestDaemon::start_without_worker(
        |config| config.lease_timeout = lease_timeout,
        Access::default(),
    )
    .await;
    let dataset = upload_sample(&mut daemon.datasets().await, 5_000, 5).await;
    let mut jobs = daemon.jobs().await;
    let scratch = tempfile::tempdir().expect("tempdir");
    let bin = scratch.path().join("bin");
    std::fs::create_dir_all(&bin).expect("bin");
    stalling_ffmpeg(&bin);
    let stalling = PathWorker::start(&daemon.url(), &scratch.path().join("stall"), "stall", &bin);
    let job = submit(
        &mut jobs,
        with_video(turntable_job(request_id, &dataset.id, 4, 32, 24), "mp4", ""),
    )
    .await;
    let log = stalling.log.clone();
    tokio::task::spawn_blocking(move || {
        wait_for(Duration::from_secs(120), "the video leased", || {
            let said = std::fs::read_to_string(&log).unwrap_or_default();
            said.contains("video leased").then_some(())
        })
    })
    .await
    .expect("wait");
    StalledVideo {
        daemon,
        jobs,
        scratch,
        stalling,
        job,
    }
}

impl StalledVideo {
    /// Starts a worker whose ffmpeg works and waits for it to finish the job, checking that
    /// the job stored a video and that the worker leased it after `failed_attempts` failed
    /// attempts, as `why` explains.
    async fn made_by_another_worker(&mut self, failed_attempts: u32, why: &str) {
        let cache = self.scratch.path().join("encoder");
        let encoder = WorkerProcess::start(&self.daemon.url(), &cache, "encoder");
        let (done, _) = watch_to_success(&mut self.jobs, &self.job.id, || encoder.log()).await;
        assert!(done.video_size_bytes > 0);
        let log = encoder.log();
        let attempts = format!("failed_attempts={failed_attempts}");
        assert!(
            log.contains("video leased") && log.contains(&attempts),
            "{why}:\n{log}"
        );
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_worker_killed_while_making_the_video_has_it_leased_again() {
    let mut stalled = video_stalled_in_a_worker(Duration::from_secs(1), "again").await;
    stalled.stalling.kill();

    let why = "the second worker made the video at its second attempt";
    stalled.made_by_another_worker(1, why).await;
    let fetched = stalled.scratch.path().join("again.mp4");
    fetch_video(&mut stalled.jobs, &stalled.job.id, &fetched).await;
    assert_eq!(probe(&fetched), ("h264".to_owned(), 32, 24, 4));
    stalled.daemon.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_worker_stopped_while_making_the_video_hands_it_back_for_another_at_once() {
    // A lease timeout far longer than the test: only the hand-back lets another worker in.
    let mut stalled = video_stalled_in_a_worker(Duration::from_secs(600), "back").await;
    // Waiting for the exit blocks this thread alone: the daemon serves on the others.
    let status = tokio::task::block_in_place(|| stalled.stalling.terminate());
    let log = stalled.stalling.log();
    assert!(status.success(), "{status:?}:\n{log}");
    assert!(log.contains("the video is handed back unmade"), "{log}");
    let job = get_job(&mut stalled.jobs, &stalled.job.id).await;
    assert_eq!(job.stage, "video");

    let why = "handing back counted no attempt";
    stalled.made_by_another_worker(0, why).await;
    stalled.daemon.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn render_server_video_downloads_the_farms_video_and_jobs_video_fetches_it_again() {
    let daemon = TestDaemon::start(|_| {}, Access::default()).await;
    let (scan_dir, scan) = scratch_sample("scan.laz", 5_000, 6);
    let out = scan_dir.path().join("frames");
    let video = scan_dir.path().join("spin.webm");
    let rendered = pointfarm_off_runtime(vec![
        "render".into(),
        scan.display().to_string(),
        "--server".into(),
        daemon.url(),
        "--turntable".into(),
        "5".into(),
        "--size".into(),
        "48x32".into(),
        "--out".into(),
        out.display().to_string(),
        "--video".into(),
        video.display().to_string(),
        "--fps".into(),
        "10".into(),
    ])
    .await;
    let said = stdout(&rendered);
    assert!(rendered.status.success(), "{rendered:?}");
    assert!(said.contains("made on the server"), "{said}");
    assert_eq!(probe(&video), ("vp9".to_owned(), 48, 32, 5));

    let mut jobs = daemon.jobs().await;
    let listed = jobs
        .list_jobs(pb::ListJobsRequest::default())
        .await
        .expect("list")
        .into_inner();
    let job = listed.jobs.first().expect("the render's job");
    let again = scan_dir.path().join("again.webm");
    fetch_video_with_cli(&daemon, &job.id, &again, false).await;
    assert_eq!(
        std::fs::read(&again).expect("again"),
        std::fs::read(&video).expect("video")
    );
    daemon.stop().await;
}

/// Downloads job `id`'s preview video through FetchVideo once it is stored, into `path`.
async fn fetch_preview_video_when_stored(
    jobs: &mut JobServiceClient<Channel>,
    id: &str,
    path: &Path,
) {
    let deadline = Instant::now() + Duration::from_secs(240);
    loop {
        let status = match ask_for_video(jobs, id, true).await {
            Ok(stream) => {
                save_video(stream, path).await;
                return;
            }
            Err(status) => status,
        };
        assert_eq!(status.code(), tonic::Code::FailedPrecondition, "{status:?}");
        assert!(
            Instant::now() < deadline,
            "job {id} never had its preview video: {status:?}"
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_preview_jobs_previews_make_a_preview_video_and_its_final_video_still_comes() {
    let scratch = tempfile::tempdir().expect("tempdir");
    write_scene_tiles(scratch.path(), 120_000, 3);
    // The store's build is held before it is ready: the frames are previews only meanwhile.
    let ready = StoreBuildGate::closed();
    let (roots, held_ready) = (scratch.path().to_path_buf(), ready.clone());
    let daemon = TestDaemon::start(
        move |config| {
            config.data_roots = vec![roots];
            config.store_ready_gate = Some(held_ready);
        },
        Access::default(),
    )
    .await;
    let root = scratch.path().display().to_string();
    let dataset = register_path(&mut daemon.datasets().await, &root).await;
    let mut jobs = daemon.jobs().await;
    let previewed_job = |name: &str, preview: bool| {
        let request = pb::SubmitJobRequest {
            preview,
            ..lod_turntable_job(name, &dataset.id, 4, (160, 120), 0.5)
        };
        with_video(request, "mp4", "")
    };
    let job = submit(&mut jobs, previewed_job("previewed", true)).await;

    let preview_video = scratch.path().join("preview.mp4");
    fetch_preview_video_when_stored(&mut jobs, &job.id, &preview_video).await;
    assert_eq!(probe(&preview_video), ("h264".to_owned(), 160, 120, 4));
    let shown = get_job(&mut jobs, &job.id).await;
    assert_eq!(shown.state, pb::JobState::Running as i32, "{shown:?}");
    assert_eq!(shown.frames_done, 0, "made of previews alone: {shown:?}");
    assert_eq!(shown.video_size_bytes, 0, "no final video yet: {shown:?}");
    // `jobs video --preview` fetches the same file.
    let again = scratch.path().join("again.mp4");
    let fetched = fetch_video_with_cli(&daemon, &job.id, &again, true).await;
    assert!(
        stdout(&fetched).contains("preview video of job"),
        "{fetched:?}"
    );
    let preview_bytes = std::fs::read(&preview_video).expect("preview video");
    assert_eq!(std::fs::read(&again).expect("again"), preview_bytes);

    // The store is ready: the final frames, then the final video, apart from the preview's.
    ready.open();
    let (finished, _) = watch_to_success(&mut jobs, &job.id, String::new).await;
    assert_eq!(finished.frames_done, 4);
    let final_video = scratch.path().join("final.mp4");
    fetch_video(&mut jobs, &job.id, &final_video).await;
    assert_eq!(probe(&final_video), ("h264".to_owned(), 160, 120, 4));
    assert_ne!(std::fs::read(&final_video).expect("final"), preview_bytes);
    let kept = scratch.path().join("kept.mp4");
    fetch_preview_video_when_stored(&mut jobs, &job.id, &kept).await;
    assert_eq!(std::fs::read(&kept).expect("kept"), preview_bytes);

    // A job without previews makes none; its final video comes.
    let plain = submit(&mut jobs, previewed_job("plain", false)).await;
    watch_to_success(&mut jobs, &plain.id, String::new).await;
    fetch_video(&mut jobs, &plain.id, &scratch.path().join("plain.mp4")).await;
    let refused = ask_for_video(&mut jobs, &plain.id, true)
        .await
        .expect_err("no preview video");
    assert_eq!(refused.code(), tonic::Code::FailedPrecondition);
    assert!(
        refused.message().contains("asked for no previews"),
        "{refused:?}"
    );
    daemon.stop().await;
}

/// The target: a 120-frame 1920x1080 turntable's video ready within 10 s of its last frame.
/// `cargo test -p pointfarm-tests --test job_video -- --ignored --nocapture` prints the time
/// from the event that reports the video stage to the job's success.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[ignore = "a measurement: renders 120 full-HD frames"]
async fn a_full_hd_turntables_video_is_ready_soon_after_its_last_frame() {
    let daemon = TestDaemon::start(|_| {}, Access::default()).await;
    let dataset = upload_sample(&mut daemon.datasets().await, 200_000, 7).await;
    let mut jobs = daemon.jobs().await;
    let job = submit(
        &mut jobs,
        pb::SubmitJobRequest {
            video: Some(pb::VideoSpec {
                container: "mp4".into(),
                ..Default::default()
            }),
            ..turntable_job("full-hd", &dataset.id, 120, 1920, 1080)
        },
    )
    .await;
    let mut events = watch(&mut jobs, &job.id).await;
    let (mut video_stage, mut ended) = (None, None);
    let started = Instant::now();
    while let Some(event) = events.message().await.expect("event") {
        let Some(job) = event.job else { continue };
        if job.stage == "video" && video_stage.is_none() {
            video_stage = Some(Instant::now());
        }
        if job.state == pb::JobState::Succeeded as i32 {
            ended = Some((Instant::now(), job));
            break;
        }
        assert_ne!(job.state, pb::JobState::Failed as i32, "{}", job.error);
    }
    let (ended, done) = ended.expect("the job succeeded");
    let after_last_frame = ended - video_stage.expect("a video stage");
    println!(
        "120 frames 1920x1080: rendered in {:.1} s; video of {} bytes ready {:.2} s after the last frame",
        (video_stage.expect("stage") - started).as_secs_f64(),
        done.video_size_bytes,
        after_last_frame.as_secs_f64()
    );
    assert!(
        after_last_frame < Duration::from_secs(10),
        "the video took {after_last_frame:?}"
    );
    daemon.stop().await;
}

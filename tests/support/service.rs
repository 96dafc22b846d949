//! A daemon (with or without an embedded worker) on a loopback port, and clients for it.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use pointfarm_daemon::access::Access;
use pointfarm_daemon::model::JobSpec;
use pointfarm_daemon::server::ServeOptions;
use pointfarm_daemon::service::{Daemon, DaemonConfig};
use pointfarm_daemon::supervisor::WorkerCommand;
use pointfarm_proto::v1 as pb;
use pointfarm_proto::v1::dataset_service_client::DatasetServiceClient;
use pointfarm_proto::v1::job_service_client::JobServiceClient;
use pointfarm_proto::v1::worker_service_client::WorkerServiceClient;
use pointfarm_render::extent::Extent;
use pointfarm_render::filter::{ClipBox, PointFilter};
use pointfarm_render::ingest::{load_point_cloud, write_las, LasWriteOptions};
use pointfarm_render::raster::{Exposure, FrameSettings, Renderer};
use pointfarm_render::request::{
    CameraPath, Lens, RenderOptions, RenderRequest, StillCamera, Turntable,
};
use sha2::{Digest, Sha256};
use tonic::transport::Channel;

use crate::ServeProcess;

pub use pointfarm_render::testing::gpu;

/// A running daemon; shut down and its data deleted on drop.
pub struct TestDaemon {
    pub address: SocketAddr,
    pub data_dir: tempfile::TempDir,
    shutdown: Option<tokio::sync::oneshot::Sender<()>>,
    task: Option<tokio::task::JoinHandle<()>>,
}

impl TestDaemon {
    /// Starts a daemon with an embedded worker (a `pointfarm worker` process); `configure` may change the defaults (limits,
    /// data roots).
    pub async fn start(configure: impl FnOnce(&mut DaemonConfig), access: Access) -> Self {
        Self::start_with(configure, access, true).await
    }

    /// Starts a daemon without an embedded worker: only worker processes render for it.
    pub async fn start_without_worker(
        configure: impl FnOnce(&mut DaemonConfig),
        access: Access,
    ) -> Self {
        Self::start_with(configure, access, false).await
    }

    async fn start_with(
        configure: impl FnOnce(&mut DaemonConfig),
        access: Access,
        embedded_worker: bool,
    ) -> Self {
        let data_dir = tempfile::tempdir().expect("tempdir");
        let mut config = DaemonConfig::new(data_dir.path().to_path_buf());
        configure(&mut config);
        let worker = embedded_worker.then(|| embedded_worker_command(&config));
        let daemon = Daemon::open(config).expect("open daemon");
        let (address, shutdown, task) = serve_on_loopback(daemon, worker, access).await;
        Self {
            address,
            data_dir,
            shutdown: Some(shutdown),
            task: Some(task),
        }
    }

    pub async fn channel(&self) -> Channel {
        connect(&self.address.to_string()).await
    }

    pub async fn jobs(&self) -> JobServiceClient<Channel> {
        JobServiceClient::new(self.channel().await)
    }

    pub async fn workers(&self) -> WorkerServiceClient<Channel> {
        WorkerServiceClient::new(self.channel().await)
    }

    /// The address as `pointfarm worker --server` takes it.
    pub fn url(&self) -> String {
        format!("http://{}", self.address)
    }

    pub async fn datasets(&self) -> DatasetServiceClient<Channel> {
        DatasetServiceClient::new(self.channel().await)
    }

    /// This daemon, the generated sample scene (`points` of them, from `seed`) uploaded to it
    /// (as [`upload_sample`] does), and a client of its jobs.
    pub async fn with_sample(
        self,
        points: usize,
        seed: u64,
    ) -> (Self, pb::Dataset, JobServiceClient<Channel>) {
        let dataset = upload_sample(&mut self.datasets().await, points, seed).await;
        let jobs = self.jobs().await;
        (self, dataset, jobs)
    }

    /// Stops the server and waits until the worker has finished its frame.
    pub async fn stop(mut self) {
        if let Some(shutdown) = self.shutdown.take() {
            let _ = shutdown.send(());
        }
        if let Some(task) = self.task.take() {
            let _ = task.await;
        }
    }
}

impl Drop for TestDaemon {
    fn drop(&mut self) {
        if let Some(shutdown) = self.shutdown.take() {
            let _ = shutdown.send(());
        }
    }
}

/// Serves `daemon`'s API with the tokens of `access` (and `worker` as its embedded worker)
/// on a loopback port, in a task of this runtime: the address, the sender that stops it and
/// the task.
pub async fn serve_on_loopback(
    daemon: Arc<Daemon>,
    worker: Option<WorkerCommand>,
    access: Access,
) -> (
    SocketAddr,
    tokio::sync::oneshot::Sender<()>,
    tokio::task::JoinHandle<()>,
) {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
        .await
        .expect("bind loopback");
    let address = listener.local_addr().expect("address");
    let (shutdown, signal) = tokio::sync::oneshot::channel::<()>();
    let options = ServeOptions {
        access,
        ..ServeOptions::default()
    };
    let task = tokio::spawn(async move {
        let stop = async {
            let _ = signal.await;
        };
        pointfarm_daemon::server::serve(daemon, worker, listener, options, stop)
            .await
            .expect("serve");
    });
    (address, shutdown, task)
}

/// The embedded worker of a daemon with `config`: this workspace's `pointfarm worker`.
fn embedded_worker_command(config: &DaemonConfig) -> WorkerCommand {
    WorkerCommand {
        program: crate::pointfarm_bin().to_path_buf(),
        args: vec![
            "worker".into(),
            "--cache-dir".into(),
            config.data_dir.join("embedded-worker").into(),
        ],
        env_removed: Vec::new(),
    }
}

/// A channel to the daemon at `address` (`host:port`).
pub async fn connect(address: &str) -> Channel {
    Channel::from_shared(format!("http://{address}"))
        .expect("url")
        .connect()
        .await
        .expect("connect")
}

/// Dataset and job clients of the daemon at `address` (`host:port`), e.g. a `ServeProcess`.
pub async fn clients(address: &str) -> (DatasetServiceClient<Channel>, JobServiceClient<Channel>) {
    let channel = connect(address).await;
    (
        DatasetServiceClient::new(channel.clone()),
        JobServiceClient::new(channel),
    )
}

/// The upload messages for `bytes` named `name`.
pub fn upload_messages(name: &str, bytes: &[u8]) -> Vec<pb::UploadDatasetRequest> {
    let sha256: String = Sha256::digest(bytes)
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect();
    let header = pb::UploadDatasetRequest {
        part: Some(pb::upload_dataset_request::Part::Header(pb::UploadHeader {
            name: name.into(),
            size_bytes: bytes.len() as u64,
            sha256,
        })),
    };
    std::iter::once(header)
        .chain(bytes.chunks(256 * 1024).map(|c| pb::UploadDatasetRequest {
            part: Some(pb::upload_dataset_request::Part::Data(c.to_vec())),
        }))
        .collect()
}

/// The dataset service of a daemon on loopback.
pub type Datasets = DatasetServiceClient<Channel>;

pub async fn upload(datasets: &mut Datasets, name: &str, bytes: &[u8]) -> pb::Dataset {
    datasets
        .upload_dataset(tokio_stream::iter(upload_messages(name, bytes)))
        .await
        .expect("upload")
        .into_inner()
}

/// Uploads the file at `path` as `name`.
pub async fn upload_file(datasets: &mut Datasets, name: &str, path: &Path) -> pb::Dataset {
    let bytes = std::fs::read(path).expect("read the file to upload");
    upload(datasets, name, &bytes).await
}

pub fn turntable_job(
    request_id: &str,
    dataset_id: &str,
    frames: u32,
    width: u32,
    height: u32,
) -> pb::SubmitJobRequest {
    pb::SubmitJobRequest {
        request_id: request_id.into(),
        dataset_id: dataset_id.into(),
        camera_path: Some(pb::CameraPath::turntable(pb::Turntable::of_frames(frames))),
        width,
        height,
        ..Default::default()
    }
}

/// [`turntable_job`] drawn from levels of detail at the pixel error `lod_error`: its dataset
/// needs a store.
pub fn lod_turntable_job(
    request_id: &str,
    dataset_id: &str,
    frames: u32,
    (width, height): (u32, u32),
    lod_error: f64,
) -> pb::SubmitJobRequest {
    pb::SubmitJobRequest {
        render: Some(pb::RenderOptions {
            lod_error: Some(lod_error),
            ..Default::default()
        }),
        ..turntable_job(request_id, dataset_id, frames, width, height)
    }
}

/// A lease for the worker `worker_name` that answers at once, with a frame or with none.
pub fn lease_at_once(worker_name: &str) -> pb::LeaseFrameRequest {
    pb::LeaseFrameRequest {
        worker_name: worker_name.into(),
        wait_ms: 0,
        capabilities: None,
    }
}

/// Submits `request`; the job as the daemon answers.
pub async fn submit(
    jobs: &mut JobServiceClient<Channel>,
    request: pb::SubmitJobRequest,
) -> pb::Job {
    jobs.submit_job(request).await.expect("submit").into_inner()
}

/// Cancels the job `id`; the job as the daemon answers.
pub async fn cancel(jobs: &mut JobServiceClient<Channel>, id: &str) -> pb::Job {
    jobs.cancel_job(pb::CancelJobRequest { id: id.into() })
        .await
        .expect("cancel")
        .into_inner()
}

/// The job `id` as GetJob shows it, with its finished frames.
pub async fn get_job(jobs: &mut JobServiceClient<Channel>, id: &str) -> pb::Job {
    jobs.get_job(pb::GetJobRequest { id: id.into() })
        .await
        .expect("get")
        .into_inner()
}

/// The leases the daemon of `jobs` holds now.
pub async fn list_leases(jobs: &mut JobServiceClient<Channel>) -> Vec<pb::Lease> {
    jobs.list_leases(pb::ListLeasesRequest {})
        .await
        .expect("list leases")
        .into_inner()
        .leases
}

/// When job `id` first left the queue (was leased, or ended): the update time of the first
/// event of its watch in another state than queued or paused.
pub async fn left_the_queue_at(jobs: &mut JobServiceClient<Channel>, id: &str) -> i64 {
    let mut stream = jobs
        .watch_job(pb::WatchJobRequest { id: id.into() })
        .await
        .expect("watch")
        .into_inner();
    while let Some(event) = stream.message().await.expect("event") {
        let waiting = [pb::JobState::Queued as i32, pb::JobState::Paused as i32];
        if let Some(job) = event.job.filter(|job| !waiting.contains(&job.state)) {
            return job.updated_unix_ms;
        }
    }
    panic!("job {id} never left the queue");
}

/// Watches a job to its end, asserting that it succeeded; a failure shows the job's error and
/// `context` (e.g. a worker's log). Returns the final job and the finished-frame events.
pub async fn watch_to_success(
    jobs: &mut JobServiceClient<Channel>,
    id: &str,
    context: impl FnOnce() -> String,
) -> (pb::Job, Vec<pb::FrameFinished>) {
    let (finished, frames) = watch_to_end(jobs, id).await;
    assert_eq!(
        finished.state,
        pb::JobState::Succeeded as i32,
        "{}\n{}",
        finished.error,
        context()
    );
    (finished, frames)
}

/// A 64x48 still whose clip box, a unit cube at the origin, lies outside the generated sample
/// scene: a job of it fails saying so.
pub fn still_clipped_outside_the_sample() -> RenderRequest {
    let mut request = RenderRequest {
        width: 64,
        height: 48,
        camera_path: CameraPath::Still(StillCamera::default()),
        lens: Lens::default(),
        render: RenderOptions::default(),
    };
    request.render.filter = PointFilter {
        clip: Some(ClipBox {
            min: [0.0, 0.0, 0.0],
            max: [1.0, 1.0, 1.0],
        }),
        ..Default::default()
    };
    request
}

/// Submits `request` on `dataset_id` as the job `name` (its request id) and watches it to its
/// end; returns the final job.
pub async fn run_job(
    jobs: &mut JobServiceClient<Channel>,
    dataset_id: &str,
    name: &str,
    request: RenderRequest,
) -> pb::Job {
    let spec = JobSpec::new(name.into(), dataset_id.into(), request);
    let job = jobs
        .submit_job(pb::SubmitJobRequest::from(&spec))
        .await
        .unwrap_or_else(|e| panic!("{name}: {e}"))
        .into_inner();
    watch_to_end(jobs, &job.id).await.0
}

/// The event stream of job `id`: its state first (with the frames already finished), then an
/// event per change.
pub async fn watch(
    jobs: &mut JobServiceClient<Channel>,
    id: &str,
) -> tonic::Streaming<pb::JobEvent> {
    jobs.watch_job(pb::WatchJobRequest { id: id.into() })
        .await
        .expect("watch")
        .into_inner()
}

/// Watches a job to its end; returns the final job and the finished-frame events.
pub async fn watch_to_end(
    jobs: &mut JobServiceClient<Channel>,
    id: &str,
) -> (pb::Job, Vec<pb::FrameFinished>) {
    let mut stream = watch(jobs, id).await;
    let mut frames = Vec::new();
    let mut last = None;
    let deadline = tokio::time::Instant::now() + std::time::Duration::from_secs(300);
    while let Ok(Some(event)) = tokio::time::timeout_at(deadline, stream.message())
        .await
        .expect("job ends within 5 minutes")
    {
        if let Some(job) = &event.job {
            // The first event holds the frames finished before the watch began.
            frames.extend(job.frames.iter().cloned());
        }
        frames.extend(event.frame);
        last = event.job;
    }
    frames.sort_by_key(|frame| frame.index);
    (last.expect("at least one event"), frames)
}

/// All finished frames of a job as decoded images, by index.
pub async fn fetch_images(
    jobs: &mut JobServiceClient<Channel>,
    id: &str,
    from_index: u32,
) -> Vec<(u32, image::RgbaImage)> {
    let mut stream = jobs
        .fetch_frames(pb::FetchFramesRequest {
            job_id: id.into(),
            from_index,
        })
        .await
        .expect("fetch")
        .into_inner();
    let mut images = Vec::new();
    let mut buffer = Vec::new();
    while let Some(chunk) = stream.message().await.expect("frame chunk") {
        buffer.extend_from_slice(&chunk.png);
        if chunk.last {
            images.push((
                chunk.index,
                image::load_from_memory(&buffer).expect("png").to_rgba8(),
            ));
            buffer.clear();
        }
    }
    images
}

/// Asserts that the fetched frames are every frame of a default turntable of `frames` frames
/// around `file`, in order, each equal to the renderer's direct rendering of that frame,
/// exposed with the gain its frame 0 measures as every frame of a job is.
pub fn assert_equal_to_direct_renders(
    file: &Path,
    frames: u32,
    (width, height): (u32, u32),
    fetched: &[(u32, image::RgbaImage)],
) {
    let indices: Vec<u32> = fetched.iter().map(|(index, _)| *index).collect();
    assert_eq!(
        indices,
        (0..frames).collect::<Vec<_>>(),
        "the fetched frames"
    );
    let cloud = load_point_cloud(file).expect("load");
    let mut renderer = Renderer::new(gpu());
    let resident = renderer.upload(&cloud).expect("upload");
    let request = RenderRequest {
        width,
        height,
        camera_path: CameraPath::Turntable(Turntable::around_the_cloud(frames)),
        lens: Lens::default(),
        render: RenderOptions::default(),
    };
    // Framed as a frame source frames a resident cloud: by the robust extent of a sample.
    let sample = pointfarm_render::spacing::sample_of(&cloud.positions);
    let extent = Extent::of_points(cloud.bounds, cloud.origin, &sample, &cloud.positions);
    let spacing = pointfarm_render::spacing::of_sample(&sample, cloud.len() as u64);
    let first = renderer
        .render(&resident, &request.frame_settings(0, &extent, spacing))
        .expect("render frame 0");
    for (index, image) in fetched {
        let settings = FrameSettings {
            exposure: first.gain.map_or(Exposure::Measured, Exposure::Held),
            ..request.frame_settings(*index, &extent, spacing)
        };
        let direct = renderer.render(&resident, &settings).expect("render");
        assert!(
            direct.image == *image,
            "frame {index} differs from the direct rendering"
        );
    }
}

/// Writes the generated sample scene (`points` of them, from `seed`) to `path` as LAS.
pub fn write_sample(path: &Path, points: usize, seed: u64) {
    let cloud = pointfarm_render::sample::sample_scene(points, seed);
    write_las(path, &cloud, &LasWriteOptions::default()).expect("write sample");
}

/// A scratch folder holding the generated sample scene (`points` of them, from `seed`) as
/// the LAS file `name`; the folder is deleted when dropped.
pub fn scratch_sample(name: &str, points: usize, seed: u64) -> (tempfile::TempDir, PathBuf) {
    let scratch = tempfile::tempdir().expect("tempdir");
    let file = scratch.path().join(name);
    write_sample(&file, points, seed);
    (scratch, file)
}

/// `pointfarm render FILE --server ADDRESS --turntable 2 --size 32x24 --out OUT --detach`,
/// with `more` arguments after: a small job submitted as a script submits it.
pub fn render_detached(
    address: &str,
    file: &str,
    out: &str,
    more: &[&str],
) -> std::process::Output {
    let mut args = vec![
        "render",
        file,
        "--server",
        address,
        "--turntable",
        "2",
        "--size",
        "32x24",
        "--out",
        out,
        "--detach",
    ];
    args.extend_from_slice(more);
    crate::pointfarm(&args)
}

/// The generated sample scene (`points` of them, from `seed`) uploaded through `datasets` as
/// `s.las`.
pub async fn upload_sample(datasets: &mut Datasets, points: usize, seed: u64) -> pb::Dataset {
    let (_scratch, file) = scratch_sample("s.las", points, seed);
    upload_file(datasets, "s.las", &file).await
}

/// A jobs client of the daemon at `address`, and the sample scene uploaded to it (as
/// [`upload_sample`] does).
pub async fn jobs_on_a_sample(
    address: &str,
    points: usize,
    seed: u64,
) -> (JobServiceClient<Channel>, pb::Dataset) {
    let (mut datasets, jobs) = clients(address).await;
    let dataset = upload_sample(&mut datasets, points, seed).await;
    (jobs, dataset)
}

/// A daemon with an embedded worker, and the generated sample scene (`points` of them, from
/// `seed`) uploaded to it as `sample.las`.
pub async fn daemon_with_sample(points: usize, seed: u64) -> (TestDaemon, pb::Dataset) {
    let (_scratch, file) = scratch_sample("sample.las", points, seed);
    let daemon = TestDaemon::start(|_| {}, Access::default()).await;
    let dataset = upload_file(&mut daemon.datasets().await, "sample.las", &file).await;
    (daemon, dataset)
}

/// A daemon started with `configure` and without a worker, so that its jobs stay queued until
/// a test starts one, with the generated sample scene uploaded ([`TestDaemon::with_sample`]).
pub async fn queued_farm(
    configure: impl FnOnce(&mut DaemonConfig),
    points: usize,
    seed: u64,
) -> (TestDaemon, pb::Dataset, JobServiceClient<Channel>) {
    let daemon = TestDaemon::start_without_worker(configure, Access::default()).await;
    daemon.with_sample(points, seed).await
}

/// What detached renders (`pointfarm render --server --detach`) are submitted to: a
/// `pointfarm serve` process without a worker, so that their jobs stay queued, and the
/// generated sample scene to render, in one scratch folder with the daemon's data and the
/// frames folder the renders name.
pub struct DetachedFarm {
    pub server: ServeProcess,
    pub address: String,
    /// The sample scene's LAS file.
    pub file: String,
    /// The frames folder each render names.
    pub out: String,
    /// The daemon's data folder.
    pub data: PathBuf,
    // Declared last: dropped once the daemon is killed.
    _scratch: tempfile::TempDir,
}

impl DetachedFarm {
    /// The farm, its sample scene `points` points generated from `seed`.
    pub fn start(points: usize, seed: u64) -> Self {
        let scratch = tempfile::tempdir().expect("tempdir");
        let file = scratch.path().join("s.las");
        write_sample(&file, points, seed);
        let data = scratch.path().join("data");
        let server = ServeProcess::start_with(&data, &["--no-embedded-worker"]);
        Self {
            address: server.address.clone(),
            server,
            file: file.to_str().expect("utf-8").to_owned(),
            out: scratch
                .path()
                .join("frames")
                .to_str()
                .expect("utf-8")
                .to_owned(),
            data,
            _scratch: scratch,
        }
    }

    /// [`render_detached`] of the sample scene to this farm, with `more` arguments.
    pub fn render(&self, more: &[&str]) -> std::process::Output {
        render_detached(&self.address, &self.file, &self.out, more)
    }

    /// Kills the daemon and starts it again on the same address and data, with `args`.
    pub fn restart(&mut self, args: &[&str]) {
        self.server.kill();
        self.server = ServeProcess::start_with_args(&self.address, &self.data, args);
    }
}

/// autzen_trim.laz when the real scans are present, else a generated sample in `dir`.
pub fn scan(dir: &Path) -> PathBuf {
    if let Some(path) = crate::shared_data("autzen_trim.laz") {
        return path;
    }
    let path = dir.join("sample.laz");
    write_sample(&path, 60_000, 3);
    path
}

/// `pointfarm render SCAN --server ADDRESS --turntable FRAMES --detach --output-url URL`, small
/// frames into `out`, expecting it taken: the job's id.
pub fn submit_detached(
    address: &str,
    scan: &Path,
    frames: u32,
    (out, url): (&Path, &str),
) -> String {
    let frames = frames.to_string();
    let output = crate::pointfarm_ok(&[
        "render",
        crate::path_arg(scan),
        "--server",
        address,
        "--turntable",
        &frames,
        "--size",
        "64x48",
        "--out",
        crate::path_arg(out),
        "--detach",
        "--output-url",
        url,
    ]);
    crate::stdout(&output).trim().to_owned()
}

//! A daemon (with or without an embedded worker) on a loopback port, and clients for it.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::{Arc, OnceLock};

use pointfarm_daemon::service::{Daemon, DaemonConfig};
use pointfarm_proto::v1 as pb;
use pointfarm_proto::v1::dataset_service_client::DatasetServiceClient;
use pointfarm_proto::v1::job_service_client::JobServiceClient;
use pointfarm_proto::v1::worker_service_client::WorkerServiceClient;
use pointfarm_render::gpu::{AdapterChoice, GpuContext};
use pointfarm_render::ingest::{write_las, LasWriteOptions};
use sha2::{Digest, Sha256};
use tonic::transport::Channel;

/// One GPU for all the daemons of a test process.
pub fn gpu() -> Arc<GpuContext> {
    static GPU: OnceLock<Arc<GpuContext>> = OnceLock::new();
    GPU.get_or_init(|| {
        Arc::new(
            GpuContext::new(AdapterChoice::from_env().expect("POINTFARM_ADAPTER"))
                .expect("a GPU adapter (lavapipe)"),
        )
    })
    .clone()
}

/// A running daemon; shut down and its data deleted on drop.
pub struct TestDaemon {
    pub address: SocketAddr,
    pub data_dir: tempfile::TempDir,
    shutdown: Option<tokio::sync::oneshot::Sender<()>>,
    task: Option<tokio::task::JoinHandle<()>>,
}

impl TestDaemon {
    /// Starts a daemon with an embedded worker; `configure` may change the defaults (limits,
    /// data roots).
    pub async fn start(configure: impl FnOnce(&mut DaemonConfig), token: Option<&str>) -> Self {
        Self::start_with(configure, token, true).await
    }

    /// Starts a daemon without an embedded worker: only worker processes render for it.
    pub async fn start_without_worker(
        configure: impl FnOnce(&mut DaemonConfig),
        token: Option<&str>,
    ) -> Self {
        Self::start_with(configure, token, false).await
    }

    async fn start_with(
        configure: impl FnOnce(&mut DaemonConfig),
        token: Option<&str>,
        embedded_worker: bool,
    ) -> Self {
        let data_dir = tempfile::tempdir().expect("tempdir");
        let mut config = DaemonConfig::new(data_dir.path().to_path_buf());
        configure(&mut config);
        let daemon = Daemon::open(config).expect("open daemon");
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
            .await
            .expect("bind loopback");
        let address = listener.local_addr().expect("address");
        let (shutdown, signal) = tokio::sync::oneshot::channel::<()>();
        let token = token.map(str::to_owned);
        let task = tokio::spawn(async move {
            let stop = async {
                let _ = signal.await;
            };
            let gpu = embedded_worker.then(gpu);
            pointfarm_daemon::server::serve(daemon, gpu, listener, token, stop)
                .await
                .expect("serve");
        });
        Self {
            address,
            data_dir,
            shutdown: Some(shutdown),
            task: Some(task),
        }
    }

    pub async fn channel(&self) -> Channel {
        Channel::from_shared(format!("http://{}", self.address))
            .expect("url")
            .connect()
            .await
            .expect("connect")
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

pub async fn upload(
    datasets: &mut DatasetServiceClient<Channel>,
    name: &str,
    bytes: &[u8],
) -> pb::Dataset {
    datasets
        .upload_dataset(tokio_stream::iter(upload_messages(name, bytes)))
        .await
        .expect("upload")
        .into_inner()
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
        camera_path: Some(pb::CameraPath {
            path: Some(pb::camera_path::Path::Turntable(pb::Turntable {
                frames,
                ..Default::default()
            })),
            lens: None,
        }),
        width,
        height,
        render: None,
        priority: 0,
    }
}

/// Watches a job to its end; returns the final job and the finished-frame events.
pub async fn watch_to_end(
    jobs: &mut JobServiceClient<Channel>,
    id: &str,
) -> (pb::Job, Vec<pb::FrameFinished>) {
    let mut stream = jobs
        .watch_job(pb::WatchJobRequest { id: id.into() })
        .await
        .expect("watch")
        .into_inner();
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

/// Writes the generated sample scene (`points` of them, from `seed`) to `path` as LAS.
pub fn write_sample(path: &Path, points: usize, seed: u64) {
    let cloud = pointfarm_render::sample::sample_scene(points, seed);
    write_las(path, &cloud, &LasWriteOptions::default()).expect("write sample");
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

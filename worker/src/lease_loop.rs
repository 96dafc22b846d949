//! A worker in its own process (`pointfarm worker`): leases frames from a daemon over gRPC,
//! renders them with [`WorkerRenderState`] on its own GPU and hands the PNGs back.
//!
//! - The dataset's points come from the worker's own `DatasetCache`; a dataset it has never
//!   seen is downloaded once (`FetchDataset`, SHA-256 checked) and decoded into the cache.
//!   A dataset that needs a store is read from the daemon's; while the daemon builds it, a
//!   frame is handed back (the daemon holds it until the store is ready, and the worker asks
//!   for work again at once), or, of a job that asks for previews, rendered from the daemon's
//!   preview sample and handed in as a preview (the daemon leases it again for a redraw when
//!   its build has stored another tenth of the points, the sample fetched again then, and
//!   for its final render once the store is ready).
//!   The cloud stays resident on the GPU across frames of the same dataset.
//! - While a frame renders, heartbeats renew the lease every third of the lease timeout (at
//!   most 5 s apart); when the daemon answers "stop" (job cancelled, lease lost) the frame is
//!   dropped.
//! - Lost connections are retried with exponential backoff, so a daemon restart is ridden out;
//!   a finished frame is handed in again until its lease would have expired.
//! - RESOURCE_EXHAUSTED means the daemon cannot store frames now (its disk is full): it gave
//!   the frame back to its queue, and the worker waits with the same backoff before asking
//!   for another, saying so once, not per try.
//! - Stopping (SIGTERM) lets the current frame finish and hands it in; a stop while waiting for
//!   work exits at once.
//! - Every lease request says what the worker can render (`WorkerCapabilities`: its adapter,
//!   the largest image side it draws, the operator's tags), so the daemon leases it only frames
//!   it can render.
//! - A failed frame is reported with its kind: permanent (the dataset cannot be read, the
//!   request cannot render) fails the job at once, transient is tried again. A panic while
//!   rendering is reported, and then the worker exits: its renderer is lost.

use std::future::Future;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

use anyhow::{bail, Context};
use pointfarm_daemon::capabilities::WorkerCapabilities;
use pointfarm_daemon::grpc::streaming::{HashingWriter, CHUNK_BYTES};
use pointfarm_daemon::grpc::{frame_cut_message, frame_task, timings_message};
use pointfarm_daemon::lease::{FrameTask, TaskFile};
use pointfarm_daemon::metrics::WorkerMetrics;
use pointfarm_proto::endpoint::{certificate, ServerEndpoint};
use pointfarm_proto::v1 as pb;
use pointfarm_proto::v1::worker_service_client::WorkerServiceClient;
use pointfarm_proto::BearerToken;
use pointfarm_render::cache::DatasetCache;
use pointfarm_render::cut::CutOptions;
use pointfarm_render::gpu::GpuContext;
use pointfarm_render::source::StoreCache;
use tokio::sync::watch;
use tonic::{Code, Status};
use tracing::Instrument;

use crate::backoff::Backoff;
use crate::client::Client;
use crate::daemon_store::{self, DaemonStore};
use crate::failure::FrameFailure;
use crate::lease_renewal::{keep_lease, renewal_interval};
use crate::range_cache::DiskRangeCache;
use crate::render_state::{DatasetAccess, LodConfig, RenderedFrame, WorkerRenderState};
use crate::stopping::stopped_during;
use crate::url_dataset::UrlReader;

/// How long one lease request waits for work on the daemon.
const LEASE_WAIT_MS: u32 = 10_000;

#[derive(Debug, Clone)]
pub struct RemoteWorkerConfig {
    /// The daemon, e.g. `http://127.0.0.1:50051`, and for `https://` the CA to trust.
    pub server: ServerEndpoint,
    /// The daemon's `--worker-token`.
    pub token: Option<String>,
    /// Shown in the daemon's leases and logs.
    pub name: String,
    /// The worker's dataset cache and downloads live here.
    pub cache_dir: PathBuf,
    pub cache_bytes: u64,
    /// The bound of the cache of ranges of datasets by URL, in `cache_dir/ranges` (0: none).
    pub url_cache_bytes: u64,
    /// The pixel error of datasets rendered from levels of detail without one of their own,
    /// and the node caches' budgets.
    pub cut: CutOptions,
    /// What the worker counts of its frames (served when `worker --metrics-listen` asks).
    pub metrics: Arc<WorkerMetrics>,
    /// What the worker says it can render, with every lease request: the daemon leases it
    /// only frames of jobs it meets the requirements of, no larger than it draws.
    pub capabilities: WorkerCapabilities,
    /// Make jobs' videos too, when this machine's ffmpeg can (`encode`).
    pub videos: bool,
}

/// Whether a failed call may succeed when tried again (the daemon restarting, a network cut).
fn is_transient(status: &Status) -> bool {
    matches!(
        status.code(),
        Code::Unavailable
            | Code::Unknown
            | Code::DeadlineExceeded
            | Code::Aborted
            | Code::Cancelled
    )
}

/// Whether the daemon refused a call because it cannot store frames now (its disk is full):
/// the frame is back in its queue, and the worker waits before it asks for another.
fn daemon_cannot_store(status: &Status) -> bool {
    status.code() == Code::ResourceExhausted
}

/// How a leased frame ended, for the lease loop.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum TaskEnd {
    Finished,
    /// The daemon could not store the result (its disk is full): wait before the next lease.
    DaemonCannotStore,
    /// The daemon is building the store the frame needs: wait before the next lease.
    StoreBuilding,
}

/// Runs the worker until `shutdown` completes (and the current frame is handed in).
pub async fn run(
    config: RemoteWorkerConfig,
    gpu: Arc<GpuContext>,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> anyhow::Result<()> {
    std::fs::create_dir_all(&config.cache_dir)
        .with_context(|| format!("creating {}", config.cache_dir.display()))?;
    let cache_path = config.cache_dir.join("datasets.sled");
    let cache = DatasetCache::open(&cache_path, config.cache_bytes)
        .with_context(|| format!("opening the dataset cache {}", cache_path.display()))?;
    let downloads = config.cache_dir.join("downloads");
    // Downloads are removed once decoded; what is left was interrupted.
    let _ = std::fs::remove_dir_all(&downloads);
    std::fs::create_dir_all(&downloads)
        .with_context(|| format!("creating {}", downloads.display()))?;

    let url = config.server.url().to_owned();
    let channel = config.server.endpoint()?.connect_lazy();
    let token = BearerToken::new(config.token.as_deref())?;
    let mut client =
        WorkerServiceClient::with_interceptor(channel, token).max_decoding_message_size(8 << 20);

    let (stop_sender, mut stop) = watch::channel(false);
    tokio::spawn(async move {
        shutdown.await;
        tracing::info!("stopping: the current frame is finished first");
        let _ = stop_sender.send(true);
    });

    let lod = LodConfig {
        stores: StoreCache {
            dir: config.cache_dir.join("lod"),
            disk_budget: Some(config.cache_bytes),
        },
        options: config.cut,
    };
    let urls = match config.url_cache_bytes {
        0 => UrlReader::default(),
        budget => {
            let dir = config.cache_dir.join("ranges");
            let ranges = DiskRangeCache::open(&dir, budget)
                .with_context(|| format!("opening the range cache {}", dir.display()))?;
            UrlReader::with_cache(Arc::new(ranges))
        }
    };
    let mut render_state =
        Some(WorkerRenderState::new(gpu, Some(Arc::new(cache)), Some(lod)).with_url_reader(urls));
    let encoders = match config.videos {
        true => tokio::task::spawn_blocking(crate::encode::probe_encoders).await?,
        false => Vec::new(),
    };
    // Said with every lease request, so a job whose video no worker can make says why.
    let capabilities = pb::WorkerCapabilities {
        video_encoders: encoders.clone(),
        ..pb::WorkerCapabilities::from(&config.capabilities)
    };
    let videos = tokio::spawn(crate::encode::run(
        client.clone(),
        config.name.clone(),
        encoders,
        config.cache_dir.join("videos"),
        stop.clone(),
    ));
    let mut backoff = Backoff::calls();
    // The daemon holds a frame whose store builds and wakes the lease long poll when it is
    // ready, so a frame handed back is followed by a lease request at once; only a second one
    // in a row (a frame leased as its store's build began) waits, less the sooner it is ready.
    let mut store_building = Backoff::store_building();
    let mut handed_back = false;
    // Said once when the daemon cannot store frames, once when it can again.
    let mut daemon_full = false;
    tracing::info!(server = %url, worker = %config.name, "worker started");
    while !*stop.borrow() {
        let request = pb::LeaseFrameRequest {
            worker_name: config.name.clone(),
            wait_ms: LEASE_WAIT_MS,
            capabilities: Some(capabilities.clone()),
        };
        let mut lease_client = client.clone();
        let lease_call = lease_client.lease_frame(request);
        tokio::pin!(lease_call);
        let leased = tokio::select! {
            leased = &mut lease_call => leased,
            _ = stop.changed() => {
                // A lease may be on its way: take it and give it back. A request still
                // waiting for work is dropped (the daemon then gives back what it leased).
                if let Ok(Ok(response)) = tokio::time::timeout(Duration::from_secs(1), &mut lease_call).await {
                    if let Some(task) = response.into_inner().task {
                        release_frame(&mut client, &task.lease_id).await;
                    }
                }
                break;
            }
        };
        let message = match leased {
            Ok(response) => {
                backoff.reset();
                if std::mem::take(&mut daemon_full) {
                    tracing::info!("the daemon stores frames again");
                }
                match response.into_inner().task {
                    Some(task) => task,
                    None => continue,
                }
            }
            Err(status) if daemon_cannot_store(&status) => {
                let wait = backoff.next();
                if !std::mem::replace(&mut daemon_full, true) {
                    tracing::warn!(
                        message = status.message(),
                        "the daemon cannot store frames now; waiting until it can"
                    );
                }
                if stopped_during(&mut stop, wait).await {
                    break;
                }
                continue;
            }
            // Retrying cannot help: the daemon's certificate has to be replaced.
            Err(status) if certificate::is_ca_used_as_server_certificate(&status) => {
                return Err(config.server.connect_error(&status).into());
            }
            Err(status) if is_transient(&status) => {
                let wait = backoff.next();
                tracing::warn!(code = ?status.code(), message = status.message(), ?wait, "the daemon is unreachable; retrying");
                if stopped_during(&mut stop, wait).await {
                    break;
                }
                continue;
            }
            Err(status) => bail!(
                "the daemon refused to lease frames: {}: {}",
                pointfarm_proto::code_words(status.code()),
                status.message()
            ),
        };
        let task = match frame_task(&message, &config.name) {
            Ok(task) => task,
            Err(e) => {
                let failure = FrameFailure::permanent(format!("the task is invalid: {e}"));
                tracing::error!(reason = %failure.reason);
                fail_frame(&mut client, &message.lease_id, &failure).await;
                continue;
            }
        };
        let span = tracing::info_span!(
            "frame",
            job = %task.lease.job_id,
            frame = task.lease.index,
            lease = %task.lease.id
        );
        let end = run_task(
            &mut client,
            &mut render_state,
            &downloads,
            task,
            &config.metrics,
        )
        .instrument(span)
        .await?;
        let wait = match end {
            TaskEnd::Finished => {
                store_building.reset();
                handed_back = false;
                None
            }
            TaskEnd::DaemonCannotStore => {
                daemon_full = true;
                Some(backoff.next())
            }
            TaskEnd::StoreBuilding => {
                std::mem::replace(&mut handed_back, true).then(|| store_building.next())
            }
        };
        if let Some(wait) = wait {
            if stopped_during(&mut stop, wait).await {
                break;
            }
        }
    }
    // The video being made is handed in before the worker exits.
    let _ = videos.await;
    tracing::info!("worker stopped");
    Ok(())
}

/// Renders one leased frame and hands it in (or reports the failure). Errors only when the
/// worker cannot go on.
async fn run_task(
    client: &mut Client,
    render_state: &mut Option<WorkerRenderState>,
    downloads: &Path,
    task: FrameTask,
    metrics: &WorkerMetrics,
) -> anyhow::Result<TaskEnd> {
    tracing::info!(
        dataset = %task.dataset.id,
        size = %format!("{}x{}", task.request.width, task.request.height),
        failed_attempts = task.failed_attempts,
        "frame leased"
    );
    let abandoned = Arc::new(AtomicBool::new(false));
    let heartbeats = tokio::spawn(keep_lease(
        "frame",
        renewal_interval(task.lease_timeout),
        abandoned.clone(),
        {
            let (client, lease_id) = (client.clone(), task.lease.id.clone());
            move || {
                let mut client = client.clone();
                let request = pb::HeartbeatRequest {
                    lease_id: lease_id.clone(),
                };
                async move { client.heartbeat(request).await }
            }
        },
    ));
    let result = download_and_render(client, render_state, downloads, &task).await;
    heartbeats.abort();
    if abandoned.load(Ordering::SeqCst) {
        tracing::info!("frame dropped on the daemon's word");
        return result.map(|_| TaskEnd::Finished);
    }
    match result {
        Ok(Attempt::Rendered(frame)) => {
            metrics.frame_rendered(&frame.outcome);
            Ok(complete_frame(client, &task, frame).await)
        }
        Ok(Attempt::Failed(failure)) => {
            metrics.frame_failed();
            tracing::warn!(reason = %failure.reason, kind = ?failure.kind, "frame failed");
            Ok(fail_frame(client, &task.lease.id, &failure).await)
        }
        Ok(Attempt::StoreBuilding) => {
            tracing::info!(dataset = %task.dataset.id, "the daemon is building the dataset's store; frame handed back");
            release_frame(client, &task.lease.id).await;
            Ok(TaskEnd::StoreBuilding)
        }
        Err(lost) => {
            metrics.frame_failed();
            let failure = FrameFailure::transient(format!("{lost:#}"));
            fail_frame(client, &task.lease.id, &failure).await;
            Err(lost)
        }
    }
}

/// How an attempt at a leased frame went, short of the renderer being lost.
enum Attempt {
    Rendered(RenderedFrame),
    Failed(FrameFailure),
    /// The daemon is building the dataset's store: the frame goes back.
    StoreBuilding,
}

/// Where the points of `task` come from: the daemon's store of its dataset where the daemon
/// keeps one, else its files (downloaded unless the worker has the points).
async fn dataset_access(
    client: &mut Client,
    state: &WorkerRenderState,
    downloads: &Path,
    task: &FrameTask,
) -> Result<DatasetAccess, Attempt> {
    // The worker reads a dataset by URL itself: the daemon has neither its files nor a store.
    if task.dataset.remote.is_some() {
        return Ok(DatasetAccess::Url);
    }
    // A published store is read from object storage: the daemon is out of its data path.
    if state.published_store(task).is_some() {
        return Ok(DatasetAccess::Published);
    }
    if state.is_loaded(task) && !state.is_loaded_resident(task) {
        return Ok(DatasetAccess::Files(Vec::new()));
    }
    match daemon_store::open(client, task).await {
        Ok(DaemonStore::Ready(store)) => return Ok(DatasetAccess::DaemonStore(store)),
        Ok(DaemonStore::Building) if task.preview().is_some() => {
            if state.has_preview(task) {
                return Ok(DatasetAccess::Preview(None));
            }
            return match daemon_store::fetch_preview(client, task).await {
                Ok(sample) => Ok(DatasetAccess::Preview(Some(Box::new(sample)))),
                // The file at fault is named; its store would not build either.
                Err(status) if status.code() == Code::FailedPrecondition => {
                    Err(Attempt::Failed(FrameFailure::permanent(status.message())))
                }
                // A preview is never worth one of the frame's attempts: it goes back uncounted
                // and this worker waits before its next lease, as for a store being built.
                Err(status) => {
                    tracing::warn!(dataset = %task.dataset.id, reason = %status.message(),
                        "no preview sample; frame handed back");
                    Err(Attempt::StoreBuilding)
                }
            };
        }
        Ok(DaemonStore::Building) => return Err(Attempt::StoreBuilding),
        Ok(DaemonStore::NotNeeded) => {}
        Err(status) if status.code() == Code::FailedPrecondition => {
            return Err(Attempt::Failed(FrameFailure::permanent(status.message())));
        }
        Err(status) => {
            return Err(Attempt::Failed(FrameFailure::transient(format!(
                "opening the daemon's store of dataset {}: {}",
                task.dataset.id,
                status.message()
            ))));
        }
    }
    if !state.needs_files(task) {
        return Ok(DatasetAccess::Files(Vec::new()));
    }
    match download(client, task, downloads).await {
        Ok(files) => Ok(DatasetAccess::Files(files)),
        Err(e) => Err(Attempt::Failed(FrameFailure::transient(format!(
            "downloading dataset {}: {e:#}",
            task.dataset.id
        )))),
    }
}

/// The attempt at the frame. The error means the renderer itself was lost (it panicked).
async fn download_and_render(
    client: &mut Client,
    render_state: &mut Option<WorkerRenderState>,
    downloads: &Path,
    task: &FrameTask,
) -> anyhow::Result<Attempt> {
    let state = render_state.as_ref().context("the renderer was lost")?;
    let access = match dataset_access(client, state, downloads, task).await {
        Ok(access) => access,
        Err(attempt) => return Ok(attempt),
    };
    let files = match &access {
        DatasetAccess::Files(files) => files.clone(),
        DatasetAccess::DaemonStore(_)
        | DatasetAccess::Preview(_)
        | DatasetAccess::Url
        | DatasetAccess::Published => Vec::new(),
    };
    let state = render_state.take().context("the renderer was lost")?;
    // Rendering blocks on the GPU: off the async threads, so heartbeats go on meanwhile.
    let blocking_task = task.clone();
    let span = tracing::Span::current();
    let (state, rendered) = tokio::task::spawn_blocking(move || {
        let _entered = span.enter();
        let mut state = state;
        let rendered = state.render(&blocking_task, access);
        (state, rendered)
    })
    .await
    .map_err(|e| anyhow::anyhow!("the renderer panicked: {}", panic_message(e)))?;
    *render_state = Some(state);
    // The points are in the cache now.
    for file in files {
        let _ = tokio::fs::remove_file(file).await;
    }
    Ok(match rendered {
        Ok(frame) => Attempt::Rendered(frame),
        Err(failure) => Attempt::Failed(failure),
    })
}

/// Downloads the dataset's files into `dir`, checking each one's SHA-256; on an error none is
/// left behind.
async fn download(
    client: &mut Client,
    task: &FrameTask,
    dir: &Path,
) -> anyhow::Result<Vec<PathBuf>> {
    let mut paths = Vec::with_capacity(task.dataset.files.len());
    for (index, file) in task.dataset.files.iter().enumerate() {
        match download_file(client, &task.dataset.id, index, file, dir).await {
            Ok(path) => paths.push(path),
            Err(e) => {
                for path in paths {
                    let _ = tokio::fs::remove_file(path).await;
                }
                return Err(e);
            }
        }
    }
    Ok(paths)
}

/// Downloads file `index` of dataset `dataset_id` into `dir`, checking its SHA-256.
async fn download_file(
    client: &mut Client,
    dataset_id: &str,
    index: usize,
    dataset: &TaskFile,
    dir: &Path,
) -> anyhow::Result<PathBuf> {
    let started = std::time::Instant::now();
    let path = dir.join(&dataset.sha256);
    let partial = dir.join(format!("{}.part", dataset.sha256));
    let result = async {
        let mut stream = client
            .fetch_dataset(pb::FetchDatasetRequest {
                dataset_id: dataset_id.to_owned(),
                file_index: u32::try_from(index)?,
            })
            .await
            .map_err(|s| {
                anyhow::anyhow!("{}: {}", pointfarm_proto::code_words(s.code()), s.message())
            })?
            .into_inner();
        let mut file = HashingWriter::create(&partial).await?;
        while let Some(chunk) = stream.message().await.map_err(|s| {
            anyhow::anyhow!("{}: {}", pointfarm_proto::code_words(s.code()), s.message())
        })? {
            if file.received() + chunk.data.len() as u64 > dataset.size_bytes {
                bail!("more than the {} bytes announced", dataset.size_bytes);
            }
            file.write(&chunk.data).await?;
        }
        let received = file.received();
        let sha256 = file.finish().await?;
        if sha256 != dataset.sha256 {
            bail!(
                "the download's SHA-256 is {sha256}, expected {}",
                dataset.sha256
            );
        }
        tokio::fs::rename(&partial, &path).await?;
        Ok(received)
    }
    .await;
    match result {
        Ok(bytes) => {
            tracing::info!(dataset = %dataset_id, file = index, bytes, ms = started.elapsed().as_millis() as u64, "dataset file downloaded");
            Ok(path)
        }
        Err(e) => {
            let _ = tokio::fs::remove_file(&partial).await;
            Err(e)
        }
    }
}

/// Hands the frame in, retrying through connection losses until its lease would have expired.
async fn complete_frame(client: &mut Client, task: &FrameTask, frame: RenderedFrame) -> TaskEnd {
    let give_up = tokio::time::Instant::now() + task.lease_timeout;
    let mut backoff = Backoff::calls();
    loop {
        let result = pb::CompleteFrameRequest {
            part: Some(pb::complete_frame_request::Part::Result(pb::FrameResult {
                lease_id: task.lease.id.clone(),
                png_size_bytes: frame.png.len() as u64,
                timings: timings_message(&frame.outcome.timings),
                dataset_cache_hit: frame.outcome.dataset_cache_hit,
                cut: frame.outcome.cut.as_ref().map(frame_cut_message),
                preview: frame.outcome.preview.is_some(),
                completeness: frame.outcome.preview.unwrap_or(0.0),
            })),
        };
        let chunks: Vec<pb::CompleteFrameRequest> = frame
            .png
            .chunks(CHUNK_BYTES)
            .map(|c| pb::CompleteFrameRequest {
                part: Some(pb::complete_frame_request::Part::Png(c.to_vec())),
            })
            .collect();
        let messages = tokio_stream::iter(std::iter::once(result).chain(chunks));
        match client.complete_frame(messages).await {
            Ok(_) => {
                tracing::info!(bytes = frame.png.len(), "frame handed in");
                return TaskEnd::Finished;
            }
            Err(status) if daemon_cannot_store(&status) => {
                // The daemon gave the frame back to its queue; it is rendered again later.
                tracing::warn!(
                    message = status.message(),
                    "the daemon could not store the frame; waiting before the next one"
                );
                return TaskEnd::DaemonCannotStore;
            }
            Err(status) if is_transient(&status) && tokio::time::Instant::now() < give_up => {
                let wait = backoff.next();
                tracing::warn!(code = ?status.code(), message = status.message(), ?wait, "handing the frame in failed; retrying");
                tokio::time::sleep(wait).await;
            }
            Err(status) => {
                tracing::warn!(
                    code = ?status.code(),
                    message = status.message(),
                    "the daemon did not take the frame; it is dropped"
                );
                return TaskEnd::Finished;
            }
        }
    }
}

async fn release_frame(client: &mut Client, lease_id: &str) {
    let request = pb::ReleaseFrameRequest {
        lease_id: lease_id.to_string(),
    };
    match client.release_frame(request).await {
        Ok(_) => tracing::info!(lease = lease_id, "frame handed back unrendered"),
        Err(status) => {
            tracing::warn!(code = ?status.code(), message = status.message(), "handing the frame back failed; the lease will expire")
        }
    }
}

/// What a panicked render thread said.
fn panic_message(error: tokio::task::JoinError) -> String {
    if !error.is_panic() {
        return error.to_string();
    }
    let payload = error.into_panic();
    payload
        .downcast_ref::<&str>()
        .map(|s| s.to_string())
        .or_else(|| payload.downcast_ref::<String>().cloned())
        .unwrap_or_else(|| "no message".into())
}

/// Reports a failed frame; the daemon may answer that it cannot store even that.
async fn fail_frame(client: &mut Client, lease_id: &str, failure: &FrameFailure) -> TaskEnd {
    let request = pb::FailFrameRequest {
        lease_id: lease_id.to_string(),
        reason: failure.reason.clone(),
        kind: pb::FailureKind::from(failure.kind) as i32,
    };
    match client.fail_frame(request).await {
        Ok(_) => TaskEnd::Finished,
        Err(status) if daemon_cannot_store(&status) => {
            tracing::warn!(
                message = status.message(),
                "the daemon could not record the failure; waiting before the next frame"
            );
            TaskEnd::DaemonCannotStore
        }
        Err(status) => {
            tracing::warn!(code = ?status.code(), message = status.message(), "reporting the failure failed; the lease will expire");
            TaskEnd::Finished
        }
    }
}

//! The daemon's domain layer: datasets and jobs, validated and stored, with events for
//! watchers. The gRPC layer only converts and calls these methods.

use std::path::{Path, PathBuf};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};

use pointfarm_render::ingest::{open_dataset_file, Symlinks};
use pointfarm_render::remote::{AllowedPrefixes, ObjectUrl, RemoteClient, RemoteSettings};
use sha2::{Digest, Sha256};
use tokio::sync::broadcast;

use crate::dataset_files::DatasetFolders;
use crate::error::{DaemonError, StateError};
use crate::limits::{check_id, check_length, MAX_REQUEST_ID_BYTES};
use crate::metrics::DaemonMetrics;
use crate::model::{now_unix_ms, FrameReport, Job, JobEvent, JobSpec, JobState};
use crate::state::{Page, StateDb};
use crate::stores::{DatasetStores, StoreBuildGate, StorePublisher};
use crate::webhooks::{WebhookEndpoint, Webhooks};
use crate::worker_presence::WorkerPresence;

/// The default bound of one upload.
pub const DEFAULT_MAX_UPLOAD_BYTES: u64 = 16 << 30;
/// Most frames in one job, unless configured otherwise.
pub const DEFAULT_MAX_FRAMES: u32 = 100_000;
/// The size bound of a worker's dataset cache, unless configured otherwise.
pub const DEFAULT_WORKER_CACHE_BYTES: u64 = 8 << 30;
/// The largest image side a daemon accepts unless configured otherwise.
pub const DEFAULT_MAX_IMAGE_SIDE: u32 = 8192;
/// Attempts at a frame before its job fails, unless configured otherwise.
pub const DEFAULT_MAX_FRAME_ATTEMPTS: u32 = 3;
/// How long a lease lasts without a heartbeat, unless configured otherwise.
pub const DEFAULT_LEASE_TIMEOUT: std::time::Duration = std::time::Duration::from_secs(30);
/// How often the retention rules are applied, unless configured otherwise.
pub const DEFAULT_RETENTION_SWEEP_PERIOD: std::time::Duration = std::time::Duration::from_secs(60);

/// The longest a read of a dataset by URL may take (a registration's HEAD and header), well
/// within the bound of a blocking call, so that a stalled server is told as such.
pub const REMOTE_OPERATION_DEADLINE: std::time::Duration = std::time::Duration::from_secs(45);

/// Limits and locations of a daemon.
/// Frames of one job a worker may fail before it gets no more of them, as Flamenco's and
/// Deadline's blocklists have it.
pub const DEFAULT_WORKER_FAILURES_BEFORE_BLOCKLIST: u32 = 3;

#[derive(Debug, Clone)]
pub struct DaemonConfig {
    /// State database, uploaded datasets and rendered frames live here.
    pub data_dir: PathBuf,
    /// Server-side files may only be registered from below these folders.
    pub data_roots: Vec<PathBuf>,
    /// The URL prefixes datasets may be registered from (`s3://`, `http(s)://`); empty, no
    /// dataset by URL is accepted.
    pub allowed_url_prefixes: AllowedPrefixes,
    /// The object-storage prefixes jobs may write their outputs under (`outputs`); empty,
    /// no job may name an output URL.
    pub allowed_output_prefixes: AllowedPrefixes,
    /// Timeouts and retries of the reads of datasets by URL.
    pub remote_settings: RemoteSettings,
    /// Largest image side accepted, in pixels.
    pub max_image_side: u32,
    /// Most frames in one job.
    pub max_frames: u32,
    /// Largest upload, in bytes.
    pub max_upload_bytes: u64,
    /// Most bytes all uploaded datasets may take together (none: only the disk bounds them).
    pub upload_quota_bytes: Option<u64>,
    /// Attempts per frame before its job fails.
    pub max_frame_attempts: u32,
    /// Frames of one job a worker may fail before it is leased no more of them (the job's
    /// blocklist); 0 keeps no blocklist.
    pub worker_failures_before_blocklist: u32,
    /// A remote worker's lease on a frame ends unless renewed within this time.
    pub lease_timeout: std::time::Duration,
    /// Size bound of the worker's processed-dataset cache.
    pub worker_cache_bytes: u64,
    /// Host memory a build of a dataset's level-of-detail store may hold (one build at a
    /// time; stores are kept in `data_dir/lod`).
    pub store_build_memory_bytes: u64,
    /// Start on a damaged state database with what can be read, saying what was lost,
    /// rather than refusing to start.
    pub recover_state: bool,
    /// Job events buffered for watchers; one that falls further behind catches up from the
    /// store instead.
    pub event_buffer: usize,
    /// Held closed, store builds wait until it opens (tests look at a build under way).
    pub store_build_gate: Option<StoreBuildGate>,
    /// Held closed, a finished build waits until it opens before its store is ready, its
    /// nodes all stored (tests look at previews redrawn while a build is under way).
    pub store_ready_gate: Option<StoreBuildGate>,
    /// The endpoints told of every job's end, checked and with their secrets read.
    pub webhooks: Vec<WebhookEndpoint>,
    /// Jobs that ended longer ago than this are removed with their frames (`retention`);
    /// none are when None.
    pub job_retention: Option<std::time::Duration>,
    /// While the stored frames take more bytes than this, the jobs that ended first are
    /// removed with theirs (`retention`); no bound when None.
    pub frame_quota_bytes: Option<u64>,
    /// How often the retention rules are applied.
    pub retention_sweep_period: std::time::Duration,
    /// Where ready level-of-detail stores are published for workers to read (`--store-url`,
    /// checked by `stores::store_url`); none keeps every store's nodes served by the daemon.
    pub store_url: Option<ObjectUrl>,
    /// Tries at publishing one store before it waits for a frame of it to be leased again
    /// (`--store-publish-attempts`, 1 to `stores::MAX_PUBLISH_ATTEMPTS`).
    pub store_publish_attempts: u32,
}

impl DaemonConfig {
    pub fn new(data_dir: PathBuf) -> Self {
        Self {
            data_roots: Vec::new(),
            allowed_url_prefixes: AllowedPrefixes::default(),
            allowed_output_prefixes: AllowedPrefixes::default(),
            remote_settings: RemoteSettings {
                operation_deadline: REMOTE_OPERATION_DEADLINE,
                ..RemoteSettings::default()
            },
            max_image_side: DEFAULT_MAX_IMAGE_SIDE,
            max_frames: DEFAULT_MAX_FRAMES,
            max_upload_bytes: DEFAULT_MAX_UPLOAD_BYTES,
            upload_quota_bytes: None,
            max_frame_attempts: DEFAULT_MAX_FRAME_ATTEMPTS,
            lease_timeout: DEFAULT_LEASE_TIMEOUT,
            worker_cache_bytes: DEFAULT_WORKER_CACHE_BYTES,
            worker_failures_before_blocklist: DEFAULT_WORKER_FAILURES_BEFORE_BLOCKLIST,
            store_build_memory_bytes: pointfarm_render::cut::DEFAULT_MEMORY_BUDGET_BYTES,
            event_buffer: 1024,
            recover_state: false,
            store_build_gate: None,
            store_ready_gate: None,
            webhooks: Vec::new(),
            job_retention: None,
            frame_quota_bytes: None,
            retention_sweep_period: DEFAULT_RETENTION_SWEEP_PERIOD,
            store_url: None,
            store_publish_attempts: crate::stores::DEFAULT_PUBLISH_ATTEMPTS,
            data_dir,
        }
    }

    pub fn frames_dir(&self, job_id: &str) -> PathBuf {
        self.data_dir.join("jobs").join(job_id)
    }

    pub fn frame_path(&self, job_id: &str, index: u32) -> PathBuf {
        self.frames_dir(job_id)
            .join(format!("frame_{index:05}.png"))
    }

    pub fn worker_cache_dir(&self) -> PathBuf {
        self.data_dir.join("worker-cache.sled")
    }

    pub(crate) fn uploads_dir(&self) -> PathBuf {
        self.data_dir.join("datasets")
    }
}

/// Wakes the workers when there may be new work: embedded threads wait on the condition
/// variable, long-polling lease requests on the watch channel.
pub struct WorkSignal {
    pending: Mutex<bool>,
    condvar: Condvar,
    generation: tokio::sync::watch::Sender<u64>,
}

impl Default for WorkSignal {
    fn default() -> Self {
        Self {
            pending: Mutex::new(false),
            condvar: Condvar::new(),
            generation: tokio::sync::watch::Sender::new(0),
        }
    }
}

impl WorkSignal {
    pub fn notify(&self) {
        self.generation.send_modify(|g| *g = g.wrapping_add(1));
        if let Ok(mut pending) = self.pending.lock() {
            *pending = true;
            self.condvar.notify_all();
        }
    }

    /// Waits until notified or `timeout` passes.
    pub fn wait(&self, timeout: std::time::Duration) {
        if let Ok(mut pending) = self.pending.lock() {
            if !*pending {
                if let Ok((guard, _)) = self.condvar.wait_timeout(pending, timeout) {
                    pending = guard;
                } else {
                    return;
                }
            }
            *pending = false;
        }
    }

    /// Changes on every notification, for async waiters.
    pub fn subscribe(&self) -> tokio::sync::watch::Receiver<u64> {
        self.generation.subscribe()
    }
}

/// The state and behaviour of one daemon, shared by the gRPC handlers and the workers.
pub struct Daemon {
    pub config: DaemonConfig,
    pub state: StateDb,
    events: broadcast::Sender<JobEvent>,
    pub work: Arc<WorkSignal>,
    /// Held while leases, frame states and job states change together (see `lease`).
    pub(crate) scheduling: Mutex<()>,
    stopping: std::sync::atomic::AtomicBool,
    /// Which workers can render now, for health checking.
    pub workers: WorkerPresence,
    /// The datasets' level-of-detail stores, whose nodes workers read.
    pub stores: DatasetStores,
    /// The counters and histograms of what happens here, for Prometheus.
    pub metrics: DaemonMetrics,
    /// Reads datasets by URL; none while no URL prefix is allowed.
    pub(crate) remote: Option<RemoteClient>,
    /// Tells the configured endpoints that a job ended.
    webhooks: Webhooks,
    /// Writes jobs' outputs to their output URLs.
    pub(crate) outputs: crate::output_queue::OutputUploads,
}

impl Daemon {
    /// Opens (or creates) the state in `config.data_dir`; jobs that were running when the
    /// daemon stopped go back to the queue, and the frames its embedded worker held count a
    /// failed attempt.
    pub fn open(config: DaemonConfig) -> Result<Arc<Self>, DaemonError> {
        std::fs::create_dir_all(config.uploads_dir())?;
        std::fs::create_dir_all(config.data_dir.join("jobs"))?;
        remove_unfinished_uploads(&config.uploads_dir());
        let (state, loss) =
            StateDb::open(&config.data_dir.join("state.sled"), config.recover_state)?;
        if !loss.is_empty() {
            tracing::warn!(%loss, "started on a damaged state database with what it still holds");
        }
        check_frames_have_jobs(&state, &config.data_dir.join("jobs"), config.recover_state)?;
        let requeued = state.requeue_running()?;
        if requeued > 0 {
            tracing::info!(requeued, "resuming jobs that were running");
        }
        remove_partial_frames(&config.data_dir.join("jobs"));
        // Stores built before stores listed their files are listed, so datasets near them grow.
        match state.datasets() {
            Ok(datasets) => {
                crate::stores::list_unlisted_stores(&config.data_dir.join("lod"), &datasets)
            }
            Err(error) => {
                tracing::warn!(%error, "reading the datasets to list their stores' files")
            }
        }
        let remote = match config.allowed_url_prefixes.prefixes() {
            [] => None,
            prefixes => {
                let shown: Vec<&str> = prefixes.iter().map(|prefix| prefix.as_str()).collect();
                tracing::info!(prefixes = %shown.join(", "), "datasets by URL are allowed");
                Some(RemoteClient::within(
                    config.remote_settings.clone(),
                    config.allowed_url_prefixes.clone(),
                )?)
            }
        };
        let (events, _) = broadcast::channel(config.event_buffer.max(1));
        let work = Arc::new(WorkSignal::default());
        let built = Arc::clone(&work);
        let publisher = config
            .store_url
            .clone()
            .map(|url| {
                let records = config.data_dir.join("published-stores");
                StorePublisher::start(
                    url,
                    config.remote_settings.clone(),
                    config.store_publish_attempts,
                    &records,
                )
            })
            .transpose()?;
        let stores =
            DatasetStores::new(config.data_dir.join("lod"), config.store_build_memory_bytes)
                .gated(config.store_build_gate.clone())
                .held_before_ready(config.store_ready_gate.clone())
                .reading_within(DatasetFolders::new(
                    config.data_roots.clone(),
                    config.uploads_dir(),
                ))
                // Frames that wait for the store are leased again: previews for a redraw when
                // the build's version moves, every frame for its final render when it ends.
                .notifying(Arc::new(move || built.notify()))
                .publishing(publisher)
                .reading_urls(remote.clone());
        let metrics = DaemonMetrics::new();
        let webhooks = Webhooks::start(&config.webhooks, metrics.webhook_counters())?;
        let daemon = Arc::new(Self {
            config,
            stores,
            state,
            events,
            work,
            scheduling: Mutex::new(()),
            stopping: std::sync::atomic::AtomicBool::new(false),
            workers: WorkerPresence::default(),
            metrics,
            remote,
            webhooks,
            outputs: Default::default(),
        });
        daemon.start_output_uploads()?;
        daemon.count_leases_of_previous_run()?;
        daemon.fail_broken_chains()?;
        // Before the builds resume: a whole store grows from its recorded part.
        daemon.keep_store_parts();
        // Store builds a stopped daemon left go on now for the jobs that wait for them.
        let waiting = daemon
            .state
            .datasets()?
            .into_iter()
            .filter(|dataset| matches!(daemon.state.dataset_in_use(&dataset.id), Ok(true)));
        daemon.stores.resume_builds(waiting);
        Ok(daemon)
    }

    /// Taken while leases, frame states and job states change together.
    pub(crate) fn scheduling(&self) -> Result<MutexGuard<'_, ()>, DaemonError> {
        self.scheduling
            .lock()
            .map_err(|_| DaemonError::Internal("the scheduling lock is poisoned".into()))
    }

    /// The server is stopping: waiting lease requests answer without work.
    pub fn begin_shutdown(&self) {
        self.stopping
            .store(true, std::sync::atomic::Ordering::SeqCst);
        self.work.notify();
    }

    pub fn is_stopping(&self) -> bool {
        self.stopping.load(std::sync::atomic::Ordering::SeqCst)
    }

    pub fn subscribe(&self) -> broadcast::Receiver<JobEvent> {
        self.events.subscribe()
    }

    pub fn publish(&self, job: &Job, frame: Option<FrameReport>) {
        // No watcher is not an error.
        let _ = self.events.send(JobEvent {
            job: job.clone(),
            frame,
        });
    }

    // ------------------------------------------------------------------ jobs

    /// Validates limits that depend on this server and the jobs it runs after, stores the job
    /// and wakes a worker; a job after one that has already failed or been cancelled is
    /// stored failed, as it would have been had it been waiting then.
    pub fn submit_job(&self, mut spec: JobSpec) -> Result<Job, DaemonError> {
        check_length("request_id", &spec.request_id, MAX_REQUEST_ID_BYTES)?;
        let side = self.config.max_image_side;
        let (width, height) = (spec.request.width, spec.request.height);
        if width > side || height > side {
            return Err(DaemonError::invalid(
                if width > side { "width" } else { "height" },
                format!("{width}x{height} exceeds this server's maximum of {side} pixels per side"),
            ));
        }
        if spec.request.frames() > self.config.max_frames {
            return Err(DaemonError::invalid(
                "camera_path",
                format!("more than {} frames", self.config.max_frames),
            ));
        }
        self.dataset(&spec.dataset_id)?;
        self.check_job_output(&spec)?;
        spec.after = self.checked_after(&spec.after)?;
        // A chained job is stored under the scheduling lock, which every job's end holds, so a
        // job it runs after cannot end unseen between the check of its chain and its storing.
        let _scheduling = (!spec.after.is_empty())
            .then(|| self.scheduling())
            .transpose()?;
        let (job, created) = self.state.submit_job(spec)?;
        if created {
            tracing::info!(job = %job.id, frames = job.frames_total, "job submitted");
            self.publish(&job, None);
            self.fail_if_chain_broken_locked(&job)?;
            self.work.notify();
        }
        // What a job after one that already failed became: failed.
        self.job(&job.id)
    }

    pub fn job(&self, id: &str) -> Result<Job, DaemonError> {
        lookup("id", "job", id, |id| self.state.job(id))
    }

    /// A job and the reports of its finished frames, as a crash would leave them: read under
    /// the scheduling lock, which every change of a frame's state holds until it is flushed,
    /// so a frame reported done here is never rendered again after a restart.
    pub fn job_with_frames(&self, id: &str) -> Result<(Job, Vec<FrameReport>), DaemonError> {
        let _scheduling = self.scheduling()?;
        let job = self.job(id)?;
        let frames = self.state.frame_reports(id)?;
        Ok((job, frames))
    }

    pub fn list_jobs(
        &self,
        state: Option<JobState>,
        page_size: u32,
        token: &str,
    ) -> Result<Page<Job>, DaemonError> {
        Ok(self.state.list_jobs(state, page_size as usize, token)?)
    }

    /// Logs that `job` ended, once, with its counts, queues the event for the webhooks and
    /// settles the jobs that run after it (`chains`); called under the scheduling lock.
    /// `unstored_attempts` failed attempts ended it before they were stored at its frame.
    pub(crate) fn log_job_end(&self, job: &Job, unstored_attempts: u32) {
        self.tell_stores_job_moved(job);
        let failed_attempts = self
            .state
            .failed_attempts(&job.id)
            .map(|stored| stored + u64::from(unstored_attempts));
        self.webhooks
            .job_ended(job, failed_attempts.as_ref().ok().copied());
        let failed_attempts = match failed_attempts {
            Ok(n) => n.to_string(),
            Err(e) => format!("unknown ({e})"),
        };
        let elapsed_s = job.updated_unix_ms.saturating_sub(job.created_unix_ms) as f64 / 1000.0;
        let (id, frames_done, frames_total) = (&job.id, job.frames_done, job.frames_total);
        match job.state {
            JobState::Succeeded => tracing::info!(
                job = %id, frames_done, frames_total, %failed_attempts, elapsed_s,
                "job succeeded"
            ),
            JobState::Failed => tracing::info!(
                job = %id, frames_done, frames_total, %failed_attempts, elapsed_s,
                error = job.error.as_deref().unwrap_or_default(),
                "job failed"
            ),
            JobState::Cancelled => tracing::info!(
                job = %id, frames_done, frames_total, %failed_attempts, elapsed_s,
                "job cancelled"
            ),
            JobState::Queued | JobState::Running | JobState::Paused => {}
        }
        if let Err(e) = self.end_chain_locked(job) {
            // The next start fails what is left of the chain (`fail_broken_chains`).
            tracing::warn!(job = %job.id, error = %e, "could not settle the jobs after it");
        }
    }
}

/// The `what` that `id` (the request's `field`) names, found by `find`: an id too long to be
/// one of ours, or no such record, is an error.
pub(crate) fn lookup<T>(
    field: &str,
    what: &str,
    id: &str,
    find: impl FnOnce(&str) -> Result<Option<T>, StateError>,
) -> Result<T, DaemonError> {
    check_id(field, id)?;
    find(id)?.ok_or_else(|| DaemonError::NotFound(format!("{what} {id}")))
}

/// Every folder of rendered frames belongs to a stored job: one that does not is the trace of
/// a job the state database lost (with or without a manifest to tell it).
fn check_frames_have_jobs(
    state: &StateDb,
    jobs_dir: &Path,
    recover: bool,
) -> Result<(), DaemonError> {
    let Ok(entries) = std::fs::read_dir(jobs_dir) else {
        return Ok(());
    };
    let mut orphaned = Vec::new();
    for entry in entries.flatten() {
        let id = entry.file_name().to_string_lossy().into_owned();
        if entry.path().is_dir() && state.job(&id)?.is_none() {
            orphaned.push(id);
        }
    }
    if orphaned.is_empty() {
        return Ok(());
    }
    orphaned.sort();
    let shown = orphaned
        .iter()
        .take(10)
        .cloned()
        .collect::<Vec<_>>()
        .join(", ");
    let more = if orphaned.len() > 10 { ", ..." } else { "" };
    let message = format!(
        "the state database has lost {} jobs whose frames are in {}: {shown}{more}",
        orphaned.len(),
        jobs_dir.display(),
    );
    if !recover {
        return Err(DaemonError::FailedPrecondition(format!(
            "{message}; start with --recover-state to go on without them"
        )));
    }
    tracing::warn!("{message}");
    Ok(())
}

/// Uploads that were still arriving when the daemon stopped can never complete: remove them.
fn remove_unfinished_uploads(dir: &Path) {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for entry in entries.flatten() {
        let path = entry.path();
        if path.extension().is_some_and(|e| e == "part") {
            tracing::info!(file = %path.display(), "removing an unfinished upload");
            let _ = std::fs::remove_file(path);
        }
    }
}

/// Removes the partial frames of leases that can never complete (after a restart): `lease`
/// writes each handed-in frame under a `.part` name before renaming it into place.
fn remove_partial_frames(dir: &Path) {
    let Ok(jobs) = std::fs::read_dir(dir) else {
        return;
    };
    for job in jobs.flatten() {
        let Ok(frames) = std::fs::read_dir(job.path()) else {
            continue;
        };
        for frame in frames.flatten() {
            let path = frame.path();
            if path.extension().is_some_and(|e| e == "part") {
                let _ = std::fs::remove_file(path);
            }
        }
    }
}

/// A suffix for temporary file names: unique within the process, and across restarts.
pub(crate) fn unique_suffix() -> String {
    static COUNTER: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
    let n = COUNTER.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    format!("{}-{}-{n}", now_unix_ms(), std::process::id())
}

pub use crate::model::dataset_id;

/// [`hash_file`] of each of `paths`, in order, several files at once (a campaign's files
/// hash in parallel; each is read once, sequentially). `done` is told each file's size as
/// it is hashed. On threads of their own, so a store build busy on rayon's pool does not
/// hold a registration up.
pub fn hash_files(
    paths: &[PathBuf],
    done: &(dyn Fn(u64) + Sync),
) -> Vec<std::io::Result<(String, u64)>> {
    hash_files_opened_by(
        paths,
        &|path| open_dataset_file(path, Symlinks::Follow),
        done,
    )
}

/// [`hash_files`], each file opened by `open`.
pub(crate) fn hash_files_opened_by(
    paths: &[PathBuf],
    open: &(dyn Fn(&Path) -> std::io::Result<std::fs::File> + Sync),
    done: &(dyn Fn(u64) + Sync),
) -> Vec<std::io::Result<(String, u64)>> {
    use std::sync::atomic::{AtomicUsize, Ordering};
    let threads = std::thread::available_parallelism()
        .map_or(1, |n| n.get())
        .min(paths.len());
    let next = AtomicUsize::new(0);
    let mut hashed: Vec<_> = std::thread::scope(|scope| {
        let workers: Vec<_> = (0..threads)
            .map(|_| {
                scope.spawn(|| {
                    let mut mine = Vec::new();
                    loop {
                        let index = next.fetch_add(1, Ordering::Relaxed);
                        let Some(path) = paths.get(index) else {
                            return mine;
                        };
                        let result = open(path).and_then(hash_opened);
                        if let Ok((_, size)) = &result {
                            done(*size);
                        }
                        mine.push((index, result));
                    }
                })
            })
            .collect();
        workers
            .into_iter()
            .flat_map(|worker| worker.join().unwrap_or_default())
            .collect()
    });
    hashed.sort_by_key(|(index, _)| *index);
    hashed.into_iter().map(|(_, result)| result).collect()
}

/// The SHA-256 (hex) and size of the file at `path`, read in a stream; only a regular file is
/// opened ([`open_dataset_file`]).
pub fn hash_file(path: &Path) -> std::io::Result<(String, u64)> {
    hash_opened(open_dataset_file(path, Symlinks::Follow)?)
}

fn hash_opened(mut file: std::fs::File) -> std::io::Result<(String, u64)> {
    let mut hasher = Sha256::new();
    let size = std::io::copy(&mut file, &mut hasher)?;
    Ok((crate::model::hex(&hasher.finalize()), size))
}

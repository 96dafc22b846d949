//! The service under load: real `pointfarm serve` processes on loopback, driven through the
//! gRPC API as clients and workers drive them. No figure here is the renderer's: they are the
//! daemon's and its transport's.
//!
//! A run of one daemon binary has two phases, each against a daemon of its own (a fresh data
//! folder, a free loopback port, the generated dataset registered from a data root):
//!
//! - **load**: the daemon with its embedded worker. Once the worker is connected, `clients`
//!   tasks, each with a connection of its own, submit `jobs` turntables of `frames_per_job`
//!   frames (a job's `SubmitJob` timed), then poll their jobs with `GetJob` (each call timed)
//!   until every one has succeeded. Frames a second over the whole run, from the first
//!   submission to the last job seen finished.
//! - **lease**: the daemon without a worker. A few jobs are queued; the benchmark, as a
//!   worker, leases a frame (`LeaseFrame`, each call that carries a task timed) and hands it
//!   back (`ReleaseFrame`, which counts no attempt), `leases` times after a few unmeasured.
//!
//! Several daemon binaries (a build before a change and one after) are run alternately,
//! `runs` times each, from the same load generator, so that the machine's drifts reach each
//! alike; the first binary is the baseline of the summary's ratios. Each daemon is stopped
//! with SIGTERM (killed when it has not exited within 20 s), also when a phase fails, and the
//! scratch folder is removed.

use std::fs::File;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use pb::dataset_service_client::DatasetServiceClient;
use pb::job_service_client::JobServiceClient;
use pb::worker_service_client::WorkerServiceClient;
use pointfarm_daemon::model::JobSpec;
use pointfarm_proto::endpoint::ServerEndpoint;
use pointfarm_proto::v1 as pb;
use pointfarm_render::ingest::{write_las, LasWriteOptions};
use pointfarm_render::request::{CameraPath, Lens, RenderOptions, RenderRequest, Turntable};
use serde::Serialize;
use tonic::transport::Channel;

use crate::clouds::uniform_cube;
use crate::json::{camel_case_keys, RunContext};
use crate::stats::{median, percentile};

/// Jobs submitted in the load phase.
pub const DEFAULT_JOBS: u32 = 200;
/// Frames of each job (a turntable).
pub const DEFAULT_FRAMES_PER_JOB: u32 = 2;
/// Client tasks submitting and polling, each with a connection of its own.
pub const DEFAULT_CLIENTS: u32 = 20;
/// Measured leases of the lease phase.
pub const DEFAULT_LEASES: u32 = 200;
/// The frames' size: small, so that the renderer weighs little against the service.
pub const DEFAULT_SIZE: (u32, u32) = (64, 48);
/// Points of the generated dataset (a uniform cube, written as LAS).
pub const DATASET_POINTS: usize = 20_000;

/// Jobs queued for the lease phase, whose frames are leased and handed back in turn.
const LEASE_PHASE_JOBS: usize = 4;
/// Leases before the measured ones (the connection's first calls).
const WARM_LEASES: usize = 3;
/// The pause of a client between two passes over its unfinished jobs.
const POLL_INTERVAL: Duration = Duration::from_millis(10);
/// How long a daemon may take to listen, and its embedded worker to connect.
const START_TIMEOUT: Duration = Duration::from_secs(120);
/// How long a daemon may take to exit after SIGTERM before it is killed.
const STOP_TIMEOUT: Duration = Duration::from_secs(20);
/// The longest a phase may take.
const PHASE_TIMEOUT: Duration = Duration::from_secs(900);
/// The name the benchmark leases frames under.
const WORKER_NAME: &str = "pointfarm-bench";

/// What to run.
#[derive(Debug, Clone)]
pub struct ServiceLoadOptions {
    /// The `pointfarm` binaries whose `serve` is measured, in turn; the first is the baseline.
    pub daemon_binaries: Vec<PathBuf>,
    /// Runs of each binary.
    pub runs: u32,
    pub jobs: u32,
    pub frames_per_job: u32,
    pub clients: u32,
    pub leases: u32,
    pub width: u32,
    pub height: u32,
    /// The embedded worker's `--adapter` (auto, hardware, software).
    pub adapter: String,
}

impl ServiceLoadOptions {
    /// The defaults, with `daemon_binary` alone run once.
    pub fn new(daemon_binary: PathBuf) -> Self {
        Self {
            daemon_binaries: vec![daemon_binary],
            runs: 1,
            jobs: DEFAULT_JOBS,
            frames_per_job: DEFAULT_FRAMES_PER_JOB,
            clients: DEFAULT_CLIENTS,
            leases: DEFAULT_LEASES,
            width: DEFAULT_SIZE.0,
            height: DEFAULT_SIZE.1,
            adapter: "auto".into(),
        }
    }
}

/// Why a run failed.
#[derive(Debug, thiserror::Error)]
pub enum ServiceLoadError {
    #[error("the service benchmark: {0}")]
    Setup(String),
    /// A daemon failed to start, or a call to it failed; with the end of its log.
    #[error("the daemon {binary} ({phase} phase): {message}{log_tail}")]
    Daemon {
        binary: String,
        phase: &'static str,
        message: String,
        log_tail: String,
    },
    #[error("writing {}: {source}", path.display())]
    Write {
        path: PathBuf,
        source: std::io::Error,
    },
}

/// One run of one daemon binary: both phases.
#[derive(Debug, Clone, Serialize)]
pub struct ServiceLoadRun {
    /// The binary, as given.
    pub daemon: String,
    /// Its run, from 1.
    pub run: u32,
    /// The machine's 1-minute load average when the run started.
    pub load_average: Option<f64>,
    /// The embedded worker's adapter.
    pub adapter: String,
    pub jobs: u32,
    pub frames: u64,
    /// From the first submission to the last job seen finished.
    pub wall_s: f64,
    pub frames_per_s: f64,
    pub submit_median_ms: f64,
    pub submit_p95_ms: f64,
    pub get_job_calls: usize,
    pub get_job_median_ms: f64,
    pub leases: usize,
    /// `LeaseFrame` calls that carried a task.
    pub lease_median_ms: f64,
    pub lease_p95_ms: f64,
    pub release_median_ms: f64,
    /// Both daemons exited with success within 20 s of SIGTERM.
    pub stopped_cleanly: bool,
}

/// One binary's runs: the medians of their figures, and the ratios to the baseline's.
#[derive(Debug, Clone, Serialize)]
pub struct ServiceLoadSummary {
    pub daemon: String,
    pub runs: usize,
    pub frames_per_s: f64,
    pub submit_median_ms: f64,
    pub get_job_median_ms: f64,
    pub lease_median_ms: f64,
    /// Frames a second over the baseline's.
    pub frames_per_s_over_baseline: f64,
    /// The baseline's median over this binary's (above 1: faster).
    pub submit_speedup: f64,
    pub lease_speedup: f64,
}

/// The benchmark's figures.
#[derive(Debug, Clone, Serialize)]
pub struct ServiceLoadResult {
    pub jobs: u32,
    pub frames_per_job: u32,
    pub clients: u32,
    pub leases: u32,
    pub width: u32,
    pub height: u32,
    pub dataset_points: usize,
    /// In the order run: each binary in turn, round after round.
    pub runs: Vec<ServiceLoadRun>,
    /// One per binary, the baseline first.
    pub summaries: Vec<ServiceLoadSummary>,
}

/// Runs every binary `options.runs` times, alternately. Progress lines (the scratch folder
/// first) go to `progress`.
pub fn measure(
    options: &ServiceLoadOptions,
    progress: &mut dyn FnMut(&str),
) -> Result<ServiceLoadResult, ServiceLoadError> {
    check(options)?;
    let setup =
        |what: &str, e: &dyn std::fmt::Display| ServiceLoadError::Setup(format!("{what}: {e}"));
    // Declared first, dropped (removed) last: after every daemon writing into it has stopped.
    let scratch = tempfile::Builder::new()
        .prefix("pointfarm-service-load-")
        .tempdir()
        .map_err(|e| setup("a scratch folder", &e))?;
    progress(&format!("scratch: {}", scratch.path().display()));
    let roots = scratch.path().join("roots");
    std::fs::create_dir_all(&roots).map_err(|e| setup("the data root", &e))?;
    let cloud = uniform_cube(DATASET_POINTS, 11);
    write_las(
        &roots.join("cloud.las"),
        &cloud,
        &LasWriteOptions::default(),
    )
    .map_err(|e| setup("writing the dataset", &e))?;
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .map_err(|e| setup("the async runtime", &e))?;

    let mut runs = Vec::new();
    for run in 1..=options.runs {
        for (index, binary) in options.daemon_binaries.iter().enumerate() {
            progress(&format!(
                "run {run} of {}: {}",
                options.runs,
                binary.display()
            ));
            let dir = scratch.path().join(format!("run-{run}-{index}"));
            let measured = measure_run(&runtime, binary, &roots, &dir, options, run)?;
            progress(&format!(
                "  {:.1} frames/s, SubmitJob median {:.2} ms, LeaseFrame median {:.2} ms",
                measured.frames_per_s, measured.submit_median_ms, measured.lease_median_ms
            ));
            runs.push(measured);
        }
    }
    drop(runtime);
    scratch
        .close()
        .map_err(|e| setup("removing the scratch folder", &e))?;
    Ok(ServiceLoadResult {
        jobs: options.jobs,
        frames_per_job: options.frames_per_job,
        clients: options.clients,
        leases: options.leases,
        width: options.width,
        height: options.height,
        dataset_points: DATASET_POINTS,
        summaries: summarise(&options.daemon_binaries, &runs),
        runs,
    })
}

fn check(options: &ServiceLoadOptions) -> Result<(), ServiceLoadError> {
    let counts = [
        ("daemon binaries", options.daemon_binaries.len()),
        ("runs", options.runs as usize),
        ("jobs", options.jobs as usize),
        ("frames per job", options.frames_per_job as usize),
        ("clients", options.clients as usize),
        ("leases", options.leases as usize),
    ];
    if let Some((what, _)) = counts.iter().find(|(_, n)| *n == 0) {
        return Err(ServiceLoadError::Setup(format!(
            "at least one of {what} is needed"
        )));
    }
    Ok(())
}

/// Both phases of one binary, each against a daemon of its own in `dir`.
fn measure_run(
    runtime: &tokio::runtime::Runtime,
    binary: &Path,
    roots: &Path,
    dir: &Path,
    options: &ServiceLoadOptions,
    run: u32,
) -> Result<ServiceLoadRun, ServiceLoadError> {
    let load_average = load_average();

    let mut daemon = Daemon::start(binary, &dir.join("load"), roots, &options.adapter, true)?;
    let load = runtime
        .block_on(async {
            let endpoint = daemon.endpoint()?;
            let adapter = embedded_worker_adapter(&endpoint).await?;
            let dataset = register(&endpoint).await?;
            let figures = within_timeout(load_phase(&endpoint, &dataset, options)).await?;
            Ok::<_, String>((adapter, figures))
        })
        .map_err(|message| daemon.error("load", message));
    let load_stopped = daemon.stop();
    let (adapter, load) = load?;

    let mut daemon = Daemon::start(binary, &dir.join("lease"), roots, &options.adapter, false)?;
    let lease = runtime
        .block_on(async {
            let endpoint = daemon.endpoint()?;
            let dataset = register(&endpoint).await?;
            within_timeout(lease_phase(&endpoint, &dataset, options)).await
        })
        .map_err(|message| daemon.error("lease", message));
    let lease_stopped = daemon.stop();
    let lease = lease?;

    let wall_s = load.wall.as_secs_f64();
    Ok(ServiceLoadRun {
        daemon: binary.display().to_string(),
        run,
        load_average,
        adapter,
        jobs: options.jobs,
        frames: load.frames,
        wall_s,
        frames_per_s: load.frames as f64 / wall_s,
        submit_median_ms: median(load.submit_ms.clone()),
        submit_p95_ms: percentile(load.submit_ms, 0.95),
        get_job_calls: load.get_job_ms.len(),
        get_job_median_ms: median(load.get_job_ms),
        leases: lease.lease_ms.len(),
        lease_median_ms: median(lease.lease_ms.clone()),
        lease_p95_ms: percentile(lease.lease_ms, 0.95),
        release_median_ms: median(lease.release_ms),
        stopped_cleanly: load_stopped && lease_stopped,
    })
}

async fn within_timeout<T>(
    phase: impl std::future::Future<Output = Result<T, String>>,
) -> Result<T, String> {
    tokio::time::timeout(PHASE_TIMEOUT, phase)
        .await
        .map_err(|_| format!("the phase took longer than {} s", PHASE_TIMEOUT.as_secs()))?
}

/// A `pointfarm serve` child process; stopped when dropped.
struct Daemon {
    child: Child,
    binary: String,
    address: String,
    log: PathBuf,
    stopped: bool,
}

impl Daemon {
    /// Starts `binary serve` on a free loopback port with its data in `data_dir` and `roots`
    /// as its data root, and waits until it listens. Its settings are its flags alone: no
    /// `POINTFARM_*` variable (a token, a configuration file) reaches it.
    fn start(
        binary: &Path,
        data_dir: &Path,
        roots: &Path,
        adapter: &str,
        embedded_worker: bool,
    ) -> Result<Self, ServiceLoadError> {
        let name = binary.display().to_string();
        let failed = |message: String| ServiceLoadError::Daemon {
            binary: name.clone(),
            phase: if embedded_worker { "load" } else { "lease" },
            message,
            log_tail: String::new(),
        };
        let address = free_address().map_err(|e| failed(format!("no free port: {e}")))?;
        std::fs::create_dir_all(data_dir)
            .map_err(|e| failed(format!("creating {}: {e}", data_dir.display())))?;
        let log = data_dir.with_extension("log");
        let output = File::create(&log)
            .and_then(|out| Ok((out.try_clone()?, out)))
            .map_err(|e| failed(format!("creating {}: {e}", log.display())))?;
        let mut command = Command::new(binary);
        command
            .arg("serve")
            .arg("--listen")
            .arg(&address)
            .arg("--data-dir")
            .arg(data_dir)
            .arg("--data-root")
            .arg(roots)
            .arg("--adapter")
            .arg(adapter);
        if !embedded_worker {
            command.arg("--no-embedded-worker");
        }
        for (variable, _) in std::env::vars_os() {
            if variable.to_string_lossy().starts_with("POINTFARM_") {
                command.env_remove(variable);
            }
        }
        let child = command
            .env_remove("RUST_LOG")
            .stdin(Stdio::null())
            .stdout(output.0)
            .stderr(output.1)
            .spawn()
            .map_err(|e| failed(format!("starting it: {e}")))?;
        let mut daemon = Self {
            child,
            binary: name.clone(),
            address,
            log,
            stopped: false,
        };
        let phase = if embedded_worker { "load" } else { "lease" };
        let deadline = Instant::now() + START_TIMEOUT;
        loop {
            if let Ok(Some(status)) = daemon.child.try_wait() {
                daemon.stopped = true;
                return Err(daemon.error(phase, format!("exited ({status}) before listening")));
            }
            if std::net::TcpStream::connect(&daemon.address).is_ok() {
                return Ok(daemon);
            }
            if Instant::now() > deadline {
                return Err(daemon.error(
                    phase,
                    format!(
                        "not listening on {} after {} s",
                        daemon.address,
                        START_TIMEOUT.as_secs()
                    ),
                ));
            }
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    fn endpoint(&self) -> Result<ServerEndpoint, String> {
        ServerEndpoint::new(&self.address, None).map_err(|e| e.to_string())
    }

    /// `message` with the end of the daemon's log.
    fn error(&self, phase: &'static str, message: String) -> ServiceLoadError {
        let log = std::fs::read_to_string(&self.log).unwrap_or_default();
        let lines: Vec<&str> = log.lines().collect();
        let tail = lines[lines.len().saturating_sub(20)..].join("\n");
        ServiceLoadError::Daemon {
            binary: self.binary.clone(),
            phase,
            message,
            log_tail: if tail.is_empty() {
                String::new()
            } else {
                format!("\nthe end of its log ({}):\n{tail}", self.log.display())
            },
        }
    }

    /// SIGTERM, then a kill when it has not exited within [`STOP_TIMEOUT`]; whether it exited
    /// with success in time.
    fn stop(&mut self) -> bool {
        if std::mem::replace(&mut self.stopped, true) {
            return false;
        }
        if let Ok(Some(_)) = self.child.try_wait() {
            // It had ended by itself.
            return false;
        }
        let pid = rustix::process::Pid::from_child(&self.child);
        let _ = rustix::process::kill_process(pid, rustix::process::Signal::TERM);
        let deadline = Instant::now() + STOP_TIMEOUT;
        while Instant::now() < deadline {
            match self.child.try_wait() {
                Ok(Some(status)) => return status.success(),
                Ok(None) => std::thread::sleep(Duration::from_millis(20)),
                Err(_) => break,
            }
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
        false
    }
}

impl Drop for Daemon {
    fn drop(&mut self) {
        self.stop();
    }
}

/// `127.0.0.1:PORT` with a port that was free a moment ago.
fn free_address() -> std::io::Result<String> {
    let port = std::net::TcpListener::bind("127.0.0.1:0")?
        .local_addr()?
        .port();
    Ok(format!("127.0.0.1:{port}"))
}

/// The 1-minute load average, on Linux.
fn load_average() -> Option<f64> {
    std::fs::read_to_string("/proc/loadavg")
        .ok()?
        .split_whitespace()
        .next()?
        .parse()
        .ok()
}

async fn connect(endpoint: &ServerEndpoint) -> Result<Channel, String> {
    let endpoint = endpoint.endpoint().map_err(|e| e.to_string())?;
    endpoint
        .connect()
        .await
        .map_err(|e| format!("connecting: {e}"))
}

fn call_failed(call: &str) -> impl Fn(tonic::Status) -> String + '_ {
    move |status| format!("{call}: {}: {}", status.code(), status.message())
}

/// Waits until the embedded worker has connected; its adapter's name.
async fn embedded_worker_adapter(endpoint: &ServerEndpoint) -> Result<String, String> {
    let mut jobs = JobServiceClient::new(connect(endpoint).await?);
    let deadline = Instant::now() + START_TIMEOUT;
    loop {
        let workers = jobs
            .list_workers(pb::ListWorkersRequest {})
            .await
            .map_err(call_failed("ListWorkers"))?
            .into_inner()
            .workers;
        if let Some(worker) = workers.iter().find(|w| w.embedded) {
            let adapter = worker.capabilities.as_ref();
            return Ok(adapter.map_or_else(String::new, |c| c.adapter_name.clone()));
        }
        if Instant::now() > deadline {
            return Err(format!(
                "no embedded worker connected within {} s",
                START_TIMEOUT.as_secs()
            ));
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

/// Registers the generated dataset from the data root; its id.
async fn register(endpoint: &ServerEndpoint) -> Result<String, String> {
    let mut datasets = DatasetServiceClient::new(connect(endpoint).await?);
    let request = pb::RegisterDatasetRequest {
        path: "cloud.las".into(),
        name: "service-load".into(),
        paths: Vec::new(),
    };
    let dataset = datasets
        .register_dataset(request)
        .await
        .map_err(call_failed("RegisterDataset"))?;
    Ok(dataset.into_inner().id)
}

/// A turntable job as `pointfarm render --server` submits one: every render option spelled out.
fn job_request(
    request_id: String,
    dataset_id: &str,
    options: &ServiceLoadOptions,
) -> pb::SubmitJobRequest {
    let spec = JobSpec {
        request_id,
        dataset_id: dataset_id.into(),
        request: RenderRequest {
            width: options.width,
            height: options.height,
            camera_path: CameraPath::Turntable(Turntable::around_the_cloud(options.frames_per_job)),
            lens: Lens::default(),
            render: RenderOptions::default(),
        },
        priority: 0,
        requirements: Default::default(),
        preview: false,
    };
    pb::SubmitJobRequest::from(&spec)
}

fn ms_since(started: Instant) -> f64 {
    started.elapsed().as_secs_f64() * 1e3
}

/// What the load phase measured.
struct LoadFigures {
    frames: u64,
    wall: Duration,
    submit_ms: Vec<f64>,
    get_job_ms: Vec<f64>,
}

/// What one client measured.
struct ClientFigures {
    frames: u64,
    finished: Instant,
    submit_ms: Vec<f64>,
    get_job_ms: Vec<f64>,
}

async fn load_phase(
    endpoint: &ServerEndpoint,
    dataset_id: &str,
    options: &ServiceLoadOptions,
) -> Result<LoadFigures, String> {
    // Connected before the clock starts: a connection's set-up is not the service's work.
    let mut clients = Vec::new();
    for client in 0..options.clients.min(options.jobs) {
        let jobs: Vec<String> = (client..options.jobs)
            .step_by(options.clients as usize)
            .map(|job| format!("service-load-{job}"))
            .collect();
        clients.push((JobServiceClient::new(connect(endpoint).await?), jobs));
    }
    let started = Instant::now();
    let tasks: Vec<_> = clients
        .into_iter()
        .map(|(client, jobs)| {
            let requests = jobs
                .into_iter()
                .map(|id| job_request(id, dataset_id, options))
                .collect();
            tokio::spawn(client_load(client, requests))
        })
        .collect();
    let mut figures = LoadFigures {
        frames: 0,
        wall: Duration::ZERO,
        submit_ms: Vec::new(),
        get_job_ms: Vec::new(),
    };
    for task in tasks {
        let client = task.await.map_err(|e| format!("a client task: {e}"))??;
        figures.frames += client.frames;
        figures.wall = figures.wall.max(client.finished - started);
        figures.submit_ms.extend(client.submit_ms);
        figures.get_job_ms.extend(client.get_job_ms);
    }
    Ok(figures)
}

/// Submits `requests` one after another, then polls them until each has succeeded.
async fn client_load(
    mut jobs: JobServiceClient<Channel>,
    requests: Vec<pb::SubmitJobRequest>,
) -> Result<ClientFigures, String> {
    let mut submit_ms = Vec::with_capacity(requests.len());
    let mut unfinished = Vec::with_capacity(requests.len());
    for request in requests {
        let started = Instant::now();
        let job = jobs
            .submit_job(request)
            .await
            .map_err(call_failed("SubmitJob"))?;
        submit_ms.push(ms_since(started));
        unfinished.push(job.into_inner().id);
    }
    let (mut frames, mut finished) = (0, Instant::now());
    let mut get_job_ms = Vec::new();
    while !unfinished.is_empty() {
        let mut waiting = Vec::with_capacity(unfinished.len());
        for id in unfinished {
            let started = Instant::now();
            let job = jobs
                .get_job(pb::GetJobRequest { id: id.clone() })
                .await
                .map_err(call_failed("GetJob"))?
                .into_inner();
            get_job_ms.push(ms_since(started));
            match job.state() {
                pb::JobState::Succeeded => {
                    frames += u64::from(job.frames_done);
                    finished = Instant::now();
                }
                pb::JobState::Failed | pb::JobState::Cancelled => {
                    return Err(format!(
                        "job {id} ended {}: {}",
                        job.state().as_str_name(),
                        job.error
                    ))
                }
                _ => waiting.push(id),
            }
        }
        unfinished = waiting;
        if !unfinished.is_empty() {
            tokio::time::sleep(POLL_INTERVAL).await;
        }
    }
    Ok(ClientFigures {
        frames,
        finished,
        submit_ms,
        get_job_ms,
    })
}

/// What the lease phase measured.
struct LeaseFigures {
    lease_ms: Vec<f64>,
    release_ms: Vec<f64>,
}

/// The capabilities the benchmark leases with: a software adapter with no frame limit.
fn capabilities() -> pb::WorkerCapabilities {
    pb::WorkerCapabilities {
        adapter_kind: pb::AdapterKind::Software.into(),
        adapter_name: "pointfarm bench (renders nothing)".into(),
        ..Default::default()
    }
}

async fn lease_phase(
    endpoint: &ServerEndpoint,
    dataset_id: &str,
    options: &ServiceLoadOptions,
) -> Result<LeaseFigures, String> {
    let mut jobs = JobServiceClient::new(connect(endpoint).await?);
    for job in 0..LEASE_PHASE_JOBS {
        let request = job_request(format!("lease-{job}"), dataset_id, options);
        jobs.submit_job(request)
            .await
            .map_err(call_failed("SubmitJob"))?;
    }
    // A connection of its own, as a worker process has.
    let mut worker = WorkerServiceClient::new(connect(endpoint).await?);
    let request = pb::LeaseFrameRequest {
        worker_name: WORKER_NAME.into(),
        wait_ms: 0,
        capabilities: Some(capabilities()),
    };
    let mut figures = LeaseFigures {
        lease_ms: Vec::with_capacity(options.leases as usize),
        release_ms: Vec::with_capacity(options.leases as usize),
    };
    for lease in 0..WARM_LEASES + options.leases as usize {
        let started = Instant::now();
        let task = worker
            .lease_frame(request.clone())
            .await
            .map_err(call_failed("LeaseFrame"))?
            .into_inner()
            .task
            .ok_or("LeaseFrame: no frame to lease with frames queued")?;
        let lease_ms = ms_since(started);
        let started = Instant::now();
        worker
            .release_frame(pb::ReleaseFrameRequest {
                lease_id: task.lease_id,
            })
            .await
            .map_err(call_failed("ReleaseFrame"))?;
        if lease >= WARM_LEASES {
            figures.lease_ms.push(lease_ms);
            figures.release_ms.push(ms_since(started));
        }
    }
    Ok(figures)
}

/// Per binary, the medians of its runs' figures and their ratios to the first binary's.
fn summarise(binaries: &[PathBuf], runs: &[ServiceLoadRun]) -> Vec<ServiceLoadSummary> {
    let mut summaries: Vec<ServiceLoadSummary> = Vec::new();
    for binary in binaries {
        let name = binary.display().to_string();
        let own: Vec<&ServiceLoadRun> = runs.iter().filter(|r| r.daemon == name).collect();
        let of =
            |figure: fn(&ServiceLoadRun) -> f64| median(own.iter().map(|r| figure(r)).collect());
        let (frames_per_s, submit_median_ms, lease_median_ms) = (
            of(|r| r.frames_per_s),
            of(|r| r.submit_median_ms),
            of(|r| r.lease_median_ms),
        );
        let baseline = summaries.first();
        summaries.push(ServiceLoadSummary {
            runs: own.len(),
            frames_per_s,
            submit_median_ms,
            get_job_median_ms: of(|r| r.get_job_median_ms),
            lease_median_ms,
            frames_per_s_over_baseline: baseline.map_or(1.0, |b| frames_per_s / b.frames_per_s),
            submit_speedup: baseline.map_or(1.0, |b| b.submit_median_ms / submit_median_ms),
            lease_speedup: baseline.map_or(1.0, |b| b.lease_median_ms / lease_median_ms),
            daemon: name,
        });
    }
    summaries
}

/// The runs' table and, for more than one binary, the summary against the first.
pub fn markdown(result: &ServiceLoadResult) -> String {
    let mut md = format!(
        "{} jobs x {} frames at {}x{} from {} clients (a generated dataset of {} points); \
         {} leases handed back\n\n\
         | daemon | run | load | adapter | frames/s | SubmitJob median (ms) | p95 (ms) | \
         GetJob median (ms) | LeaseFrame median (ms) | p95 (ms) | ReleaseFrame median (ms) |\n\
         |---|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|\n",
        result.jobs,
        result.frames_per_job,
        result.width,
        result.height,
        result.clients,
        result.dataset_points,
        result.leases,
    );
    for r in &result.runs {
        let load = r
            .load_average
            .map_or_else(String::new, |l| format!("{l:.2}"));
        md.push_str(&format!(
            "| {} | {} | {load} | {} | {:.1} | {:.2} | {:.2} | {:.2} | {:.2} | {:.2} | {:.2} |\n",
            r.daemon,
            r.run,
            r.adapter,
            r.frames_per_s,
            r.submit_median_ms,
            r.submit_p95_ms,
            r.get_job_median_ms,
            r.lease_median_ms,
            r.lease_p95_ms,
            r.release_median_ms,
        ));
    }
    if result.summaries.len() > 1 {
        md.push_str(
            "\n| daemon | runs | frames/s | against the first | SubmitJob median (ms) | \
             speed-up | GetJob median (ms) | LeaseFrame median (ms) | speed-up |\n\
             |---|---:|---:|---:|---:|---:|---:|---:|---:|\n",
        );
        for s in &result.summaries {
            md.push_str(&format!(
                "| {} | {} | {:.1} | {:.2}x | {:.2} | {:.2}x | {:.2} | {:.2} | {:.2}x |\n",
                s.daemon,
                s.runs,
                s.frames_per_s,
                s.frames_per_s_over_baseline,
                s.submit_median_ms,
                s.submit_speedup,
                s.get_job_median_ms,
                s.lease_median_ms,
                s.lease_speedup,
            ));
        }
    }
    md
}

/// Writes the figures with the run's `context` as pretty-printed JSON (lowerCamelCase keys,
/// as every `--json` of the CLI) to `path`, as the file's `serviceLoad` section.
pub fn write_json(
    path: &Path,
    result: &ServiceLoadResult,
    context: &RunContext,
) -> Result<(), ServiceLoadError> {
    #[derive(Serialize)]
    struct ServiceLoadFile<'a> {
        command: &'a str,
        finished_unix_s: u64,
        wall_s: f64,
        cores: usize,
        service_load: &'a ServiceLoadResult,
    }
    let file = ServiceLoadFile {
        command: &context.command,
        finished_unix_s: std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_secs()),
        wall_s: context.started.elapsed().as_secs_f64(),
        cores: std::thread::available_parallelism().map_or(1, |n| n.get()),
        service_load: result,
    };
    let json = serde_json::to_value(&file)
        .map(camel_case_keys)
        .and_then(|value| serde_json::to_string_pretty(&value))
        .map_err(|e| ServiceLoadError::Setup(format!("the JSON: {e}")))?;
    std::fs::write(path, json + "\n").map_err(|source| ServiceLoadError::Write {
        path: path.to_path_buf(),
        source,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn run(daemon: &str, run: u32, frames_per_s: f64, submit: f64, lease: f64) -> ServiceLoadRun {
        ServiceLoadRun {
            daemon: daemon.into(),
            run,
            load_average: Some(1.5),
            adapter: "llvmpipe".into(),
            jobs: 4,
            frames: 8,
            wall_s: 8.0 / frames_per_s,
            frames_per_s,
            submit_median_ms: submit,
            submit_p95_ms: submit * 2.0,
            get_job_calls: 10,
            get_job_median_ms: submit,
            leases: 5,
            lease_median_ms: lease,
            lease_p95_ms: lease * 2.0,
            release_median_ms: lease,
            stopped_cleanly: true,
        }
    }

    #[test]
    fn binaries_are_summarised_against_the_first() {
        let runs = [
            run("before", 1, 10.0, 40.0, 40.0),
            run("after", 1, 100.0, 1.0, 2.0),
            run("before", 2, 20.0, 50.0, 44.0),
            run("after", 2, 140.0, 2.0, 2.0),
        ];
        let binaries = [PathBuf::from("before"), PathBuf::from("after")];
        let summaries = summarise(&binaries, &runs);
        assert_eq!(summaries.len(), 2);
        let (before, after) = (&summaries[0], &summaries[1]);
        assert_eq!((before.runs, before.frames_per_s), (2, 15.0));
        assert_eq!(before.frames_per_s_over_baseline, 1.0);
        assert_eq!(after.frames_per_s, 120.0);
        assert_eq!(after.frames_per_s_over_baseline, 8.0);
        assert_eq!(after.submit_speedup, 45.0 / 1.5);
        assert_eq!(after.lease_speedup, 21.0);

        let result = ServiceLoadResult {
            jobs: 4,
            frames_per_job: 2,
            clients: 2,
            leases: 5,
            width: 64,
            height: 48,
            dataset_points: DATASET_POINTS,
            runs: runs.to_vec(),
            summaries,
        };
        let table = markdown(&result);
        assert!(
            table.contains("| after | 2 | 1.50 | llvmpipe | 140.0 | 2.00 |"),
            "{table}"
        );
        assert!(
            table.contains("| after | 2 | 120.0 | 8.00x | 1.50 | 30.00x |"),
            "{table}"
        );
    }

    #[test]
    fn nothing_to_run_is_refused_before_any_work() {
        let mut options = ServiceLoadOptions::new(PathBuf::from("pointfarm"));
        options.clients = 0;
        let refused = measure(&options, &mut |_| {}).expect_err("no clients");
        assert!(refused.to_string().contains("clients"), "{refused}");
    }
}

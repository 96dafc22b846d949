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
use pointfarm_render::request::RenderRequest;
use serde::Serialize;
use tonic::transport::Channel;

use crate::clouds::uniform_cube;
use crate::scratch::load_average;
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
    pub load: ServiceLoad,
    /// The embedded worker's `--adapter` (auto, hardware, software).
    pub adapter: String,
}

/// The load each run puts on a daemon: what the options ask for and the result reports.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct ServiceLoad {
    pub jobs: u32,
    pub frames_per_job: u32,
    pub clients: u32,
    pub leases: u32,
    pub width: u32,
    pub height: u32,
}

impl Default for ServiceLoad {
    fn default() -> Self {
        Self {
            jobs: DEFAULT_JOBS,
            frames_per_job: DEFAULT_FRAMES_PER_JOB,
            clients: DEFAULT_CLIENTS,
            leases: DEFAULT_LEASES,
            width: DEFAULT_SIZE.0,
            height: DEFAULT_SIZE.1,
        }
    }
}

impl ServiceLoadOptions {
    /// The defaults, with `daemon_binary` alone run once.
    pub fn new(daemon_binary: PathBuf) -> Self {
        Self {
            daemon_binaries: vec![daemon_binary],
            runs: 1,
            load: ServiceLoad::default(),
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
    #[serde(flatten)]
    pub load: ServiceLoad,
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
        load: options.load,
        dataset_points: DATASET_POINTS,
        summaries: summarise(&options.daemon_binaries, &runs),
        runs,
    })
}

fn check(options: &ServiceLoadOptions) -> Result<(), ServiceLoadError> {
    let counts = [
        ("daemon binaries", options.daemon_binaries.len()),
        ("runs", options.runs as usize),
        ("jobs", options.load.jobs as usize),
        ("frames per job", options.load.frames_per_job as usize),
        ("clients", options.load.clients as usize),
        ("leases", options.load.leases as usize),
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
        jobs: options.load.jobs,
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

mod phases;
use phases::{lease_phase, load_phase};
mod report;
#[cfg(test)]
mod tests;

use report::summarise;
pub use report::{markdown, write_json};

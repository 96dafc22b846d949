//! `pointfarm worker`: a render worker in its own process, leasing frames from a daemon; also
//! what `pointfarm serve` runs as its embedded worker (`--supervised`).

use pointfarm_render::cut::{CutOptions, DEFAULT_LOD_ERROR_PX, DEFAULT_MEMORY_BUDGET_BYTES};
use std::ffi::{OsStr, OsString};
use std::path::PathBuf;
use std::sync::Arc;

use anyhow::{Context, Result};
use clap::Args;
use pointfarm_daemon::capabilities::{checked_tags, WorkerCapabilities};
use pointfarm_daemon::metrics::{http, WorkerMetrics};
use pointfarm_daemon::open_files;
use pointfarm_daemon::service::DEFAULT_WORKER_CACHE_BYTES;
use pointfarm_proto::endpoint::connections::ConnectionLimits;
use pointfarm_proto::endpoint::ServerEndpoint;
use pointfarm_render::gpu::{AdapterChoice, GpuContext};
use pointfarm_worker::lease_loop::{run as run_worker, RemoteWorkerConfig};
use pointfarm_worker::memory_limit;
use pointfarm_worker::range_cache::DEFAULT_URL_CACHE_BYTES;
use pointfarm_worker::supervised::exit_when_supervisor_exits;

use crate::config_file::ConfigArgs;
use crate::credentials::secret;
use crate::{parse, paths};

#[derive(Args)]
pub struct WorkerArgs {
    #[command(flatten)]
    config: ConfigArgs,
    /// The daemon to render for.
    #[arg(
        long,
        env = "POINTFARM_SERVER",
        default_value = "http://127.0.0.1:50051"
    )]
    server: String,
    /// The daemon's worker token (its --worker-token; a client token is refused).
    #[arg(long, env = "POINTFARM_WORKER_TOKEN", hide_env_values = true)]
    worker_token: Option<String>,
    /// Read the worker token from this file instead.
    #[arg(long, value_name = "FILE", env = "POINTFARM_WORKER_TOKEN_FILE")]
    worker_token_file: Option<PathBuf>,
    /// Trust the CA certificates in this PEM file for the daemon's TLS, instead of the
    /// system's (a bare HOST:PORT then means https://).
    #[arg(long, value_name = "FILE", env = "POINTFARM_TLS_CA")]
    tls_ca: Option<PathBuf>,
    /// Folder for this worker's dataset cache, kept across runs (default: `worker` in the
    /// unit's CacheDirectory, in /var/cache/pointfarm for root, else in
    /// $XDG_CACHE_HOME/pointfarm).
    #[arg(long, env = "POINTFARM_WORKER_CACHE_DIR", default_value_os_t = paths::worker_cache_dir())]
    cache_dir: PathBuf,
    /// Size bound of the dataset cache, in GiB, and of the levels-of-detail stores together.
    #[arg(long, env = "POINTFARM_CACHE_GIB", default_value_t = DEFAULT_WORKER_CACHE_BYTES >> 30)]
    cache_gib: u64,
    /// Size bound of the cache of byte ranges of datasets by URL, e.g. 2GiB (0: none).
    #[arg(long, value_name = "SIZE", env = "POINTFARM_URL_CACHE", value_parser = parse::bytes, default_value_t = DEFAULT_URL_CACHE_BYTES)]
    url_cache: u64,
    /// Name shown in the daemon's leases and logs (default: host name and process id).
    #[arg(long, env = "POINTFARM_WORKER_NAME")]
    name: Option<String>,
    /// GPU to render on: auto, hardware or software (lavapipe).
    #[arg(long, env = "POINTFARM_ADAPTER", default_value = "auto")]
    adapter: AdapterChoice,
    /// Which adapter of those --adapter allows, counting from 0, best first: one worker per
    /// GPU on a machine with several (an index out of range lists them).
    #[arg(
        long,
        value_name = "N",
        env = "POINTFARM_ADAPTER_INDEX",
        default_value_t = 0
    )]
    adapter_index: usize,
    /// An operator tag this worker advertises (repeatable; the environment variable takes a
    /// comma-separated list): jobs that require tags are leased only to workers with all of
    /// them. Letters, digits and -_.:/, at most 64 bytes each.
    #[arg(
        long = "tag",
        value_name = "TAG",
        env = "POINTFARM_WORKER_TAGS",
        value_delimiter = ','
    )]
    tags: Vec<String>,
    /// Draw no image larger than this many pixels a side (width or height times
    /// supersampling): larger frames go to other workers. Default: the renderer's limit
    /// (16384; frames beyond the adapter's binding limit are drawn in tiles).
    #[arg(long, value_name = "PIXELS", env = "POINTFARM_MAX_FRAME_SIDE", value_parser = clap::value_parser!(u32).range(1..))]
    max_frame_side: Option<u32>,
    /// Cap this process's memory (heap and other private writable memory) at this many MiB:
    /// a frame that needs more aborts the worker instead of exhausting the machine.
    #[arg(long, value_name = "MIB", env = "POINTFARM_MAX_MEMORY_MIB")]
    max_memory_mib: Option<u64>,
    /// Levels of detail: the pixel error of datasets of more than 20M points rendered by
    /// jobs that do not set one.
    #[arg(long, value_name = "PX", env = "POINTFARM_LOD_ERROR", value_parser = parse::non_negative, default_value_t = DEFAULT_LOD_ERROR_PX)]
    lod_error: f64,
    /// Levels of detail: host memory for the node cache and the stores' builds, e.g. 4GiB;
    /// on a software adapter the GPU node cache's share too.
    #[arg(long, value_name = "SIZE", env = "POINTFARM_MEMORY_BUDGET", value_parser = parse::bytes, default_value_t = DEFAULT_MEMORY_BUDGET_BYTES)]
    memory_budget: u64,
    /// Levels of detail: GPU memory for the node cache (default 2GiB; on a software adapter
    /// half of --memory-budget).
    #[arg(long, value_name = "SIZE", env = "POINTFARM_GPU_BUDGET", value_parser = parse::bytes)]
    gpu_budget: Option<u64>,
    /// Serve this worker's Prometheus metrics at http://ADDR/metrics (frames rendered and
    /// failed, stage latencies, dataset and node cache hits); a bare port listens on
    /// loopback. Plain HTTP and
    /// unauthenticated: it shows counts and timings only, but listen where only the
    /// scrapers reach.
    #[arg(long, value_name = "ADDR", env = "POINTFARM_METRICS_LISTEN")]
    metrics_listen: Option<String>,
    /// Make no videos of jobs, even where ffmpeg is installed (by default a worker whose
    /// ffmpeg has a job's encoder may be leased its video).
    #[arg(long, env = "POINTFARM_NO_VIDEOS")]
    no_videos: bool,
    /// Run as a daemon's embedded worker: exit as soon as standard input (a pipe from the
    /// daemon) closes.
    #[arg(long, hide = true)]
    supervised: bool,
}

/// The environment variables of the worker's settings (and of its configuration file).
pub(crate) fn settings_env() -> Vec<OsString> {
    WorkerArgs::augment_args(clap::Command::new("worker"))
        .get_arguments()
        .filter_map(|arg| arg.get_env().map(OsStr::to_os_string))
        .collect()
}

pub fn run(args: WorkerArgs) -> Result<()> {
    if args.supervised {
        exit_when_supervisor_exits().context("watching the supervising daemon")?;
    }
    // A worker holds dataset files, cache entries and connections open at once.
    let open_files = open_files::raise_soft_limit();
    // Before the GPU is set up: a wrong address or credential is reported at once.
    let server = ServerEndpoint::new(&args.server, args.tls_ca.as_deref())?;
    let token = secret(
        args.worker_token.as_deref(),
        args.worker_token_file.as_deref(),
        "--worker-token",
    )?;
    let cut = CutOptions {
        lod_error: args.lod_error,
        memory_budget_bytes: args.memory_budget,
        gpu_budget_bytes: args.gpu_budget,
    };
    cut.validate()?;
    let tags = checked_tags("--tag", args.tags.iter().map(|t| t.trim()))?;
    let gpu = Arc::new(GpuContext::with_index(args.adapter, args.adapter_index)?);
    let capabilities = WorkerCapabilities::of(&gpu, tags, args.max_frame_side);
    // After the GPU is set up: the limit is for the frames' data.
    if let Some(mib) = args.max_memory_mib {
        memory_limit::apply(mib << 20)?;
    }
    let name = args.name.unwrap_or_else(|| {
        let host = std::env::var("HOSTNAME")
            .ok()
            .filter(|h| !h.is_empty())
            .unwrap_or_else(|| "worker".into());
        format!("{host}-{}", std::process::id())
    });
    outln!(
        "worker {name} on {} rendering for {}",
        gpu.describe(),
        server.url()
    );
    outln!("{}", describe_capabilities(&capabilities));
    let config = RemoteWorkerConfig {
        server,
        token,
        name,
        cache_dir: args.cache_dir,
        cache_bytes: args.cache_gib << 30,
        url_cache_bytes: args.url_cache,
        cut,
        metrics: Arc::new(WorkerMetrics::new()),
        capabilities,
        videos: !args.no_videos,
    };
    let runtime = tokio::runtime::Runtime::new().context("starting the async runtime")?;
    runtime.block_on(async move {
        if let Some(address) = &args.metrics_listen {
            let metrics = config.metrics.clone();
            let limits = ConnectionLimits::for_open_files(open_files);
            let bound = http::listen(address, limits, Arc::new(move || Ok(metrics.text()))).await?;
            outln!("metrics on http://{bound}/metrics");
        }
        run_worker(config, gpu, crate::signals::shutdown_signal()).await
    })
}

/// What the worker advertises, in one line: the frame limit and the tags.
fn describe_capabilities(capabilities: &WorkerCapabilities) -> String {
    let side = capabilities
        .max_frame_side
        .map_or_else(|| "any".to_string(), |side| side.to_string());
    let tags = if capabilities.tags.is_empty() {
        "none".to_string()
    } else {
        capabilities
            .tags
            .iter()
            .cloned()
            .collect::<Vec<_>>()
            .join(", ")
    };
    format!("largest image side drawn: {side} pixels; tags: {tags}")
}

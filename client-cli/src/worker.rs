//! `pointfarm worker`: a render worker in its own process, leasing frames from a daemon; also
//! what `pointfarm serve` runs as its embedded worker (`--supervised`).

use std::path::PathBuf;
use std::sync::Arc;

use anyhow::{Context, Result};
use clap::Args;
use pointfarm_daemon::worker::memory_limit;
use pointfarm_daemon::worker::remote::{run as run_worker, RemoteWorkerConfig};
use pointfarm_daemon::worker::supervisor::exit_when_supervisor_exits;
use pointfarm_render::gpu::{AdapterChoice, GpuContext};

#[derive(Args)]
pub struct WorkerArgs {
    /// The daemon to render for.
    #[arg(
        long,
        env = "POINTFARM_SERVER",
        default_value = "http://127.0.0.1:50051"
    )]
    server: String,
    /// Bearer token for the daemon.
    #[arg(long, env = "POINTFARM_TOKEN", hide_env_values = true)]
    token: Option<String>,
    /// Folder for this worker's dataset cache (processed points, kept across runs).
    #[arg(long, default_value = "pointfarm-worker-cache")]
    cache_dir: PathBuf,
    /// Size bound of the dataset cache, in GiB.
    #[arg(long, default_value_t = 8)]
    cache_gib: u64,
    /// Name shown in the daemon's leases and logs (default: host name and process id).
    #[arg(long)]
    name: Option<String>,
    /// GPU to render on: auto, hardware or software (lavapipe).
    #[arg(long, env = "POINTFARM_ADAPTER", default_value = "auto")]
    adapter: AdapterChoice,
    /// Cap this process's memory (heap and other private writable memory) at this many MiB:
    /// a frame that needs more aborts the worker instead of exhausting the machine.
    #[arg(long, value_name = "MIB")]
    max_memory_mib: Option<u64>,
    /// Run as a daemon's embedded worker: exit as soon as standard input (a pipe from the
    /// daemon) closes.
    #[arg(long, hide = true)]
    supervised: bool,
}

pub fn run(args: WorkerArgs) -> Result<()> {
    if args.supervised {
        exit_when_supervisor_exits().context("watching the supervising daemon")?;
    }
    let gpu = Arc::new(GpuContext::new(args.adapter)?);
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
    println!(
        "worker {name} on {} rendering for {}",
        gpu.describe(),
        args.server
    );
    let config = RemoteWorkerConfig {
        server: args.server,
        token: args.token,
        name,
        cache_dir: args.cache_dir,
        cache_bytes: args.cache_gib << 30,
    };
    let runtime = tokio::runtime::Runtime::new().context("starting the async runtime")?;
    runtime.block_on(run_worker(config, gpu, crate::serve::shutdown_signal()))
}

//! `pointfarm worker`: a render worker in its own process, leasing frames from a daemon.

use std::path::PathBuf;
use std::sync::Arc;

use anyhow::{Context, Result};
use clap::Args;
use pointfarm_daemon::worker::remote::{run as run_worker, RemoteWorkerConfig};
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
}

pub fn run(args: WorkerArgs) -> Result<()> {
    let gpu = Arc::new(GpuContext::new(args.adapter)?);
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

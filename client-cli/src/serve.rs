//! `pointfarm serve`: the daemon, by default with an embedded worker: this binary's `worker`
//! command as a child process that the daemon supervises, so that a frame that crashes its
//! worker never takes the daemon down. Separate `pointfarm worker` processes can render for it
//! as well or instead.

use std::ffi::OsString;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use clap::Args;
use pointfarm_daemon::server::serve;
use pointfarm_daemon::service::{Daemon, DaemonConfig, DEFAULT_MAX_UPLOAD_BYTES};
use pointfarm_daemon::worker::supervisor::WorkerCommand;
use pointfarm_render::gpu::AdapterChoice;

#[derive(Args)]
pub struct ServeArgs {
    /// Address to listen on.
    #[arg(long, default_value = "127.0.0.1:50051")]
    listen: String,
    /// Folder for the state database, uploaded datasets and rendered frames.
    #[arg(long, default_value = "pointfarm-data")]
    data_dir: PathBuf,
    /// Folder whose files clients may register by path (repeatable).
    #[arg(long = "data-root")]
    data_roots: Vec<PathBuf>,
    /// Require this bearer token on every call.
    #[arg(long, env = "POINTFARM_TOKEN", hide_env_values = true)]
    token: Option<String>,
    /// Largest image side accepted.
    #[arg(long, default_value_t = 8192)]
    max_image_side: u32,
    /// Largest upload accepted, in bytes.
    #[arg(long, default_value_t = DEFAULT_MAX_UPLOAD_BYTES)]
    max_upload_bytes: u64,
    /// Most bytes all uploaded datasets may take together; an upload past it is refused
    /// before its data is sent (default: no quota, only the disk bounds them).
    #[arg(long)]
    upload_quota_bytes: Option<u64>,
    /// Start even when the state database is damaged (truncated, bit-flipped, records
    /// missing): go on with what it still holds and log exactly what was lost. Without it
    /// the daemon refuses to start on such a state and says why.
    #[arg(long)]
    recover_state: bool,
    /// Run no embedded worker: only `pointfarm worker` processes render.
    #[arg(long, alias = "no-worker")]
    no_embedded_worker: bool,
    /// Seconds a worker's lease on a frame lasts without a heartbeat; when it runs out (the
    /// worker died or was cut off) the frame goes back to the queue.
    #[arg(long, default_value_t = 30.0, value_parser = parse_lease_timeout)]
    lease_timeout: f64,
    /// Attempts at a frame (failed, or lost with its worker) before its job fails.
    #[arg(long, default_value_t = 3, value_parser = clap::value_parser!(u32).range(1..=100))]
    max_frame_attempts: u32,
    /// Cap the embedded worker process's memory (heap and other private writable memory) at
    /// this many MiB: a frame that needs more crashes that process, not the machine, and
    /// counts a failed attempt.
    #[arg(long, value_name = "MIB")]
    worker_max_memory_mib: Option<u64>,
    /// GPU of the embedded worker: auto, hardware or software (lavapipe).
    #[arg(long, env = "POINTFARM_ADAPTER", default_value = "auto")]
    adapter: AdapterChoice,
}

pub fn run(args: ServeArgs) -> Result<()> {
    let runtime = tokio::runtime::Runtime::new().context("starting the async runtime")?;
    runtime.block_on(async move {
        let mut config = DaemonConfig::new(args.data_dir.clone());
        config.data_roots = args.data_roots.clone();
        config.max_image_side = args.max_image_side;
        config.max_upload_bytes = args.max_upload_bytes;
        config.upload_quota_bytes = args.upload_quota_bytes;
        config.recover_state = args.recover_state;
        config.lease_timeout = std::time::Duration::from_secs_f64(args.lease_timeout);
        config.max_frame_attempts = args.max_frame_attempts;
        let daemon =
            Daemon::open(config).with_context(|| format!("opening {}", args.data_dir.display()))?;
        let embedded_worker = if args.no_embedded_worker {
            println!("no embedded worker: start `pointfarm worker --server ...` to render");
            None
        } else {
            let command = embedded_worker_command(&args, &daemon.config)?;
            println!("embedded worker: {}", command.program.display());
            Some(command)
        };
        let listener = tokio::net::TcpListener::bind(&args.listen)
            .await
            .with_context(|| format!("listening on {}", args.listen))?;
        println!(
            "pointfarm serving on {} (data in {})",
            listener.local_addr()?,
            args.data_dir.display()
        );
        serve(
            daemon,
            embedded_worker,
            listener,
            args.token,
            shutdown_signal(),
        )
        .await
    })
}

/// This binary's `worker` command, rendering with the daemon's settings; its cache lives in
/// the data folder.
fn embedded_worker_command(args: &ServeArgs, config: &DaemonConfig) -> Result<WorkerCommand> {
    let program = std::env::current_exe().context("finding the pointfarm binary")?;
    let cache_dir = config.data_dir.join("embedded-worker");
    let mut worker_args = worker_args(&cache_dir, config.worker_cache_bytes, args.adapter);
    if let Some(mib) = args.worker_max_memory_mib {
        worker_args.extend(["--max-memory-mib".into(), mib.to_string().into()]);
    }
    Ok(WorkerCommand {
        program,
        args: worker_args,
    })
}

/// The arguments of `pointfarm worker` for an embedded worker (the supervisor adds the
/// server, the name and the token).
pub(crate) fn worker_args(
    cache_dir: &Path,
    cache_bytes: u64,
    adapter: AdapterChoice,
) -> Vec<OsString> {
    vec![
        "worker".into(),
        "--cache-dir".into(),
        cache_dir.into(),
        "--cache-gib".into(),
        (cache_bytes >> 30).max(1).to_string().into(),
        "--adapter".into(),
        adapter.to_string().into(),
    ]
}

fn parse_lease_timeout(value: &str) -> Result<f64, String> {
    match value.parse::<f64>() {
        Ok(seconds) if seconds.is_finite() && (0.1..=3600.0).contains(&seconds) => Ok(seconds),
        _ => Err(format!(
            "'{value}' is not a number of seconds from 0.1 to 3600"
        )),
    }
}

/// Completes on SIGTERM or Ctrl-C.
pub(crate) async fn shutdown_signal() {
    let ctrl_c = tokio::signal::ctrl_c();
    #[cfg(unix)]
    {
        let mut term =
            match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
                Ok(term) => term,
                Err(_) => {
                    let _ = ctrl_c.await;
                    return;
                }
            };
        tokio::select! {
            _ = ctrl_c => {}
            _ = term.recv() => {}
        }
    }
    #[cfg(not(unix))]
    {
        let _ = ctrl_c.await;
    }
}

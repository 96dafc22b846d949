//! `pointfarm serve`: the daemon, by default with an embedded worker: this binary's `worker`
//! command as a child process that the daemon supervises, so that a frame that crashes its
//! worker never takes the daemon down. Separate `pointfarm worker` processes can render for it
//! as well or instead.

use std::ffi::OsString;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use clap::Args;
use pointfarm_daemon::access::Access;
use pointfarm_daemon::server::{serve, ServeOptions, TlsIdentity};
use pointfarm_daemon::service::{
    Daemon, DaemonConfig, DEFAULT_MAX_UPLOAD_BYTES, DEFAULT_WORKER_FAILURES_BEFORE_BLOCKLIST,
};
use pointfarm_daemon::worker::supervisor::WorkerCommand;
use pointfarm_render::gpu::AdapterChoice;

use crate::credentials::secret;
use crate::parse;

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
    /// Require this bearer token of clients (datasets and jobs). Without it those services
    /// are open, which is refused beyond loopback unless --insecure.
    #[arg(long, env = "POINTFARM_TOKEN", hide_env_values = true)]
    token: Option<String>,
    /// Read the client token from this file instead.
    #[arg(long, value_name = "FILE", env = "POINTFARM_TOKEN_FILE")]
    token_file: Option<PathBuf>,
    /// Require this bearer token of workers (`pointfarm worker --worker-token`); a client
    /// token is refused there. Without it, a daemon with a client token serves no remote
    /// workers, and one without is open to any.
    #[arg(long, env = "POINTFARM_WORKER_TOKEN", hide_env_values = true)]
    worker_token: Option<String>,
    /// Read the worker token from this file instead.
    #[arg(long, value_name = "FILE", env = "POINTFARM_WORKER_TOKEN_FILE")]
    worker_token_file: Option<PathBuf>,
    /// Serve TLS with this certificate chain (PEM); needs --tls-key.
    #[arg(long, value_name = "FILE", requires = "tls_key")]
    tls_cert: Option<PathBuf>,
    /// The private key (PEM) of --tls-cert.
    #[arg(long, value_name = "FILE", requires = "tls_cert")]
    tls_key: Option<PathBuf>,
    /// Listen beyond loopback without a client token or without TLS: anyone who reaches the
    /// port can then use the farm (or read it on the wire).
    #[arg(long)]
    insecure: bool,
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
    /// Host memory the build of a dataset's level-of-detail store may hold, e.g. 4GiB. The
    /// server builds each store once (one at a time, in DATA/lod) and its workers read the
    /// nodes their frames need from it (default 2GiB).
    #[arg(long, value_name = "SIZE", value_parser = parse::bytes)]
    store_memory_budget: Option<u64>,
    /// Seconds a worker's lease on a frame lasts without a heartbeat; when it runs out (the
    /// worker died or was cut off) the frame goes back to the queue.
    #[arg(long, default_value_t = 30.0, value_parser = parse_lease_timeout)]
    lease_timeout: f64,
    /// Attempts at a frame (failed, or lost with its worker) before its job fails.
    #[arg(long, default_value_t = 3, value_parser = clap::value_parser!(u32).range(1..=100))]
    max_frame_attempts: u32,
    /// Frames of one job a worker may fail (reported failures, leases that ran out) before
    /// it is leased no more of that job's frames; 0 keeps no blocklist.
    #[arg(
        long,
        value_name = "N",
        env = "POINTFARM_BLOCKLIST_AFTER",
        default_value_t = DEFAULT_WORKER_FAILURES_BEFORE_BLOCKLIST
    )]
    blocklist_after: u32,
    /// Cap the embedded worker process's memory (heap and other private writable memory) at
    /// this many MiB: a frame that needs more crashes that process, not the machine, and
    /// counts a failed attempt.
    #[arg(long, value_name = "MIB")]
    worker_max_memory_mib: Option<u64>,
    /// GPU of the embedded worker: auto, hardware or software (lavapipe).
    #[arg(long, env = "POINTFARM_ADAPTER", default_value = "auto")]
    adapter: AdapterChoice,
}

/// The tokens and TLS identity the flags give.
fn serve_options(args: &ServeArgs) -> Result<ServeOptions> {
    let token = secret(args.token.as_deref(), args.token_file.as_deref(), "--token")?;
    let worker_token = secret(
        args.worker_token.as_deref(),
        args.worker_token_file.as_deref(),
        "--worker-token",
    )?;
    if token.is_some() && token == worker_token {
        bail!("--token and --worker-token are the same: give clients and workers different tokens");
    }
    let read =
        |path: &PathBuf| std::fs::read(path).with_context(|| format!("reading {}", path.display()));
    let tls = match (&args.tls_cert, &args.tls_key) {
        (Some(cert), Some(key)) => Some(TlsIdentity {
            cert_pem: read(cert)?,
            key_pem: read(key)?,
        }),
        _ => None,
    };
    Ok(ServeOptions {
        access: Access::new(token.as_deref(), worker_token.as_deref()),
        tls,
        insecure: args.insecure,
    })
}

pub fn run(args: ServeArgs) -> Result<()> {
    let options = serve_options(&args)?;
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
        config.worker_failures_before_blocklist = args.blocklist_after;
        if let Some(bytes) = args.store_memory_budget {
            config.store_build_memory_bytes = bytes;
        }
        let daemon =
            Daemon::open(config).with_context(|| format!("opening {}", args.data_dir.display()))?;
        let embedded_worker = if args.no_embedded_worker {
            outln!("no embedded worker: start `pointfarm worker --server ...` to render");
            None
        } else {
            let command = embedded_worker_command(&args, &daemon.config)?;
            outln!("embedded worker: {}", command.program.display());
            Some(command)
        };
        let listener = tokio::net::TcpListener::bind(&args.listen)
            .await
            .with_context(|| format!("listening on {}", args.listen))?;
        let address = listener.local_addr()?;
        options.check_exposure(address)?;
        outln!(
            "pointfarm serving on {}{address} (data in {})",
            if options.tls.is_some() {
                "https://"
            } else {
                "http://"
            },
            args.data_dir.display()
        );
        serve(
            daemon,
            embedded_worker,
            listener,
            options,
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

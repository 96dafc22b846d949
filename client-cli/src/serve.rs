//! `pointfarm serve`: the daemon, by default with an embedded worker: this binary's `worker`
//! command as a child process that the daemon supervises, so that a frame that crashes its
//! worker never takes the daemon down. Separate `pointfarm worker` processes can render for it
//! as well or instead.

use std::path::PathBuf;
use std::sync::Arc;

use anyhow::{anyhow, bail, Context, Result};
use clap::Args;
use pointfarm_daemon::access::Access;
use pointfarm_daemon::capabilities::checked_tags;
use pointfarm_daemon::dashboard::{self, DashboardOptions};
use pointfarm_daemon::metrics;
use pointfarm_daemon::open_files;
use pointfarm_daemon::output_queue::output_prefixes;
use pointfarm_daemon::remote_datasets::url_prefixes;
use pointfarm_daemon::server::{serve, ServeOptions, TlsIdentity, DEFAULT_SHUTDOWN_GRACE};
use pointfarm_daemon::service::{
    Daemon, DaemonConfig, DEFAULT_LEASE_TIMEOUT, DEFAULT_MAX_FRAMES, DEFAULT_MAX_FRAME_ATTEMPTS,
    DEFAULT_MAX_IMAGE_SIDE, DEFAULT_MAX_UPLOAD_BYTES, DEFAULT_WORKER_CACHE_BYTES,
    DEFAULT_WORKER_FAILURES_BEFORE_BLOCKLIST,
};
use pointfarm_daemon::stores::{store_url, DEFAULT_PUBLISH_ATTEMPTS, MAX_PUBLISH_ATTEMPTS};
use pointfarm_daemon::supervisor::WorkerCommand;
use pointfarm_proto::endpoint::connections::ConnectionLimits;
use pointfarm_proto::endpoint::{self, certificate};
use pointfarm_render::gpu::AdapterChoice;

use crate::config_file::{webhook_endpoints, ConfigArgs};
use crate::credentials::secret;
use crate::{parse, paths};

#[derive(Args)]
pub struct ServeArgs {
    #[command(flatten)]
    config: ConfigArgs,
    /// Address to listen on.
    #[arg(long, env = "POINTFARM_LISTEN", default_value = "127.0.0.1:50051")]
    listen: String,
    /// Folder for the state database, uploaded datasets and rendered frames (default: the
    /// unit's StateDirectory, /var/lib/pointfarm for root, else $XDG_DATA_HOME/pointfarm).
    #[arg(long, env = "POINTFARM_DATA_DIR", default_value_os_t = paths::daemon_data_dir())]
    data_dir: PathBuf,
    /// Folder whose files clients may register by path (repeatable; in the environment,
    /// separated by commas).
    #[arg(long = "data-root", env = "POINTFARM_DATA_ROOT", value_delimiter = ',')]
    data_roots: Vec<PathBuf>,
    /// A URL prefix (s3://bucket/prefix, gs://, az://, https://host/path) clients may register
    /// datasets from by URL (COPC objects, LAS/LAZ tiles), compared by whole path segments
    /// (repeatable; in the environment, separated by commas). Without one, no dataset by URL is
    /// accepted.
    #[arg(
        long = "allow-url-prefix",
        value_name = "URL",
        env = "POINTFARM_ALLOW_URL_PREFIX",
        value_delimiter = ','
    )]
    allowed_url_prefixes: Vec<String>,
    /// An s3://, gs:// or az:// prefix jobs may write their outputs under (`render --output-url`), compared
    /// by whole path segments (repeatable; in the environment, separated by commas).
    /// Without one, no job may name an output URL.
    #[arg(
        long = "allow-output-prefix",
        value_name = "URL",
        env = "POINTFARM_ALLOW_OUTPUT_PREFIX",
        value_delimiter = ','
    )]
    allowed_output_prefixes: Vec<String>,
    /// An s3://, gs:// or az:// prefix (s3://bucket/prefix) the daemon publishes each dataset's level-of-detail
    /// store under once built, STORE_URL/SHA256/, for workers to read its nodes from there with
    /// credentials of their own instead of through the daemon. Without it, workers read every
    /// store through the daemon.
    #[arg(long, value_name = "URL", env = "POINTFARM_STORE_URL")]
    store_url: Option<String>,
    /// Tries at publishing a store to --store-url, waiting 1 s after the first failure and
    /// twice as long after each (up to a minute): 8 wait about two minutes in all. After the
    /// last, `dataset get` says the publish failed, with the last error and when, workers read
    /// the store through the daemon, and it is tried again when a frame of it is next leased.
    #[arg(long, value_name = "N", env = "POINTFARM_STORE_PUBLISH_ATTEMPTS", default_value_t = DEFAULT_PUBLISH_ATTEMPTS, value_parser = clap::value_parser!(u32).range(1..=i64::from(MAX_PUBLISH_ATTEMPTS)))]
    store_publish_attempts: u32,
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
    #[arg(long, value_name = "FILE", env = "POINTFARM_TLS_CERT")]
    tls_cert: Option<PathBuf>,
    /// The private key (PEM) of --tls-cert.
    #[arg(long, value_name = "FILE", env = "POINTFARM_TLS_KEY")]
    tls_key: Option<PathBuf>,
    /// Also serve the gRPC health service alone, in plaintext, on this address (e.g.
    /// 0.0.0.0:8081): for Kubernetes' gRPC probes, which cannot speak TLS. It tells only
    /// whether the daemon and its workers serve.
    #[arg(long, value_name = "ADDR", env = "POINTFARM_HEALTH_LISTEN")]
    health_listen: Option<std::net::SocketAddr>,
    /// Listen beyond loopback without a client token or without TLS: anyone who reaches the
    /// port can then use the farm (or read it on the wire).
    #[arg(long, env = "POINTFARM_INSECURE")]
    insecure: bool,
    /// Largest image side accepted.
    #[arg(long, env = "POINTFARM_MAX_IMAGE_SIDE", default_value_t = DEFAULT_MAX_IMAGE_SIDE)]
    max_image_side: u32,
    /// Most frames in one job.
    #[arg(long, env = "POINTFARM_MAX_FRAMES", default_value_t = DEFAULT_MAX_FRAMES, value_parser = clap::value_parser!(u32).range(1..))]
    max_frames: u32,
    /// Largest upload accepted, in bytes.
    #[arg(long, env = "POINTFARM_MAX_UPLOAD_BYTES", default_value_t = DEFAULT_MAX_UPLOAD_BYTES)]
    max_upload_bytes: u64,
    /// Most bytes all uploaded datasets may take together; an upload past it is refused
    /// before its data is sent (default: no quota, only the disk bounds them).
    #[arg(long, env = "POINTFARM_UPLOAD_QUOTA_BYTES")]
    upload_quota_bytes: Option<u64>,
    /// Remove jobs that ended (succeeded, failed or were cancelled) more than N days ago,
    /// with their frames, on a sweep every minute (default: keep them).
    #[arg(long, value_name = "N", env = "POINTFARM_JOB_RETENTION_DAYS", value_parser = clap::value_parser!(u32).range(1..))]
    job_retention_days: Option<u32>,
    /// While the stored frames take more than SIZE (e.g. 200G), remove the jobs that ended
    /// first, with their frames, until they fit; unfinished jobs are never removed (default:
    /// no quota).
    #[arg(long, value_name = "SIZE", env = "POINTFARM_FRAME_QUOTA", value_parser = parse::bytes)]
    frame_quota: Option<u64>,
    /// Start even when the state database is damaged (truncated, bit-flipped, records
    /// missing): go on with what it still holds and log exactly what was lost. Without it
    /// the daemon refuses to start on such a state and says why.
    #[arg(long, env = "POINTFARM_RECOVER_STATE")]
    recover_state: bool,
    /// Run no embedded worker: only `pointfarm worker` processes render.
    #[arg(long, alias = "no-worker", env = "POINTFARM_NO_EMBEDDED_WORKER")]
    no_embedded_worker: bool,
    /// Host memory the build of a dataset's level-of-detail store may hold, e.g. 4GiB. The
    /// server builds each store once (one at a time, in DATA/lod) and its workers read the
    /// nodes their frames need from it (default 2GiB).
    #[arg(long, value_name = "SIZE", env = "POINTFARM_STORE_MEMORY_BUDGET", value_parser = parse::bytes)]
    store_memory_budget: Option<u64>,
    /// Seconds a worker's lease on a frame lasts without a heartbeat; when it runs out (the
    /// worker died or was cut off) the frame goes back to the queue.
    #[arg(long, env = "POINTFARM_LEASE_TIMEOUT", default_value_t = DEFAULT_LEASE_TIMEOUT.as_secs_f64(), value_parser = parse_lease_timeout)]
    lease_timeout: f64,
    /// Attempts at a frame (failed, or lost with its worker) before its job fails.
    #[arg(long, env = "POINTFARM_MAX_FRAME_ATTEMPTS", default_value_t = DEFAULT_MAX_FRAME_ATTEMPTS, value_parser = clap::value_parser!(u32).range(1..=100))]
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
    #[arg(long, value_name = "MIB", env = "POINTFARM_WORKER_MAX_MEMORY_MIB")]
    worker_max_memory_mib: Option<u64>,
    /// An operator tag the embedded worker advertises, as `worker --tag` (repeatable; in the
    /// environment, separated by commas).
    #[arg(
        long = "worker-tag",
        value_name = "TAG",
        env = "POINTFARM_EMBEDDED_WORKER_TAGS",
        value_delimiter = ','
    )]
    worker_tags: Vec<String>,
    /// Size bound of the embedded worker's dataset cache (in DATA/embedded-worker), e.g. 8GiB.
    #[arg(long, value_name = "SIZE", env = "POINTFARM_WORKER_CACHE_SIZE", value_parser = parse::bytes, default_value_t = DEFAULT_WORKER_CACHE_BYTES)]
    worker_cache_size: u64,
    /// GPU of the embedded worker: auto, hardware or software (lavapipe).
    #[arg(long, env = "POINTFARM_ADAPTER", default_value = "auto")]
    adapter: AdapterChoice,
    /// Serve Prometheus metrics at http://ADDR/metrics (queue depth, frames completed and
    /// failed, stage latencies, leases, workers, cache hits, bytes uploaded); a bare port
    /// listens on loopback. Plain HTTP and unauthenticated: it shows counts and timings
    /// only, but listen where only the scrapers reach.
    #[arg(long, value_name = "ADDR", env = "POINTFARM_METRICS_LISTEN")]
    metrics_listen: Option<String>,
    /// Serve the dashboard (jobs, frames, workers and datasets in a browser, with a JSON API
    /// and live events) at ADDR (e.g. 127.0.0.1:8080): it asks for the client token
    /// (--token) and serves HTTPS with the API's certificate when --tls-cert is given.
    #[arg(long, value_name = "ADDR", env = "POINTFARM_DASHBOARD_LISTEN")]
    dashboard_listen: Option<String>,
    /// POST a signed JSON event to this http(s) URL whenever a job succeeds, fails or is
    /// cancelled (repeatable). In the configuration file, a `[[serve.webhook]]` table gives one
    /// with its own `url`, `secret_file` or `secret_env`, and `events`.
    #[arg(long = "webhook", value_name = "URL", env = "POINTFARM_WEBHOOK")]
    webhooks: Vec<String>,
    /// The file holding the secret that signs the deliveries of each webhook without one of
    /// its own (`X-Pointfarm-Signature`); its final newline is not part of it.
    #[arg(long, value_name = "FILE", env = "POINTFARM_WEBHOOK_SECRET_FILE")]
    webhook_secret_file: Option<PathBuf>,
    /// Most connections open at once on each listener (default: half the open-file limit,
    /// which the daemon raises to its hard limit at start). Connections that make no
    /// authenticated call within 10 s, or sit idle for 5 minutes, are closed.
    #[arg(long, value_name = "N", env = "POINTFARM_MAX_CONNECTIONS", value_parser = clap::value_parser!(u32).range(16..))]
    max_connections: Option<u32>,
    /// Seconds stopping (SIGTERM, Ctrl-C) waits for calls in flight and the embedded
    /// worker's frame before the daemon exits without them.
    #[arg(long, value_name = "SECONDS", env = "POINTFARM_SHUTDOWN_GRACE", default_value_t = DEFAULT_SHUTDOWN_GRACE.as_secs_f64(), value_parser = parse_shutdown_grace)]
    shutdown_grace: f64,
}

/// Each listener's connection bounds: sized by the open-file limit (raised first), or the
/// operator's `--max-connections`.
fn connection_limits(max_connections: Option<u32>) -> ConnectionLimits {
    let limits = ConnectionLimits::for_open_files(open_files::raise_soft_limit());
    match max_connections {
        Some(max) => {
            let max = max as usize;
            ConnectionLimits {
                max_connections: max,
                max_unadmitted: (max / 4).max(4),
                ..limits
            }
        }
        None => limits,
    }
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
        (Some(cert), Some(key)) => {
            let identity = TlsIdentity {
                cert_pem: read(cert)?,
                key_pem: read(key)?,
            };
            check_identity(&identity)?;
            Some(identity)
        }
        (Some(_), None) => bail!("--tls-cert needs --tls-key, the certificate's private key"),
        (None, Some(_)) => bail!("--tls-key needs --tls-cert, the key's certificate chain"),
        (None, None) => None,
    };
    Ok(ServeOptions {
        access: Access::new(token.as_deref(), worker_token.as_deref()),
        tls,
        insecure: args.insecure,
        health_listen: args.health_listen,
        connection_limits: connection_limits(args.max_connections),
        shutdown_grace: std::time::Duration::from_secs_f64(args.shutdown_grace),
    })
}

/// Refuses a certificate file that holds no certificate, and a key that is not the
/// certificate's, in the words the server would use when it sets up TLS: before anything says
/// the daemon serves.
fn check_identity(identity: &TlsIdentity) -> Result<()> {
    certificate::is_ca_certificate(&identity.cert_pem)
        .map_err(|reason| anyhow!("the TLS certificate (--tls-cert) {reason}"))?;
    endpoint::server_builder()
        .tls_config(endpoint::server_tls(&identity.cert_pem, &identity.key_pem))
        .map_err(|e| {
            anyhow!(
                "the TLS certificate and key (--tls-cert, --tls-key): {}",
                certificate::identity_error(&e)
            )
        })?;
    Ok(())
}

/// Everything that can refuse the start is checked, and every listener bound, before the
/// first line that says what the daemon serves: a refused start prints only its error.
pub fn run(args: ServeArgs) -> Result<()> {
    let options = serve_options(&args)?;
    let runtime = tokio::runtime::Runtime::new().context("starting the async runtime")?;
    let served = runtime.block_on(async move {
        let mut config = DaemonConfig::new(args.data_dir.clone());
        config.data_roots = args.data_roots.clone();
        // Checked here rather than by clap, whose error would repeat a prefix's credentials.
        config.allowed_url_prefixes =
            url_prefixes(&args.allowed_url_prefixes).context("--allow-url-prefix")?;
        config.allowed_output_prefixes =
            output_prefixes(&args.allowed_output_prefixes).context("--allow-output-prefix")?;
        config.store_url = args
            .store_url
            .as_deref()
            .map(store_url)
            .transpose()
            .context("--store-url")?;
        config.store_publish_attempts = args.store_publish_attempts;
        config.max_image_side = args.max_image_side;
        config.max_frames = args.max_frames;
        config.worker_cache_bytes = args.worker_cache_size;
        config.max_upload_bytes = args.max_upload_bytes;
        config.upload_quota_bytes = args.upload_quota_bytes;
        config.job_retention = args
            .job_retention_days
            .map(|days| std::time::Duration::from_secs(u64::from(days) * 86_400));
        config.frame_quota_bytes = args.frame_quota;
        config.recover_state = args.recover_state;
        config.lease_timeout = std::time::Duration::from_secs_f64(args.lease_timeout);
        config.max_frame_attempts = args.max_frame_attempts;
        config.worker_failures_before_blocklist = args.blocklist_after;
        if let Some(bytes) = args.store_memory_budget {
            config.store_build_memory_bytes = bytes;
        }
        config.webhooks = webhook_endpoints(&args.webhooks, args.webhook_secret_file.as_deref())?;
        // Checked before the state is opened, so that a bad tag stops the daemon rather
        // than its worker's restarts.
        let embedded_worker = if args.no_embedded_worker {
            None
        } else {
            Some(embedded_worker_command(&args, &config)?)
        };
        let daemon =
            Daemon::open(config).with_context(|| format!("opening {}", args.data_dir.display()))?;
        let listener = tokio::net::TcpListener::bind(&args.listen)
            .await
            .with_context(|| format!("listening on {}", args.listen))?;
        let address = listener.local_addr()?;
        options.check_exposure(address)?;
        if let Some(address) = &args.metrics_listen {
            let source = daemon.clone();
            let bound = metrics::http::listen(
                address,
                options.connection_limits,
                Arc::new(move || source.metrics_text().map_err(|e| e.to_string())),
            )
            .await?;
            outln!("metrics on http://{bound}/metrics");
        }
        if let Some(address) = &args.dashboard_listen {
            let dashboard_options = DashboardOptions {
                access: options.access.clone(),
                tls: options.tls.clone(),
                insecure: options.insecure,
                connection_limits: options.connection_limits,
            };
            let (bound, scheme) =
                dashboard::listen(address, daemon.clone(), dashboard_options).await?;
            outln!("dashboard on {scheme}://{bound}/");
        }
        match &embedded_worker {
            Some(command) => outln!("embedded worker: {}", command.program.display()),
            None => outln!("no embedded worker: start `pointfarm worker --server ...` to render"),
        }
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
            crate::signals::shutdown_signal(),
        )
        .await
    });
    // A call still blocked in a thread (a hung disk) must not hold the exit: the server has
    // already waited its shutdown grace.
    runtime.shutdown_timeout(std::time::Duration::from_secs(1));
    served
}

/// This binary's `worker` command, rendering with the daemon's settings; its cache lives in
/// the data folder.
fn embedded_worker_command(args: &ServeArgs, config: &DaemonConfig) -> Result<WorkerCommand> {
    let mut command = embedded_worker(config, args.adapter)?;
    checked_tags("--worker-tag", args.worker_tags.iter().map(String::as_str))?;
    for tag in &args.worker_tags {
        command.args.extend(["--tag".into(), tag.into()]);
    }
    if let Some(mib) = args.worker_max_memory_mib {
        command
            .args
            .extend(["--max-memory-mib".into(), mib.to_string().into()]);
    }
    Ok(command)
}

/// `pointfarm worker` as the embedded worker of a daemon with `config` (the supervisor adds
/// the server, the name and the token). Its settings are its arguments: the worker settings
/// of the daemon's environment are not its own.
pub(crate) fn embedded_worker(
    config: &DaemonConfig,
    adapter: AdapterChoice,
) -> Result<WorkerCommand> {
    Ok(WorkerCommand {
        program: std::env::current_exe().context("finding the pointfarm binary")?,
        args: vec![
            "worker".into(),
            "--cache-dir".into(),
            config.data_dir.join("embedded-worker").into(),
            "--cache-gib".into(),
            (config.worker_cache_bytes >> 30).max(1).to_string().into(),
            "--adapter".into(),
            adapter.to_string().into(),
        ],
        env_removed: crate::worker::settings_env(),
    })
}

fn parse_shutdown_grace(value: &str) -> Result<f64, String> {
    parse::seconds_within(value, 0.0..=3600.0)
}

fn parse_lease_timeout(value: &str) -> Result<f64, String> {
    parse::seconds_within(value, 0.1..=3600.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The embedded worker is configured by its arguments alone: the configuration file and
    /// the worker settings of the daemon's environment (meant for a separate worker on the
    /// same host) are not passed on.
    #[test]
    fn the_embedded_worker_does_not_inherit_worker_settings() {
        let config = DaemonConfig::new(PathBuf::from("/srv/pointfarm"));
        let worker = embedded_worker(&config, AdapterChoice::Auto).expect("the command");
        for variable in [
            "POINTFARM_CONFIG",
            "POINTFARM_WORKER_CACHE_DIR",
            "POINTFARM_LOD_ERROR",
            "POINTFARM_MAX_MEMORY_MIB",
            "POINTFARM_METRICS_LISTEN",
        ] {
            assert!(
                worker.env_removed.iter().any(|removed| removed == variable),
                "{variable} is inherited"
            );
        }
        assert!(worker
            .args
            .windows(2)
            .any(|pair| pair[0] == "--cache-dir" && pair[1] == "/srv/pointfarm/embedded-worker"));
    }

    /// `serve --worker-tag` reaches the embedded worker as its `--tag`s; a bad tag is
    /// refused before the daemon starts.
    #[test]
    fn the_embedded_worker_advertises_the_tags_serve_gives_it() {
        use clap::Parser;
        let serve = |tags: &[&str]| {
            let mut argv = vec!["pointfarm", "serve", "--data-dir", "/srv/pointfarm"];
            for tag in tags {
                argv.extend(["--worker-tag", tag]);
            }
            match crate::Cli::try_parse_from(argv).expect("parses").command {
                crate::Command::Serve(args) => *args,
                _ => unreachable!("a serve command"),
            }
        };
        let args = serve(&["site-x", "gpu-a100"]);
        let command = embedded_worker_command(&args, &DaemonConfig::new(args.data_dir.clone()))
            .expect("the command");
        let tags: Vec<&std::ffi::OsStr> = command
            .args
            .windows(2)
            .filter(|pair| pair[0] == "--tag")
            .map(|pair| pair[1].as_os_str())
            .collect();
        assert_eq!(tags, ["site-x", "gpu-a100"]);
        let args = serve(&["no spaces"]);
        let refused = embedded_worker_command(&args, &DaemonConfig::new(args.data_dir.clone()));
        assert!(refused.is_err());
    }
}

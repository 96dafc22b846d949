//! The embedded worker: a worker process (`pointfarm worker`) that the daemon runs and watches
//! over, so that a frame that panics or aborts takes down that process and never the daemon.
//!
//! - The caller gives the command (the daemon does not know its own binary); the supervisor
//!   adds where to connect (loopback), the name and `--supervised`. The token its calls carry
//!   is made for each daemon start and handed over in the environment, never on the command
//!   line; the server knows the embedded worker's calls by it.
//! - Its standard input is a pipe from the daemon: when the daemon exits, however it dies, the
//!   pipe closes and the worker exits at once (the worker crate's
//!   `supervised::exit_when_supervisor_exits`), so no orphan goes on rendering.
//! - Every exit is logged with its status or signal; each frame the process held counts a
//!   failed attempt (`Daemon::embedded_worker_exited`); it is started again after a backoff
//!   that grows while it keeps dying.
//! - Stopping sends SIGTERM: the worker finishes its current frame, hands it in and exits.

use std::ffi::OsString;
use std::net::{IpAddr, Ipv4Addr, Ipv6Addr, SocketAddr};
use std::path::PathBuf;
use std::process::{ExitStatus, Stdio};
use std::sync::Arc;
use std::time::{Duration, Instant};

use tokio::process::{Child, Command};
use tokio::sync::watch;
use tokio::task::JoinHandle;

use crate::service::Daemon;

/// The name of the embedded worker in leases and logs.
pub const EMBEDDED_WORKER_NAME: &str = "embedded";

/// The environment variable that hands the embedded worker its token (`worker --worker-token`).
pub const TOKEN_ENV: &str = "POINTFARM_WORKER_TOKEN";
/// Settings of the daemon's environment that are not the embedded worker's: it speaks
/// plaintext to its own loopback listener, and the daemon's metrics address is the daemon's.
const NOT_INHERITED: [&str; 4] = [
    "POINTFARM_TLS_CA",
    "POINTFARM_SERVER",
    "POINTFARM_WORKER_TOKEN_FILE",
    "POINTFARM_METRICS_LISTEN",
];

/// The first wait before a restart; it doubles on each quick exit up to [`RESTART_MAX`].
const RESTART_FIRST: Duration = Duration::from_millis(250);
const RESTART_MAX: Duration = Duration::from_secs(30);
/// A process that ran this long before exiting is restarted after the first wait again.
const HEALTHY_RUN: Duration = Duration::from_secs(60);

/// How to start a worker process: a program and its arguments (e.g. the `pointfarm` binary and
/// `worker --cache-dir ...`).
#[derive(Debug, Clone)]
pub struct WorkerCommand {
    pub program: PathBuf,
    pub args: Vec<OsString>,
    /// Variables of the daemon's environment the worker does not inherit (its settings come
    /// from `args`), besides those that are never the embedded worker's.
    pub env_removed: Vec<OsString>,
}

/// The running supervisor; [`Supervisor::stop`] ends it and its worker. Dropped without a
/// stop, it kills the worker.
pub struct Supervisor {
    stop: watch::Sender<bool>,
    task: Option<JoinHandle<()>>,
}

impl Supervisor {
    /// Starts the worker process for the daemon serving on `server`; its calls carry `token`.
    pub fn start(
        daemon: Arc<Daemon>,
        command: WorkerCommand,
        server: SocketAddr,
        token: String,
    ) -> Self {
        let (stop, stopped) = watch::channel(false);
        let launch = Launch {
            command,
            server: format!("http://{}", loopback(server)),
            token,
        };
        let task = tokio::spawn(supervise(daemon, launch, stopped));
        Self {
            stop,
            task: Some(task),
        }
    }

    /// Stops the worker (it finishes its current frame first) and waits until it has exited.
    pub async fn stop(mut self) {
        let _ = self.stop.send(true);
        if let Some(task) = self.task.take() {
            if let Err(e) = task.await {
                tracing::error!(error = %e, "the embedded worker's supervisor failed");
            }
        }
    }
}

impl Drop for Supervisor {
    fn drop(&mut self) {
        // The task owns the child, which is killed when the task is dropped.
        if let Some(task) = self.task.take() {
            task.abort();
        }
    }
}

/// What starts one worker process.
struct Launch {
    command: WorkerCommand,
    server: String,
    token: String,
}

impl Launch {
    fn spawn(&self) -> std::io::Result<Child> {
        let mut command = Command::new(&self.command.program);
        for name in NOT_INHERITED {
            command.env_remove(name);
        }
        for name in &self.command.env_removed {
            command.env_remove(name);
        }
        command
            .args(&self.command.args)
            .args(["--server", &self.server, "--name", EMBEDDED_WORKER_NAME])
            .arg("--supervised")
            .env(TOKEN_ENV, &self.token)
            .stdin(Stdio::piped())
            .kill_on_drop(true)
            .spawn()
    }
}

/// Runs worker processes one after the other until `stop` is set.
async fn supervise(daemon: Arc<Daemon>, launch: Launch, mut stop: watch::Receiver<bool>) {
    let mut backoff = RESTART_FIRST;
    while !*stop.borrow() {
        let started = Instant::now();
        match launch.spawn() {
            Ok(child) => {
                let how = run_until_exit(&daemon, child, &mut stop).await;
                let stopping = *stop.borrow();
                count_lost_frames(&daemon, how).await;
                if stopping {
                    return;
                }
            }
            Err(e) => tracing::error!(
                error = %e,
                program = %launch.command.program.display(),
                "cannot start the embedded worker"
            ),
        }
        if started.elapsed() >= HEALTHY_RUN {
            backoff = RESTART_FIRST;
        }
        tracing::info!(wait = ?backoff, "restarting the embedded worker");
        tokio::select! {
            _ = tokio::time::sleep(backoff) => {}
            _ = stop.changed() => {}
        }
        backoff = (backoff * 2).min(RESTART_MAX);
    }
}

/// Counts a failed attempt for each frame the exited worker held (`how` it exited).
async fn count_lost_frames(daemon: &Arc<Daemon>, how: String) {
    let daemon = daemon.clone();
    let counted = tokio::task::spawn_blocking(move || {
        // The video it was making is leased again, as its frames are.
        daemon.embedded_encoder_exited(EMBEDDED_WORKER_NAME, &how)?;
        daemon.embedded_worker_exited(EMBEDDED_WORKER_NAME, &how)
    })
    .await
    .map_err(|e| e.to_string())
    .and_then(|counted| counted.map_err(|e| e.to_string()));
    match counted {
        Ok(0) => {}
        Ok(frames) => tracing::warn!(frames, "each frame it held counts a failed attempt"),
        Err(error) => {
            tracing::error!(%error, "counting the attempts of the embedded worker's frames")
        }
    }
}

/// Waits for the worker to exit, stopping it when `stop` is set; returns how it exited.
async fn run_until_exit(
    daemon: &Daemon,
    mut child: Child,
    stop: &mut watch::Receiver<bool>,
) -> String {
    // Held until the worker has exited: closing it tells the worker to exit.
    let _lifeline = child.stdin.take();
    let pid = child.id().unwrap_or_default();
    daemon.workers.embedded_started();
    tracing::info!(pid, "embedded worker started");
    let status = tokio::select! {
        status = child.wait() => status,
        _ = stop.changed() => {
            tracing::info!(pid, "stopping the embedded worker: its current frame is finished first");
            terminate(&mut child);
            child.wait().await
        }
    };
    daemon.workers.embedded_exited();
    let how = describe_exit(&status);
    match status {
        Ok(status) if status.success() && *stop.borrow() => {
            tracing::info!(pid, "embedded worker stopped")
        }
        _ => tracing::warn!(pid, %how, "embedded worker exited"),
    }
    how
}

/// Asks the worker to stop after its current frame (SIGTERM).
fn terminate(child: &mut Child) {
    #[cfg(unix)]
    {
        let pid = child
            .id()
            .and_then(|id| i32::try_from(id).ok())
            .and_then(rustix::process::Pid::from_raw);
        if let Some(pid) = pid {
            match rustix::process::kill_process(pid, rustix::process::Signal::TERM) {
                Ok(()) => return,
                Err(e) => tracing::warn!(error = %e, "cannot send SIGTERM to the embedded worker"),
            }
        }
    }
    let _ = child.start_kill();
}

/// How a process ended, for logs and failed frames: "exited with status 1", "killed by signal
/// 9 (SIGKILL)".
pub fn describe_exit(status: &std::io::Result<ExitStatus>) -> String {
    let status = match status {
        Ok(status) => status,
        Err(e) => return format!("its exit status is unknown: {e}"),
    };
    #[cfg(unix)]
    {
        use std::os::unix::process::ExitStatusExt;
        if let Some(signal) = status.signal() {
            return match signal_name(signal) {
                Some(name) => format!("killed by signal {signal} ({name})"),
                None => format!("killed by signal {signal}"),
            };
        }
    }
    match status.code() {
        Some(code) => format!("exited with status {code}"),
        None => "exited".into(),
    }
}

/// The names of the signals that end processes (their numbers are the same on Linux and the
/// BSDs).
fn signal_name(signal: i32) -> Option<&'static str> {
    Some(match signal {
        1 => "SIGHUP",
        2 => "SIGINT",
        3 => "SIGQUIT",
        4 => "SIGILL",
        6 => "SIGABRT",
        8 => "SIGFPE",
        9 => "SIGKILL",
        11 => "SIGSEGV",
        13 => "SIGPIPE",
        15 => "SIGTERM",
        _ => return None,
    })
}

/// Where a worker on this machine reaches a server listening on `address` (a wildcard address
/// is reached on loopback).
fn loopback(address: SocketAddr) -> SocketAddr {
    let ip = match address.ip() {
        IpAddr::V4(ip) if ip.is_unspecified() => IpAddr::V4(Ipv4Addr::LOCALHOST),
        IpAddr::V6(ip) if ip.is_unspecified() => IpAddr::V6(Ipv6Addr::LOCALHOST),
        ip => ip,
    };
    SocketAddr::new(ip, address.port())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn wildcard_addresses_are_reached_on_loopback() {
        let cases = [
            ("0.0.0.0:7", "127.0.0.1:7"),
            ("[::]:7", "[::1]:7"),
            ("127.0.0.2:7", "127.0.0.2:7"),
        ];
        for (listen, reached) in cases {
            let listen: SocketAddr = listen.parse().expect("address");
            assert_eq!(loopback(listen).to_string(), reached);
        }
    }

    #[cfg(unix)]
    #[test]
    fn exits_are_described_by_status_or_signal() {
        use std::os::unix::process::ExitStatusExt;
        let cases = [
            (ExitStatus::from_raw(0), "exited with status 0"),
            (ExitStatus::from_raw(3 << 8), "exited with status 3"),
            (ExitStatus::from_raw(9), "killed by signal 9 (SIGKILL)"),
            (ExitStatus::from_raw(6), "killed by signal 6 (SIGABRT)"),
        ];
        for (status, described) in cases {
            assert_eq!(describe_exit(&Ok(status)), described);
        }
    }
}

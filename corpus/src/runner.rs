//! The parent side of a corpus run: every file is loaded by a child process (this binary's
//! `load`), so an abort is seen as an abort rather than the end of the run, with a timeout.
//! While a child runs its `/proc/<pid>/status` is sampled, so a child killed by an abort
//! still has a peak (a lower bound); a child that reports its own peak is exact.

use std::io::Read;
use std::os::unix::process::ExitStatusExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Mutex;
use std::thread;
use std::time::{Duration, Instant};

use crate::child::{exec_peak_kib, CONTAINED, ERROR, LOADED};
use crate::CorpusError;

/// How often a running child's memory is sampled.
const SAMPLE_EVERY: Duration = Duration::from_millis(5);

/// What loading one file gave.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Outcome {
    /// Loaded; the point count.
    Loaded(String),
    /// A clean one-line error; whether it names the file.
    Error {
        message: String,
        names_file: bool,
    },
    /// A decoder panic that ingest contained and reported as an error.
    ContainedPanic(String),
    /// The child died of a panic (exit status 101).
    Panic(String),
    /// The child was killed by a signal (an abort is SIGABRT).
    Abort {
        signal: i32,
        detail: String,
    },
    Timeout,
    /// Anything else: an exit status and output that fit none of the above.
    Unexpected(String),
}

/// One file's run.
#[derive(Debug, Clone)]
pub struct FileRun {
    pub path: PathBuf,
    pub file_len: u64,
    pub outcome: Outcome,
    /// Peak resident memory of the child in KiB.
    pub peak_kib: u64,
    pub elapsed: Duration,
}

impl FileRun {
    /// The memory bound a load must stay within: twice the file's size plus 256 MiB.
    pub fn bound_kib(&self) -> u64 {
        2 * self.file_len.div_ceil(1024) + 256 * 1024
    }
}

/// Runs every file in `files` through `child_exe load FILE`, `jobs` at a time.
pub fn run_files(
    child_exe: &Path,
    files: &[PathBuf],
    timeout: Duration,
    jobs: usize,
    progress: impl Fn(usize, &FileRun) + Sync,
) -> Result<Vec<FileRun>, CorpusError> {
    let next = AtomicUsize::new(0);
    let done = AtomicUsize::new(0);
    let runs = Mutex::new(Vec::with_capacity(files.len()));
    let failure = Mutex::new(None);
    thread::scope(|scope| {
        for _ in 0..jobs.max(1) {
            scope.spawn(|| loop {
                let index = next.fetch_add(1, Ordering::Relaxed);
                let Some(path) = files.get(index) else { break };
                match run_one(child_exe, path, timeout) {
                    Ok(run) => {
                        progress(done.fetch_add(1, Ordering::Relaxed) + 1, &run);
                        runs.lock()
                            .unwrap_or_else(|e| e.into_inner())
                            .push((index, run));
                    }
                    Err(error) => {
                        *failure.lock().unwrap_or_else(|e| e.into_inner()) = Some(error);
                        break;
                    }
                }
            });
        }
    });
    if let Some(error) = failure.into_inner().unwrap_or_else(|e| e.into_inner()) {
        return Err(error);
    }
    let mut runs = runs.into_inner().unwrap_or_else(|e| e.into_inner());
    runs.sort_by_key(|(index, _)| *index);
    Ok(runs.into_iter().map(|(_, run)| run).collect())
}

/// Loads one file in a child, sampling its memory until it exits or the timeout passes.
pub fn run_one(child_exe: &Path, path: &Path, timeout: Duration) -> Result<FileRun, CorpusError> {
    let file_len = path
        .metadata()
        .map_err(|error| CorpusError::io(path, error))?
        .len();
    let started = Instant::now();
    let mut child = Command::new(child_exe)
        .arg("load")
        .arg(path)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .env("RUST_BACKTRACE", "0")
        .spawn()
        .map_err(|error| CorpusError::io(child_exe, error))?;
    let stdout = drain(child.stdout.take());
    let stderr = drain(child.stderr.take());
    let status_file = PathBuf::from(format!("/proc/{}/status", child.id()));
    let program = child_exe
        .file_name()
        .map(|name| name.to_string_lossy().into_owned())
        .unwrap_or_default();
    let mut sampled_kib = 0;
    let status = loop {
        if let Some(peak) = exec_peak_kib(&status_file, &program) {
            sampled_kib = sampled_kib.max(peak);
        }
        if let Some(status) = child
            .try_wait()
            .map_err(|error| CorpusError::io(path, error))?
        {
            break Some(status);
        }
        if started.elapsed() > timeout {
            kill(&mut child);
            break None;
        }
        thread::sleep(SAMPLE_EVERY);
    };
    let elapsed = started.elapsed();
    let stdout = stdout.join().unwrap_or_default();
    let stderr = stderr.join().unwrap_or_default();
    let report = stdout.lines().last().unwrap_or("");
    let reported_kib = report
        .split_whitespace()
        .nth(1)
        .and_then(|peak| peak.parse().ok())
        .unwrap_or(0);
    let outcome = match status {
        None => Outcome::Timeout,
        Some(status) => classify(path, status, report, &stderr),
    };
    Ok(FileRun {
        path: path.to_owned(),
        file_len,
        outcome,
        peak_kib: sampled_kib.max(reported_kib),
        elapsed,
    })
}

fn kill(child: &mut Child) {
    // Already gone if it exited between the last poll and now; either way it is reaped.
    let _ = child.kill();
    let _ = child.wait();
}

/// Reads a pipe to its end on a thread of its own, so a chatty child never blocks on it.
fn drain(pipe: Option<impl Read + Send + 'static>) -> thread::JoinHandle<String> {
    thread::spawn(move || {
        let mut text = String::new();
        if let Some(mut pipe) = pipe {
            let mut bytes = Vec::new();
            let _ = pipe.read_to_end(&mut bytes);
            text = String::from_utf8_lossy(&bytes).into_owned();
        }
        text
    })
}

fn classify(path: &Path, status: ExitStatus, report: &str, stderr: &str) -> Outcome {
    let (word, detail) = match report.split_once(' ') {
        Some((word, rest)) => (word, rest.split_once(' ').map_or("", |(_, detail)| detail)),
        None => (report, ""),
    };
    let last_stderr_line = || stderr.lines().last().unwrap_or("").to_owned();
    if let Some(signal) = status.signal() {
        let detail = stderr
            .lines()
            .find(|line| !line.trim().is_empty())
            .unwrap_or("")
            .to_owned();
        return Outcome::Abort { signal, detail };
    }
    match (status.code(), word) {
        (Some(0), LOADED) => Outcome::Loaded(detail.to_owned()),
        (Some(crate::child::ERROR_EXIT), ERROR) => {
            let name = path.file_name().map(|name| name.to_string_lossy());
            Outcome::Error {
                names_file: name.is_some_and(|name| detail.contains(name.as_ref())),
                message: detail.to_owned(),
            }
        }
        (Some(crate::child::ERROR_EXIT), CONTAINED) => Outcome::ContainedPanic(detail.to_owned()),
        (Some(101), _) => Outcome::Panic(if detail.is_empty() {
            last_stderr_line()
        } else {
            detail.to_owned()
        }),
        (code, _) => Outcome::Unexpected(format!(
            "exit status {code:?}: {report} {}",
            last_stderr_line()
        )),
    }
}

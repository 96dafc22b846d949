//! The outputs of jobs on their way to object storage, below the daemon: the operator's
//! output prefixes and a submission's output URL checked, the record of an output waiting to
//! be sent, and the thread that sends each with retries and reports how it went
//! (`outputs.rs` ties it to the daemon's jobs and its state database).
//!
//! Waiting outputs live in the state database, not in memory: the thread takes them one at
//! a time in the order they were queued and is woken when one is added, so the scheduler never
//! waits for object storage, memory stays bounded however many wait, and none is refused for
//! want of room. The outputs it finished are flushed to disk together, once per batch
//! (`state/outputs.rs` says why that loses none).

use std::path::PathBuf;
use std::sync::mpsc::{self, Receiver, RecvTimeoutError, SyncSender};
use std::sync::{Mutex, PoisonError};
use std::time::{Duration, Instant};

use pointfarm_render::remote::{AllowedPrefixes, ObjectUrl, RemoteClient, RemoteSettings};
use serde::{Deserialize, Serialize};

use crate::error::DaemonError;

/// Tries of one output before its failure is recorded; each request is retried by the
/// storage client too.
pub const OUTPUT_ATTEMPTS: u32 = 4;
/// The wait before the second try; it doubles after each.
pub const OUTPUT_FIRST_BACKOFF: Duration = Duration::from_millis(500);
/// Failures kept per job, so that a job record stays small whatever its frame count.
pub const MAX_OUTPUT_ERRORS: usize = 16;
/// How long the idle upload thread waits for a wake-up before looking at the records again
/// (after a state database that could not be read).
const IDLE_RECHECK: Duration = Duration::from_secs(30);
/// The most finished outputs, and the longest time since the first of them, before the
/// upload thread flushes them; it flushes sooner whenever no output waits.
const FLUSH_EVERY_OUTPUTS: u32 = 64;
const FLUSH_EVERY: Duration = Duration::from_secs(1);

/// What was written to a job's output URL.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct JobOutputs {
    /// Outputs uploaded (frames and the video).
    pub uploaded: u32,
    /// Outputs queued and not yet uploaded or failed.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub pending: u32,
    /// The first `MAX_OUTPUT_ERRORS` outputs that could not be, each naming its URL and why.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub errors: Vec<String>,
}

fn is_zero(count: &u32) -> bool {
    *count == 0
}

impl JobOutputs {
    pub fn is_empty(&self) -> bool {
        self.uploaded == 0 && self.pending == 0 && self.errors.is_empty()
    }

    /// Counts a pending output as uploaded, or keeps why it was not.
    pub fn record(&mut self, outcome: Result<(), String>) {
        self.pending = self.pending.saturating_sub(1);
        match outcome {
            Ok(()) => self.uploaded += 1,
            Err(reason) => self.record_failure(reason),
        }
    }

    /// Keeps why an output was not uploaded, up to `MAX_OUTPUT_ERRORS`.
    pub fn record_failure(&mut self, reason: String) {
        if self.errors.len() < MAX_OUTPUT_ERRORS {
            self.errors.push(reason);
        }
    }
}

/// One output waiting to be written, as the state database keeps it: a stored file of a job
/// and the URL it goes to (an output URL holds no credentials).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct PendingOutput {
    pub job_id: String,
    /// The output's name under the job's output URL: a frame's or the video's file name.
    pub name: String,
    /// The file the daemon stored.
    pub file: PathBuf,
    /// Where it goes.
    pub url: String,
}

/// What the upload thread does next.
pub(crate) enum NextOutput {
    /// Send this output, the record `key`.
    Send(u64, PendingOutput),
    /// Nothing waits: sleep until woken.
    Idle,
    /// The daemon is gone.
    Stop,
}

/// Checks the operator's output prefixes (`serve --allow-output-prefix`): `s3://` URLs, each
/// named in the error that refuses it.
pub fn output_prefixes<S: AsRef<str>>(prefixes: &[S]) -> Result<AllowedPrefixes, DaemonError> {
    for prefix in prefixes {
        let url = ObjectUrl::parse(prefix.as_ref())
            .map_err(|e| DaemonError::invalid("allowed output prefix", e.to_string()))?;
        if !url.is_object_storage() {
            return Err(DaemonError::invalid(
                "allowed output prefix",
                format!(
                    "{url}: outputs are written to object storage (s3://, gs:// or az://) only"
                ),
            ));
        }
    }
    Ok(AllowedPrefixes::new(prefixes)?)
}

/// A submission's `output_url`, checked for what needs no server: an `s3://` prefix without
/// credentials or a query; empty is none.
pub fn check_output_url(field: &str, text: &str) -> Result<Option<String>, DaemonError> {
    if text.is_empty() {
        return Ok(None);
    }
    let url = ObjectUrl::parse(text).map_err(|e| DaemonError::invalid(field, e.to_string()))?;
    if !url.is_object_storage() {
        return Err(DaemonError::invalid(
            field,
            format!("{url}: outputs are written to object storage (s3://, gs:// or az://bucket/prefix) only"),
        ));
    }
    Ok(Some(url.to_string()))
}

/// The thread that sends the waiting outputs; idle on a daemon with no output prefix allowed.
#[derive(Default)]
pub struct OutputUploads {
    wake: Mutex<Option<SyncSender<()>>>,
}

impl OutputUploads {
    /// Starts the upload thread: `next` gives it the output after the record it names,
    /// `done` takes each output's record key, job and outcome and says whether to go on, and
    /// `flush` makes the outputs done so far durable, once per batch of them.
    pub(crate) fn start(
        &self,
        settings: RemoteSettings,
        next: impl Fn(Option<u64>) -> NextOutput + Send + 'static,
        done: impl Fn(u64, &PendingOutput, Result<(), String>) -> bool + Send + 'static,
        flush: impl Fn() + Send + 'static,
    ) -> Result<(), DaemonError> {
        let client = RemoteClient::new(settings)?;
        // One wake-up waiting is enough: the thread reads every record after it.
        let (sender, receiver) = mpsc::sync_channel(1);
        std::thread::Builder::new()
            .name("pointfarm-outputs".into())
            .spawn(move || send_outputs(&client, &receiver, next, done, flush))
            .map_err(|e| DaemonError::Internal(format!("starting the output uploads: {e}")))?;
        *self.wake.lock().unwrap_or_else(PoisonError::into_inner) = Some(sender);
        Ok(())
    }

    /// Whether the thread runs (this server writes outputs by URL).
    pub(crate) fn started(&self) -> bool {
        self.wake
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .is_some()
    }

    /// Tells the thread an output was recorded; never waits.
    pub(crate) fn wake(&self) {
        if let Some(wake) = self
            .wake
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .as_ref()
        {
            // A wake-up already waiting will do as well.
            let _ = wake.try_send(());
        }
    }
}

/// The upload thread: sends each recorded output in order, with retries, until the daemon
/// is gone, flushing those done when [`FLUSH_EVERY_OUTPUTS`] are, when the first of them
/// was done [`FLUSH_EVERY`] ago, and whenever none waits.
fn send_outputs(
    client: &RemoteClient,
    wake: &Receiver<()>,
    next: impl Fn(Option<u64>) -> NextOutput,
    done: impl Fn(u64, &PendingOutput, Result<(), String>) -> bool,
    flush: impl Fn(),
) {
    let mut after = None;
    // Outputs done and not flushed yet, and when the first of them was.
    let mut unflushed: Option<(u32, Instant)> = None;
    loop {
        let next = next(after);
        if let Some((count, since)) = unflushed {
            let idle = !matches!(next, NextOutput::Send(..));
            if idle || count >= FLUSH_EVERY_OUTPUTS || since.elapsed() >= FLUSH_EVERY {
                flush();
                unflushed = None;
            }
        }
        match next {
            NextOutput::Send(key, output) => {
                after = Some(key);
                let outcome = send_with_retries(client, &output);
                if !done(key, &output, outcome) {
                    return;
                }
                unflushed.get_or_insert((0, Instant::now())).0 += 1;
            }
            NextOutput::Idle => match wake.recv_timeout(IDLE_RECHECK) {
                Ok(()) | Err(RecvTimeoutError::Timeout) => {}
                Err(RecvTimeoutError::Disconnected) => return,
            },
            NextOutput::Stop => return,
        }
    }
}

fn send_with_retries(client: &RemoteClient, output: &PendingOutput) -> Result<(), String> {
    let url = ObjectUrl::parse(&output.url).map_err(|e| format!("{}: {e}", output.url))?;
    let mut backoff = OUTPUT_FIRST_BACKOFF;
    let mut attempt = 1;
    loop {
        match send(client, &output.file, &url) {
            Ok(()) => return Ok(()),
            Err(error) if attempt >= OUTPUT_ATTEMPTS => {
                return Err(format!("{error} (after {attempt} tries)"))
            }
            Err(error) => {
                tracing::debug!(%url, %error, attempt, "an output upload failed; trying again");
                std::thread::sleep(backoff);
                backoff *= 2;
                attempt += 1;
            }
        }
    }
}

/// One try: a frame (small) in one request, a larger file by a multipart upload.
fn send(client: &RemoteClient, file: &std::path::Path, url: &ObjectUrl) -> Result<(), String> {
    let reading = |e: std::io::Error| format!("{url}: reading {}: {e}", file.display());
    let size = std::fs::metadata(file).map_err(reading)?.len();
    if size <= client.settings().upload_part_bytes as u64 {
        let bytes = std::fs::read(file).map_err(reading)?;
        client.put(url, bytes).map_err(|e| e.to_string())
    } else {
        client
            .upload_file(file, url)
            .map(drop)
            .map_err(|e| e.to_string())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_output_url_is_an_s3_prefix_or_nothing() {
        assert_eq!(check_output_url("output_url", "").expect("none"), None);
        assert_eq!(
            check_output_url("output_url", "s3://renders/farm/job-a")
                .expect("s3")
                .as_deref(),
            Some("s3://renders/farm/job-a")
        );
        for refused in [
            "https://example.com/renders/",
            "file:///tmp/renders",
            "s3://renders/x?X-Amz-Signature=1",
            "ftp://renders/x",
        ] {
            let error = check_output_url("output_url", refused).expect_err(refused);
            assert!(
                matches!(error, DaemonError::InvalidArgument { ref field, .. } if field == "output_url"),
                "{refused}: {error:?}"
            );
        }
    }

    #[test]
    fn the_outputs_done_are_flushed_once_per_batch_not_once_each() {
        use std::cell::{Cell, RefCell};
        // Outputs whose URL is refused before any request, so that each is done at once.
        const OUTPUTS: u64 = 100;
        let client = RemoteClient::new(RemoteSettings::default()).expect("client");
        let (sender, receiver) = mpsc::sync_channel::<()>(1);
        let sender = RefCell::new(Some(sender));
        let (done, flushes) = (Cell::new(0u64), RefCell::new(Vec::new()));
        let next = |after: Option<u64>| {
            let key = after.map_or(0, |key| key + 1);
            if key == OUTPUTS {
                // Nothing waits, and the waker goes: the thread ends.
                sender.borrow_mut().take();
                return NextOutput::Idle;
            }
            NextOutput::Send(
                key,
                PendingOutput {
                    job_id: "job".into(),
                    name: format!("frame_{key:05}.png"),
                    file: "/nowhere.png".into(),
                    url: "not a URL".into(),
                },
            )
        };
        let record = |_: u64, _: &PendingOutput, outcome: Result<(), String>| {
            assert!(outcome.is_err());
            done.set(done.get() + 1);
            true
        };
        let flush = || flushes.borrow_mut().push(done.get());
        send_outputs(&client, &receiver, next, record, flush);
        assert_eq!(done.get(), OUTPUTS);
        // A full batch, then the rest as the queue ran dry.
        assert_eq!(*flushes.borrow(), [u64::from(FLUSH_EVERY_OUTPUTS), OUTPUTS]);
    }

    #[test]
    fn the_operators_output_prefixes_are_s3_urls() {
        let allowed = output_prefixes(&["s3://renders/farm"]).expect("allowed");
        let url = ObjectUrl::parse("s3://renders/farm/job-a/frame_00000.png").expect("url");
        assert!(allowed.check(&url).is_ok());
        let error = output_prefixes(&["s3://renders/farm", "https://example.com/out/"])
            .expect_err("not s3")
            .to_string();
        assert!(error.contains("https://example.com/out/"), "{error}");
    }
}

//! The queue of a job's outputs on their way to object storage, below the daemon: the
//! operator's output prefixes and a submission's output URL checked, and the thread that
//! sends each stored file with retries and reports how it went (`outputs.rs` ties it to the
//! daemon's jobs). A stored frame is only offered to the bounded queue, so the scheduler never
//! waits for object storage.

use std::path::PathBuf;
use std::sync::mpsc::{self, Receiver, SyncSender, TrySendError};
use std::sync::{Mutex, PoisonError};
use std::time::Duration;

use pointfarm_render::remote::{AllowedPrefixes, ObjectUrl, RemoteClient, RemoteSettings, UrlKind};
use serde::{Deserialize, Serialize};

use crate::error::DaemonError;

/// Uploads waiting for the upload thread; past this, a stored frame's upload is recorded as
/// refused rather than wait.
pub const OUTPUT_QUEUE_CAPACITY: usize = 1024;
/// Tries of one output before its failure is recorded; each request is retried by the
/// storage client too.
pub const OUTPUT_ATTEMPTS: u32 = 4;
/// The wait before the second try; it doubles after each.
pub const OUTPUT_FIRST_BACKOFF: Duration = Duration::from_millis(500);
/// Failures kept per job, so that a job record stays small whatever its frame count.
pub const MAX_OUTPUT_ERRORS: usize = 16;

/// What was written to a job's output URL.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct JobOutputs {
    /// Outputs uploaded (frames and the video).
    pub uploaded: u32,
    /// The first `MAX_OUTPUT_ERRORS` outputs that could not be, each naming its URL and why.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub errors: Vec<String>,
}

impl JobOutputs {
    pub fn is_empty(&self) -> bool {
        self.uploaded == 0 && self.errors.is_empty()
    }
}

/// Checks the operator's output prefixes (`serve --allow-output-prefix`): `s3://` URLs, each
/// named in the error that refuses it.
pub fn output_prefixes<S: AsRef<str>>(prefixes: &[S]) -> Result<AllowedPrefixes, DaemonError> {
    for prefix in prefixes {
        let url = ObjectUrl::parse(prefix.as_ref())
            .map_err(|e| DaemonError::invalid("allowed output prefix", e.to_string()))?;
        if !matches!(url.kind(), UrlKind::S3 { .. }) {
            return Err(DaemonError::invalid(
                "allowed output prefix",
                format!("{url}: outputs are written to object storage (s3://) only"),
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
    if !matches!(url.kind(), UrlKind::S3 { .. }) {
        return Err(DaemonError::invalid(
            field,
            format!("{url}: outputs are written to object storage (s3://bucket/prefix) only"),
        ));
    }
    Ok(Some(url.to_string()))
}

/// One output to write: a stored file of a job and the URL it goes to.
pub(crate) struct OutputUpload {
    pub job_id: String,
    pub file: PathBuf,
    pub url: ObjectUrl,
}

/// The queue of uploads and the thread that sends them; idle on a daemon with no output
/// prefix allowed.
#[derive(Default)]
pub struct OutputUploads {
    queue: Mutex<Option<SyncSender<OutputUpload>>>,
}

impl OutputUploads {
    /// Starts the upload thread, which calls `done` with each upload's job and outcome.
    pub(crate) fn start(
        &self,
        settings: RemoteSettings,
        done: impl Fn(&str, Result<(), String>) -> bool + Send + 'static,
    ) -> Result<(), DaemonError> {
        let client = RemoteClient::new(settings)?;
        let (sender, receiver) = mpsc::sync_channel(OUTPUT_QUEUE_CAPACITY);
        std::thread::Builder::new()
            .name("pointfarm-outputs".into())
            .spawn(move || send_outputs(&client, &receiver, done))
            .map_err(|e| DaemonError::Internal(format!("starting the output uploads: {e}")))?;
        *self.queue.lock().unwrap_or_else(PoisonError::into_inner) = Some(sender);
        Ok(())
    }

    /// Offers `upload` to the queue without waiting; the error says why it will not be sent.
    pub(crate) fn offer(&self, upload: OutputUpload) -> Result<(), String> {
        let queue = self.queue.lock().unwrap_or_else(PoisonError::into_inner);
        let shown = upload.url.to_string();
        let no_uploads = || format!("{shown}: not uploaded: this server writes no outputs by URL");
        match queue.as_ref() {
            None => Err(no_uploads()),
            Some(queue) => match queue.try_send(upload) {
                Ok(()) => Ok(()),
                Err(TrySendError::Full(_)) => Err(format!(
                    "{shown}: not uploaded: {OUTPUT_QUEUE_CAPACITY} uploads were already waiting"
                )),
                Err(TrySendError::Disconnected(_)) => Err(no_uploads()),
            },
        }
    }
}

/// The upload thread: sends each output, with retries, until `done` says to stop.
fn send_outputs(
    client: &RemoteClient,
    queue: &Receiver<OutputUpload>,
    done: impl Fn(&str, Result<(), String>) -> bool,
) {
    while let Ok(upload) = queue.recv() {
        let outcome = send_with_retries(client, &upload);
        if !done(&upload.job_id, outcome) {
            return;
        }
    }
}
fn send_with_retries(client: &RemoteClient, upload: &OutputUpload) -> Result<(), String> {
    let mut backoff = OUTPUT_FIRST_BACKOFF;
    let mut attempt = 1;
    loop {
        match send(client, upload) {
            Ok(()) => return Ok(()),
            Err(error) if attempt >= OUTPUT_ATTEMPTS => {
                return Err(format!("{error} (after {attempt} tries)"))
            }
            Err(error) => {
                tracing::debug!(url = %upload.url, %error, attempt, "an output upload failed; trying again");
                std::thread::sleep(backoff);
                backoff *= 2;
                attempt += 1;
            }
        }
    }
}

/// One try: a frame (small) in one request, a larger file by a multipart upload.
fn send(client: &RemoteClient, upload: &OutputUpload) -> Result<(), String> {
    let size = std::fs::metadata(&upload.file)
        .map_err(|e| format!("{}: reading {}: {e}", upload.url, upload.file.display()))?
        .len();
    if size <= client.settings().upload_part_bytes as u64 {
        let bytes = std::fs::read(&upload.file)
            .map_err(|e| format!("{}: reading {}: {e}", upload.url, upload.file.display()))?;
        client.put(&upload.url, bytes).map_err(|e| e.to_string())
    } else {
        client
            .upload_file(&upload.file, &upload.url)
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

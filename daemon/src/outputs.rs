//! A job's outputs written where its users are: each stored final frame (and the video, once
//! made) uploaded under the object-storage prefix the job names (`JobSpec::output_url`),
//! which must lie under one of the operator's output prefixes. More `Daemon` methods.
//!
//! Uploads run on a thread of their own from a bounded queue: storing a frame only offers it
//! to the queue, so the scheduler never waits for object storage. An upload is tried again
//! with a growing backoff; one that still fails, or that finds the queue full, is recorded
//! in the job (`JobOutputs::errors`). The frame is stored by the daemon first either way, so
//! it stays fetchable from it.

use std::path::{Path, PathBuf};
use std::sync::mpsc::{self, Receiver, SyncSender, TrySendError};
use std::sync::{Mutex, PoisonError, Weak};
use std::time::Duration;

use pointfarm_render::remote::{AllowedPrefixes, ObjectUrl, RemoteClient, RemoteError, UrlKind};
use serde::{Deserialize, Serialize};

use crate::error::DaemonError;
use crate::model::{Job, JobSpec};
use crate::service::{Daemon, DaemonConfig};

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
struct OutputUpload {
    job_id: String,
    file: PathBuf,
    url: ObjectUrl,
}

/// The queue of uploads and the thread that sends them; idle on a daemon with no output
/// prefix allowed.
#[derive(Default)]
pub struct OutputUploads {
    queue: Mutex<Option<SyncSender<OutputUpload>>>,
}

impl OutputUploads {
    /// Starts the upload thread of `daemon`, when its operator allows output prefixes.
    pub(crate) fn start(daemon: &std::sync::Arc<Daemon>) -> Result<(), DaemonError> {
        let config: &DaemonConfig = &daemon.config;
        if config.allowed_output_prefixes.prefixes().is_empty() {
            return Ok(());
        }
        let shown: Vec<&str> = config
            .allowed_output_prefixes
            .prefixes()
            .iter()
            .map(ObjectUrl::as_str)
            .collect();
        tracing::info!(prefixes = %shown.join(", "), "job outputs may be written by URL");
        let client = RemoteClient::new(config.remote_settings.clone())?;
        let (sender, receiver) = mpsc::sync_channel(OUTPUT_QUEUE_CAPACITY);
        let owner = std::sync::Arc::downgrade(daemon);
        std::thread::Builder::new()
            .name("pointfarm-outputs".into())
            .spawn(move || send_outputs(&owner, &client, &receiver))
            .map_err(|e| DaemonError::Internal(format!("starting the output uploads: {e}")))?;
        *daemon
            .outputs
            .queue
            .lock()
            .unwrap_or_else(PoisonError::into_inner) = Some(sender);
        Ok(())
    }
}

impl Daemon {
    /// Refuses a job whose output URL is not under the operator's output prefixes, naming
    /// the rule (PERMISSION_DENIED).
    pub fn check_job_output(&self, spec: &JobSpec) -> Result<(), DaemonError> {
        let Some(text) = &spec.output_url else {
            return Ok(());
        };
        let url = ObjectUrl::parse(text)
            .map_err(|e| DaemonError::invalid("output_url", e.to_string()))?;
        self.config
            .allowed_output_prefixes
            .check(&url)
            .map_err(|e| match e {
                RemoteError::NotAllowed { url, rule } => DaemonError::PermissionDenied(format!(
                    "output_url {url} is not under an allowed output prefix (serve \
                     --allow-output-prefix): {rule}"
                )),
                other => DaemonError::from(other),
            })
    }

    /// Offers the stored final frame `index` of `job` to the upload queue when the job names
    /// an output URL; never waits. Called under the scheduling lock, as a frame is stored.
    pub fn enqueue_frame_output(&self, job: &Job, index: u32) {
        let file = self.config.frame_path(&job.id, index);
        self.enqueue_output(job, &file, &format!("frame_{index:05}.png"));
    }

    /// Offers the stored video of `job` to the upload queue, as `enqueue_frame_output` does.
    pub fn enqueue_video_output(&self, job: &Job, file: &Path) {
        let name = file.file_name().unwrap_or_default().to_string_lossy();
        self.enqueue_output(job, file, &name);
    }

    fn enqueue_output(&self, job: &Job, file: &Path, name: &str) {
        let Some(prefix) = &job.spec.output_url else {
            return;
        };
        let url = match ObjectUrl::parse(prefix).and_then(|prefix| prefix.join(name)) {
            Ok(url) => url,
            Err(error) => return self.record_output_locked(&job.id, Err(error.to_string())),
        };
        let upload = OutputUpload {
            job_id: job.id.clone(),
            file: file.to_owned(),
            url,
        };
        let queue = self
            .outputs
            .queue
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        let shown = upload.url.to_string();
        let no_uploads = || format!("{shown}: not uploaded: this server writes no outputs by URL");
        let refused = match queue.as_ref() {
            None => no_uploads(),
            Some(queue) => match queue.try_send(upload) {
                Ok(()) => return,
                Err(TrySendError::Full(_)) => format!(
                    "{shown}: not uploaded: {OUTPUT_QUEUE_CAPACITY} uploads were already waiting"
                ),
                Err(TrySendError::Disconnected(_)) => no_uploads(),
            },
        };
        drop(queue);
        self.record_output_locked(&job.id, Err(refused));
    }

    /// Counts an output uploaded, or keeps why it was not, in its job, under the scheduling
    /// lock as every other change of a job is, so that none is lost.
    fn record_output(&self, job_id: &str, outcome: Result<(), String>) {
        match self.scheduling() {
            Ok(_scheduling) => self.record_output_locked(job_id, outcome),
            Err(error) => tracing::warn!(job = %job_id, %error, "recording a job output"),
        }
    }

    /// `record_output` for a caller that holds the scheduling lock; a job gone meanwhile is
    /// passed over, and watchers are told.
    fn record_output_locked(&self, job_id: &str, outcome: Result<(), String>) {
        if let Err(reason) = &outcome {
            tracing::warn!(job = %job_id, %reason, "a job output was not uploaded");
        }
        let recorded = self.state.update_job(job_id, |job| match outcome {
            Ok(()) => job.outputs.uploaded += 1,
            Err(reason) => {
                if job.outputs.errors.len() < MAX_OUTPUT_ERRORS {
                    job.outputs.errors.push(reason);
                }
            }
        });
        match recorded {
            Ok(Some(job)) => self.publish(&job, None),
            Ok(None) => {}
            Err(error) => tracing::warn!(job = %job_id, %error, "recording a job output"),
        }
    }
}

/// The upload thread: sends each output, with retries, until the daemon is gone.
fn send_outputs(owner: &Weak<Daemon>, client: &RemoteClient, queue: &Receiver<OutputUpload>) {
    while let Ok(upload) = queue.recv() {
        let outcome = send_with_retries(client, &upload);
        let Some(daemon) = owner.upgrade() else {
            return;
        };
        daemon.record_output(&upload.job_id, outcome);
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

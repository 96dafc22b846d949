//! A job's outputs written where its users are: each stored final frame (and the video, once
//! made) uploaded under the object-storage prefix the job names (`JobSpec::output_url`),
//! which must lie under one of the operator's output prefixes. More `Daemon` methods;
//! the queue and its thread are `output_queue.rs`.
//!
//! Uploads run on a thread of their own from a bounded queue: storing a frame only offers it
//! to the queue, so the scheduler never waits for object storage. An upload is tried again
//! with a growing backoff; one that still fails, or that finds the queue full, is recorded
//! in the job (`JobOutputs::errors`). The frame is stored by the daemon first either way, so
//! it stays fetchable from it.

use std::path::Path;
use std::sync::Arc;

use pointfarm_render::remote::{ObjectUrl, RemoteError};

use crate::error::DaemonError;
use crate::model::{Job, JobSpec};
use crate::output_queue::{OutputUpload, MAX_OUTPUT_ERRORS};
use crate::service::Daemon;

impl Daemon {
    /// Starts the upload thread, when its operator allows output prefixes.
    pub(crate) fn start_output_uploads(self: &Arc<Self>) -> Result<(), DaemonError> {
        let daemon = self;
        let config = &daemon.config;
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
        let owner = Arc::downgrade(daemon);
        daemon
            .outputs
            .start(config.remote_settings.clone(), move |job_id, outcome| {
                let Some(daemon) = owner.upgrade() else {
                    return false;
                };
                daemon.record_output(job_id, outcome);
                true
            })
    }

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
        if let Err(refused) = self.outputs.offer(upload) {
            self.record_output_locked(&job.id, Err(refused));
        }
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

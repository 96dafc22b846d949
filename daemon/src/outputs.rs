//! A job's outputs written where its users are: each stored final frame (and the video, once
//! made) uploaded under the object-storage prefix the job names (`JobSpec::output_url`),
//! which must lie under one of the operator's output prefixes. More `Daemon` methods;
//! the queue and its thread are `output_queue.rs`.
//!
//! Storing a frame records its output as pending in the state database and wakes the upload
//! thread, so the scheduler never waits for object storage, and a daemon stopped (even by
//! `kill -9`) resumes every pending output when it starts again. An upload is tried again
//! with a growing backoff; one that still fails is recorded in the job
//! (`JobOutputs::errors`), as is one whose stored file is gone by then. The frame is stored
//! by the daemon first either way, so it stays fetchable from it.

use std::path::Path;
use std::sync::Arc;

use pointfarm_render::remote::{ObjectUrl, RemoteError};

use crate::error::DaemonError;
use crate::model::{Job, JobSpec};
use crate::output_queue::{NextOutput, PendingOutput};
use crate::service::Daemon;

impl Daemon {
    /// Starts the upload thread, when its operator allows output prefixes, after going over
    /// the outputs a previous run left pending: one whose stored file is gone, or whose URL
    /// is no longer allowed, is recorded as failed; the thread sends the rest.
    pub(crate) fn start_output_uploads(self: &Arc<Self>) -> Result<(), DaemonError> {
        let daemon = self;
        let config = &daemon.config;
        let allowed = !config.allowed_output_prefixes.prefixes().is_empty();
        if allowed {
            let shown: Vec<&str> = config
                .allowed_output_prefixes
                .prefixes()
                .iter()
                .map(ObjectUrl::as_str)
                .collect();
            tracing::info!(prefixes = %shown.join(", "), "job outputs may be written by URL");
        }
        let resumed = daemon.check_pending_outputs(allowed)?;
        if resumed > 0 {
            tracing::info!("resumed {resumed} pending output upload(s)");
        }
        if !allowed {
            return Ok(());
        }
        let (reader, owner) = (Arc::downgrade(daemon), Arc::downgrade(daemon));
        let flusher = Arc::downgrade(daemon);
        daemon.outputs.start(
            config.remote_settings.clone(),
            move |after| {
                let Some(daemon) = reader.upgrade() else {
                    return NextOutput::Stop;
                };
                match daemon.state.pending_output_after(after) {
                    Ok(Some((key, output))) => NextOutput::Send(key, output),
                    Ok(None) => NextOutput::Idle,
                    Err(error) => {
                        tracing::warn!(%error, "reading the pending outputs");
                        NextOutput::Idle
                    }
                }
            },
            move |key, output, outcome| {
                let Some(daemon) = owner.upgrade() else {
                    return false;
                };
                daemon.finish_output(key, output, outcome);
                true
            },
            move || {
                if let Some(daemon) = flusher.upgrade() {
                    if let Err(error) = daemon.state.flush() {
                        tracing::warn!(%error, "flushing the finished job outputs");
                    }
                }
            },
        )
    }

    /// Records as failed each pending output that cannot be sent (its stored file gone, its
    /// URL not allowed, or no uploads on this server) and returns how many remain to send.
    fn check_pending_outputs(&self, allowed: bool) -> Result<usize, DaemonError> {
        let mut remaining = 0;
        let mut after = None;
        while let Some((key, output)) = self.state.pending_output_after(after)? {
            after = Some(key);
            let refused = if !allowed {
                Some(format!(
                    "{}: not uploaded: this server writes no outputs by URL",
                    output.url
                ))
            } else if !output.file.is_file() {
                Some(format!(
                    "{}: not uploaded: its stored file {} no longer exists",
                    output.url,
                    output.file.display()
                ))
            } else {
                ObjectUrl::parse(&output.url)
                    .map_err(|e| e.to_string())
                    .and_then(|url| {
                        self.config
                            .allowed_output_prefixes
                            .check(&url)
                            .map_err(|e| e.to_string())
                    })
                    .err()
                    .map(|reason| format!("{}: not uploaded: {reason}", output.url))
            };
            match refused {
                Some(reason) => self.finish_output(key, &output, Err(reason)),
                None => remaining += 1,
            }
        }
        Ok(remaining)
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
    /// an output URL; never waits. Called under the scheduling lock, as a frame is stored,
    /// before the frame is marked done: that flush makes the output's record durable too.
    pub fn enqueue_frame_output(&self, job: &Job, index: u32) {
        let file = self.config.frame_path(&job.id, index);
        self.enqueue_output(job, &file, &format!("frame_{index:05}.png"));
    }

    /// Offers the stored video of `job` to the upload queue, as `enqueue_frame_output` does,
    /// and flushes its record, which no other flush follows.
    pub fn enqueue_video_output(&self, job: &Job, file: &Path) {
        let name = file.file_name().unwrap_or_default().to_string_lossy();
        if self.enqueue_output(job, file, &name) {
            if let Err(error) = self.state.flush() {
                tracing::warn!(job = %job.id, %error, "flushing a job's video output");
            }
        }
    }

    /// Queues the output `name` of `job`; whether a record was written.
    fn enqueue_output(&self, job: &Job, file: &Path, name: &str) -> bool {
        let Some(prefix) = &job.spec.output_url else {
            return false;
        };
        let url = match ObjectUrl::parse(prefix).and_then(|prefix| prefix.join(name)) {
            Ok(url) => url,
            Err(error) => {
                self.record_output_refused(&job.id, error.to_string());
                return false;
            }
        };
        if !self.outputs.started() {
            let refused = format!("{url}: not uploaded: this server writes no outputs by URL");
            self.record_output_refused(&job.id, refused);
            return false;
        }
        let output = PendingOutput {
            job_id: job.id.clone(),
            name: name.to_owned(),
            file: file.to_owned(),
            url: url.to_string(),
        };
        match self.state.queue_output(&output) {
            Ok(Some(job)) => self.publish(&job, None),
            Ok(None) => return false,
            Err(error) => {
                let refused = format!("{url}: not uploaded: recording it: {error}");
                self.record_output_refused(&job.id, refused);
                return false;
            }
        }
        self.outputs.wake();
        true
    }

    /// Removes the pending output `key` and counts it uploaded, or keeps why it was not, in
    /// its job, under the scheduling lock as every other change of a job is, so that none is
    /// lost; watchers are told.
    fn finish_output(&self, key: u64, output: &PendingOutput, outcome: Result<(), String>) {
        let _scheduling = match self.scheduling() {
            Ok(scheduling) => scheduling,
            Err(error) => {
                return tracing::warn!(job = %output.job_id, %error, "recording a job output")
            }
        };
        if let Err(reason) = &outcome {
            tracing::warn!(job = %output.job_id, %reason, "a job output was not uploaded");
        }
        match self.state.finish_output(key, &output.job_id, outcome) {
            Ok(Some(job)) => self.publish(&job, None),
            Ok(None) => {}
            Err(error) => tracing::warn!(job = %output.job_id, %error, "recording a job output"),
        }
    }

    /// Keeps why an output was not queued in its job, for a caller that holds the scheduling
    /// lock; a job gone meanwhile is passed over, and watchers are told.
    fn record_output_refused(&self, job_id: &str, reason: String) {
        tracing::warn!(job = %job_id, %reason, "a job output was not uploaded");
        let recorded = self
            .state
            .update_job(job_id, |job| job.outputs.record_failure(reason));
        match recorded {
            Ok(Some(job)) => self.publish(&job, None),
            Ok(None) => {}
            Err(error) => tracing::warn!(job = %job_id, %error, "recording a job output"),
        }
    }
}

#[cfg(test)]
mod tests {
    use crate::output_queue::{output_prefixes, PendingOutput};
    use crate::test_daemon;

    #[test]
    fn a_pending_output_whose_stored_file_is_gone_is_recorded_as_failed_at_startup() {
        let dir = tempfile::tempdir().expect("dir");
        let configure = |config: &mut crate::service::DaemonConfig| {
            config.allowed_output_prefixes = output_prefixes(&["s3://renders/farm"]).expect("ok");
        };
        let daemon = test_daemon::open_with(dir.path(), configure);
        let job = test_daemon::submit(&daemon, 2, |request| {
            request.output_url = "s3://renders/farm/job".into();
        });
        let output = PendingOutput {
            job_id: job.id.clone(),
            name: "frame_00000.png".into(),
            file: dir.path().join("gone.png"),
            url: "s3://renders/farm/job/frame_00000.png".into(),
        };
        daemon.state.queue_output(&output).expect("queue");
        drop(daemon);

        let daemon = test_daemon::open_with(dir.path(), configure);
        let job = daemon.state.job(&job.id).expect("read").expect("job");
        assert_eq!(job.outputs.pending, 0);
        let [error] = job.outputs.errors.as_slice() else {
            panic!("one error: {:?}", job.outputs.errors);
        };
        assert!(
            error.contains("frame_00000.png") && error.contains("no longer exists"),
            "{error}"
        );
        assert_eq!(daemon.state.pending_output_after(None).expect("read"), None);
    }
}

//! Webhooks: the daemon tells the endpoints its operator configured that a job ended
//! (succeeded, failed, cancelled), so that scripts learn of it without polling.
//!
//! `Daemon::log_job_end`, the one place a job ends, hands [`Webhooks::job_ended`] the job; the
//! event goes into each interested endpoint's bounded queue without waiting (a full queue drops
//! it, with a warning and a count), and `delivery` sends it from a thread of its own: a POST
//! of the JSON body below, signed with the endpoint's secret, retried with backoff. Events are
//! kept in memory only: those still queued when the daemon stops are not sent.
//!
//! - `config`: the endpoints, their secrets and events, checked at start.
//! - `delivery`: the queues, the signed POSTs, retries and backoff.
//!
//! The body follows the proto3 JSON mapping the API's `--json` output uses: lowerCamelCase
//! names, the state by its enum name, 64-bit integers as strings:
//!
//! ```json
//! {"event": "job.succeeded",
//!  "job": {"id": "job-…", "requestId": "nightly", "datasetId": "ds-…",
//!          "state": "JOB_STATE_SUCCEEDED", "framesDone": 120, "framesTotal": 120,
//!          "failedAttempts": "0", "createdUnixMs": "1764950000000",
//!          "endedUnixMs": "1764950042000"}}
//! ```

use std::sync::Arc;

use serde::Serialize;
use tokio::sync::mpsc::error::TrySendError;

use crate::error::DaemonError;
use crate::metrics::WebhookCounters;
use crate::model::{Job, JobState};

mod config;
mod delivery;

pub use config::{
    shown_url, JobEnd, SecretSource, WebhookConfigError, WebhookEndpoint, WebhookSecret,
    WebhookSpec,
};

use delivery::{Event, Queue};

/// The endpoints' queues; without endpoints, nothing is started and job ends cost nothing.
pub struct Webhooks {
    queues: Vec<Queue>,
    counters: WebhookCounters,
}

impl Webhooks {
    /// Starts delivering to `endpoints` (none: nothing to start).
    pub fn start(
        endpoints: &[WebhookEndpoint],
        counters: WebhookCounters,
    ) -> Result<Self, DaemonError> {
        let queues = if endpoints.is_empty() {
            Vec::new()
        } else {
            let queues = delivery::start(endpoints, counters.clone())
                .map_err(|e| DaemonError::Internal(format!("starting webhooks: {e}")))?;
            let shown: Vec<String> = endpoints.iter().map(WebhookEndpoint::shown_url).collect();
            tracing::info!(webhooks = %shown.join(", "), "job ends are posted to webhooks");
            queues
        };
        Ok(Self { queues, counters })
    }

    /// Queues the end of `job` for the endpoints that want it, without waiting; a full queue
    /// drops the event for its endpoint. `failed_attempts` is none when it could not be read.
    pub(crate) fn job_ended(&self, job: &Job, failed_attempts: Option<u64>) {
        let Some(end) = job_end(job.state) else {
            return;
        };
        let wanted: Vec<&Queue> = self
            .queues
            .iter()
            .filter(|queue| queue.endpoint.wants(end))
            .collect();
        if wanted.is_empty() {
            return;
        }
        let body = match serde_json::to_vec(&Body::new(end, job, failed_attempts)) {
            Ok(body) => body,
            Err(e) => {
                tracing::error!(job = %job.id, error = %e, "a webhook event could not be written");
                return;
            }
        };
        let event = Arc::new(Event {
            end,
            job_id: job.id.clone(),
            body,
        });
        for queue in wanted {
            let why = match queue.events.try_send(Arc::clone(&event)) {
                Ok(()) => continue,
                Err(TrySendError::Full(_)) => "its queue is full",
                Err(TrySendError::Closed(_)) => "its delivery has stopped",
            };
            tracing::warn!(
                webhook = %queue.endpoint.shown_url(), event = end.event(), job = %job.id,
                "webhook event dropped: {why}"
            );
            self.counters.dropped();
        }
    }
}

/// The end a job in `state` came to; none while it has not ended.
fn job_end(state: JobState) -> Option<JobEnd> {
    match state {
        JobState::Succeeded => Some(JobEnd::Succeeded),
        JobState::Failed => Some(JobEnd::Failed),
        JobState::Cancelled => Some(JobEnd::Cancelled),
        JobState::Queued | JobState::Running | JobState::Paused => None,
    }
}

/// The JSON body of an event (see the module's documentation).
#[derive(Serialize)]
struct Body<'a> {
    event: &'static str,
    job: JobBody<'a>,
}

#[derive(Serialize)]
#[serde(rename_all = "camelCase")]
struct JobBody<'a> {
    id: &'a str,
    request_id: &'a str,
    dataset_id: &'a str,
    state: &'static str,
    frames_done: u32,
    frames_total: u32,
    #[serde(skip_serializing_if = "Option::is_none")]
    failed_attempts: Option<String>,
    #[serde(skip_serializing_if = "Option::is_none")]
    error: Option<&'a str>,
    created_unix_ms: String,
    ended_unix_ms: String,
}

impl<'a> Body<'a> {
    fn new(end: JobEnd, job: &'a Job, failed_attempts: Option<u64>) -> Self {
        Self {
            event: end.event(),
            job: JobBody {
                id: &job.id,
                request_id: &job.spec.request_id,
                dataset_id: &job.spec.dataset_id,
                state: match end {
                    JobEnd::Succeeded => "JOB_STATE_SUCCEEDED",
                    JobEnd::Failed => "JOB_STATE_FAILED",
                    JobEnd::Cancelled => "JOB_STATE_CANCELLED",
                },
                frames_done: job.frames_done,
                frames_total: job.frames_total,
                failed_attempts: failed_attempts.map(|n| n.to_string()),
                error: job.error.as_deref().filter(|error| !error.is_empty()),
                created_unix_ms: job.created_unix_ms.to_string(),
                ended_unix_ms: job.updated_unix_ms.to_string(),
            },
        }
    }
}

#[cfg(test)]
mod tests;

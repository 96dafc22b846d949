//! The event's body, and handing events over without ever waiting: a full queue drops the
//! event for its endpoint alone, and counts it.

use std::sync::Arc;

use pointfarm_render::request::{CameraPath, Lens, RenderOptions, RenderRequest, Turntable};
use tokio::sync::mpsc;

use super::delivery::{Event, Queue};
use super::*;
use crate::model::JobSpec;

fn job(state: JobState, error: Option<&str>) -> Job {
    Job {
        id: "job-1".into(),
        spec: JobSpec {
            request_id: "nightly".into(),
            dataset_id: "ds-1".into(),
            request: RenderRequest {
                width: 8,
                height: 8,
                camera_path: CameraPath::Turntable(Turntable::around_the_cloud(4)),
                lens: Lens::default(),
                render: RenderOptions::default(),
            },
            priority: 0,
            requirements: Default::default(),
            preview: false,
            after: Vec::new(),
            name: String::new(),
            labels: Default::default(),
            video: None,
            output_url: None,
            build_unseen: Default::default(),
        },
        state,
        frames_total: 4,
        frames_done: 3,
        error: error.map(str::to_owned),
        created_unix_ms: 1_764_950_000_000,
        updated_unix_ms: 1_764_950_042_000,
        worker_failures: Default::default(),
        blocklist: Default::default(),
        encode: None,
        outputs: Default::default(),
    }
}

/// An endpoint wanting `events`, its queue holding `capacity` events that nobody takes.
fn endpoint_queue(
    url: &str,
    events: Option<Vec<JobEnd>>,
    capacity: usize,
) -> (Queue, mpsc::Receiver<Arc<Event>>) {
    let spec = WebhookSpec {
        events,
        ..WebhookSpec::new(url, Some(SecretSource::Env("SECRET".into())))
    };
    let endpoint =
        WebhookEndpoint::load_with_env(&spec, |_| Some("s3cret".into())).expect("a good endpoint");
    let (events, received) = mpsc::channel(capacity);
    let queue = Queue {
        endpoint: Arc::new(endpoint),
        events,
    };
    (queue, received)
}

#[test]
fn the_body_has_the_jobs_end_in_proto3_json_style() {
    let failed = job(JobState::Failed, Some("frame 2: out of memory"));
    let body = serde_json::to_value(Body::new(JobEnd::Failed, &failed, Some(3))).expect("json");
    assert_eq!(
        body,
        serde_json::json!({
            "event": "job.failed",
            "job": {
                "id": "job-1",
                "requestId": "nightly",
                "datasetId": "ds-1",
                "state": "JOB_STATE_FAILED",
                "framesDone": 3,
                "framesTotal": 4,
                "failedAttempts": "3",
                "error": "frame 2: out of memory",
                "createdUnixMs": "1764950000000",
                "endedUnixMs": "1764950042000",
            }
        })
    );
    let succeeded = job(JobState::Succeeded, None);
    let body = serde_json::to_value(Body::new(JobEnd::Succeeded, &succeeded, None)).expect("json");
    assert_eq!(body["event"], "job.succeeded");
    assert_eq!(body["job"]["state"], "JOB_STATE_SUCCEEDED");
    let keys: Vec<&String> = body["job"].as_object().expect("an object").keys().collect();
    assert!(!keys.contains(&&"error".to_owned()), "{keys:?}");
    assert!(!keys.contains(&&"failedAttempts".to_owned()), "{keys:?}");
}

/// A queue that is full drops the event for its own endpoint, counted, while the other
/// endpoint gets it; an endpoint that wants no cancellations is not sent one; a job that has
/// not ended is sent to nobody.
#[test]
fn a_full_queue_drops_the_event_for_its_endpoint_alone() {
    let (full, mut full_received) = endpoint_queue("https://full.example/", None, 1);
    let (open, mut open_received) = endpoint_queue("https://open.example/", None, 8);
    let (failures_only, mut failures_received) =
        endpoint_queue("https://failures.example/", Some(vec![JobEnd::Failed]), 8);
    let counters = WebhookCounters::default();
    let webhooks = Webhooks {
        queues: vec![full, open, failures_only],
        counters: counters.clone(),
    };
    webhooks.job_ended(&job(JobState::Running, None), Some(0));
    webhooks.job_ended(&job(JobState::Succeeded, None), Some(0));
    webhooks.job_ended(&job(JobState::Cancelled, None), Some(0));
    assert_eq!(counters.counts(), [0, 0, 1], "delivered, failed, dropped");

    let taken = |received: &mut mpsc::Receiver<Arc<Event>>| {
        std::iter::from_fn(|| received.try_recv().ok())
            .map(|event| event.end)
            .collect::<Vec<_>>()
    };
    assert_eq!(taken(&mut full_received), [JobEnd::Succeeded]);
    assert_eq!(
        taken(&mut open_received),
        [JobEnd::Succeeded, JobEnd::Cancelled]
    );
    assert!(taken(&mut failures_received).is_empty());

    drop(open_received);
    webhooks.job_ended(&job(JobState::Failed, Some("lost")), Some(3));
    assert_eq!(counters.counts(), [0, 0, 2], "delivered, failed, dropped");
    let failure = failures_received.try_recv().expect("the failure");
    let body: serde_json::Value = serde_json::from_slice(&failure.body).expect("json");
    assert_eq!(body["job"]["error"], "lost");
}

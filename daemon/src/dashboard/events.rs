//! Live updates: the daemon's job events (the broadcast `WatchJob` follows) as server-sent
//! events, `GET /api/events` for every job or `GET /api/events?job=ID` for one.
//!
//! Each `job` event's data is a `JobEvent` in the proto3 JSON mapping (the job, the frame
//! that finished, a preview or its final image, and the job's stage as the pages word it). A stream for one job opens with a `job`
//! event holding the job and every frame finished so far, so a page rendered a moment before
//! misses nothing. A reader too slow for the broadcast is sent `resync`: what it skipped is
//! no longer known, so the page reads the state again.

use std::convert::Infallible;
use std::time::Duration;

use axum::extract::{RawQuery, State};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use axum::Router;
use pointfarm_proto::v1 as pb;
use tokio_stream::wrappers::errors::BroadcastStreamRecvError;
use tokio_stream::wrappers::BroadcastStream;
use tokio_stream::{Stream, StreamExt};

use super::api::job_message;
use super::auth::field;
use super::failure::Failure;
use super::pages::shown_stage;
use super::Dashboard;

/// How often an idle stream sends a comment, so proxies and the connection's idle bound
/// keep it open.
const KEEP_ALIVE: Duration = Duration::from_secs(15);

pub(super) fn routes() -> Router<Dashboard> {
    Router::new().route("/api/events", get(events))
}

pub async fn events(
    State(dashboard): State<Dashboard>,
    RawQuery(query): RawQuery,
) -> Result<Response, Failure> {
    let job = field(query.unwrap_or_default().as_bytes(), "job").filter(|id| !id.is_empty());
    // Subscribed before the job is read, so no event falls between the two.
    let subscription = BroadcastStream::new(dashboard.daemon.subscribe());
    let first = match &job {
        Some(id) => {
            let (message, job, _) = job_message(&dashboard.daemon, id.clone()).await?;
            let stage = shown_stage(&dashboard.daemon, &job).await.to_owned();
            Some(job_event(&pb::JobEvent {
                job: Some(message),
                frame: None,
                stage,
            }))
        }
        None => None,
    };
    let daemon = dashboard.daemon.clone();
    let updates = subscription
        .filter_map(move |received| match received {
            Ok(event) if job.as_ref().is_none_or(|id| *id == event.job.id) => Some(Ok(event)),
            Ok(_) => None,
            Err(BroadcastStreamRecvError::Lagged(missed)) => Some(Err(missed)),
        })
        .then(move |received| {
            let daemon = daemon.clone();
            async move {
                match received {
                    Ok(event) => job_event(&pb::JobEvent {
                        job: Some(pb::Job::from(&event.job)),
                        frame: event.frame.as_ref().map(pb::FrameFinished::from),
                        stage: shown_stage(&daemon, &event.job).await.to_owned(),
                    }),
                    Err(missed) => {
                        tracing::debug!(missed, "a dashboard's event stream fell behind");
                        Event::default().event("resync").data(missed.to_string())
                    }
                }
            }
        });
    let stream = tokio_stream::iter(first).chain(updates).map(Ok);
    Ok(sse(stream))
}

fn sse(stream: impl Stream<Item = Result<Event, Infallible>> + Send + 'static) -> Response {
    Sse::new(stream)
        .keep_alive(KeepAlive::new().interval(KEEP_ALIVE))
        .into_response()
}

fn job_event(event: &pb::JobEvent) -> Event {
    let data = serde_json::to_string(event)
        .unwrap_or_else(|e| serde_json::json!({ "error": e.to_string() }).to_string());
    Event::default().event("job").data(data)
}

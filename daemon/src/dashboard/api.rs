//! The JSON API beside the pages, for scripts (`curl -H "Authorization: Bearer T"`): each
//! body is the proto3 JSON mapping of the gRPC API's message for the same question
//! (lowerCamelCase names, 64-bit integers as strings, enums by name), so that one client
//! model reads both.
//!
//! - `GET /api/jobs?state=running&label=shot=010&name=night&pageSize=50&pageToken=...`:
//!   `ListJobsResponse` of the jobs the filter takes (`filter`); a page filtered by name may
//!   hold fewer than `pageSize` jobs and still be followed by more
//! - `GET /api/jobs/{id}`: `Job` with its finished frames, as `GetJob` answers
//! - `POST /api/jobs/{id}/{action}`: the `Job` after it (`actions`)
//! - `GET /api/workers`: `ListWorkersResponse`, each worker that jobs have blocklisted with
//!   `blocklistedBy` added: those jobs (`workers`)
//! - `GET /api/datasets?pageSize=...&pageToken=...`: `ListDatasetsResponse`

use std::sync::Arc;

use axum::extract::{Path, RawQuery, State};
use axum::http::header;
use axum::response::{Html, IntoResponse, Response};
use axum::routing::get;
use axum::Router;
use pointfarm_proto::v1 as pb;
use serde::Serialize;
use tonic::Status;

use super::auth::field;
use super::failure::Failure;
use super::filter::{jobs_message, JobQuery};
use super::Dashboard;
use crate::error::DaemonError;
use crate::grpc::{blocking_within, job_with_frames_message, BLOCKING_CALL_BOUND};
use crate::model::{FrameReport, Job};
use crate::service::Daemon;

/// A message as its proto3 JSON.
pub fn json(message: &impl Serialize) -> Response {
    match serde_json::to_string(message) {
        Ok(body) => ([(header::CONTENT_TYPE, "application/json")], body).into_response(),
        Err(e) => Failure(Status::internal(e.to_string())).into_response(),
    }
}

/// Runs `work` on the daemon off the async threads (the state database blocks), within the
/// bound the gRPC handlers use; errors without the server's folders in their messages.
pub async fn run<T: Send + 'static>(
    daemon: &Arc<Daemon>,
    work: impl FnOnce(&Daemon) -> Result<T, DaemonError> + Send + 'static,
) -> Result<T, Failure> {
    let daemon = daemon.clone();
    let done = blocking_within(BLOCKING_CALL_BOUND, {
        let daemon = daemon.clone();
        move || work(&daemon)
    })
    .await?;
    done.map_err(|error| {
        let status = Status::from(error);
        let message = daemon.without_server_folders(status.message());
        Failure(Status::new(status.code(), message))
    })
}

/// The jobs, a job and the datasets (the workers are `workers`', the actions `actions`').
pub(super) fn routes() -> Router<Dashboard> {
    Router::new()
        .route("/api/jobs", get(jobs))
        .route("/api/jobs/{id}", get(job))
        .route("/api/datasets", get(datasets))
}

/// `pageSize` of a query: absent is the API's default (0).
fn page_size(query: &[u8]) -> Result<u32, Failure> {
    match field(query, "pageSize") {
        None => Ok(0),
        Some(size) => size.parse().map_err(|_| {
            Failure(Status::invalid_argument(format!(
                "pageSize: '{size}' is not a count"
            )))
        }),
    }
}

pub async fn jobs(
    State(dashboard): State<Dashboard>,
    RawQuery(query): RawQuery,
) -> Result<Response, Failure> {
    let raw = query.unwrap_or_default().into_bytes();
    let query = JobQuery::parse(&raw)?;
    let size = page_size(&raw)?;
    let token = field(&raw, "pageToken").unwrap_or_default();
    let stored = query.stored.clone();
    let page = run(&dashboard.daemon, move |daemon| {
        daemon.find_jobs(&stored, size, &token)
    })
    .await?;
    Ok(json(&jobs_message(&query, &page.items, page.next_token)))
}

/// Job `id` with its finished frames and why it waits, as `GetJob` answers.
pub async fn job_message(
    daemon: &Arc<Daemon>,
    id: String,
) -> Result<(pb::Job, Job, Vec<FrameReport>), Failure> {
    let (job, frames) = run(daemon, move |daemon| daemon.job_with_frames(&id)).await?;
    let availability = daemon.job_availability(&job);
    let message = job_with_frames_message(&job, &frames, availability);
    Ok((message, job, frames))
}

pub async fn job(
    State(dashboard): State<Dashboard>,
    Path(id): Path<String>,
) -> Result<Response, Failure> {
    let (message, _, _) = job_message(&dashboard.daemon, id).await?;
    Ok(json(&message))
}

pub async fn datasets(
    State(dashboard): State<Dashboard>,
    RawQuery(query): RawQuery,
) -> Result<Response, Failure> {
    let query = query.unwrap_or_default().into_bytes();
    let size = page_size(&query)?;
    let token = field(&query, "pageToken").unwrap_or_default();
    let page = run(&dashboard.daemon, move |daemon| {
        daemon.list_datasets(size, &token)
    })
    .await?;
    Ok(json(&pb::ListDatasetsResponse {
        datasets: page.items.iter().map(pb::Dataset::from).collect(),
        next_page_token: page.next_token,
    }))
}

/// A failure as a page of its section.
pub(super) fn failure_page(section: &str, failure: Failure) -> Response {
    (
        failure.http_status(),
        Html(super::html::error_page(section, failure.message())),
    )
        .into_response()
}

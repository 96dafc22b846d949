//! What a user may do to a job, from its page's buttons (`POST /jobs/{id}/{action}`, which
//! goes back to the job, or to the jobs after a delete) or a script
//! (`POST /api/jobs/{id}/{action}`, answered with the job): `cancel`, `pause`, `resume`,
//! `retry`, `priority` (with `priority=N` in the form or the query) and `delete` (with
//! `force=true` to cancel a job that has not ended first). Each calls the `Daemon` method the
//! gRPC API's does, with its rules.

use axum::body::Bytes;
use axum::extract::{Path, RawQuery, State};
use axum::http::{header, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::routing::post;
use axum::Router;
use pointfarm_proto::v1 as pb;
use tonic::Status;

use super::api::{failure_page, json, run};
use super::auth::field;
use super::failure::Failure;
use super::html::segment;
use super::Dashboard;
use crate::error::DaemonError;
use crate::model::{Job, JobState};
use crate::service::Daemon;

/// An action on a job.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum JobAction {
    Cancel,
    Pause,
    Resume,
    Retry,
    Priority(i32),
    Delete { force: bool },
}

impl JobAction {
    /// The action `name`, its value from the query or the form.
    fn parse(name: &str, query: &[u8], form: &[u8]) -> Result<Self, Failure> {
        let value = |key| field(query, key).or_else(|| field(form, key));
        Ok(match name {
            "cancel" => JobAction::Cancel,
            "pause" => JobAction::Pause,
            "resume" => JobAction::Resume,
            "retry" => JobAction::Retry,
            "delete" => JobAction::Delete {
                force: value("force").is_some_and(|force| force == "true"),
            },
            "priority" => {
                let given = value("priority").unwrap_or_default();
                let priority = given.trim().parse().map_err(|_| {
                    Failure(Status::invalid_argument(format!(
                        "priority: '{given}' is not a whole number"
                    )))
                })?;
                JobAction::Priority(priority)
            }
            _ => {
                return Err(Failure(Status::not_found(format!(
                    "no action '{name}': cancel, pause, resume, retry, priority or delete"
                ))))
            }
        })
    }

    fn apply(self, daemon: &Daemon, id: &str) -> Result<Job, DaemonError> {
        match self {
            JobAction::Cancel => daemon.cancel_job(id),
            JobAction::Pause => daemon.pause_job(id),
            JobAction::Resume => daemon.resume_job(id),
            JobAction::Retry => daemon.retry_job(id),
            JobAction::Priority(priority) => daemon.set_job_priority(id, priority),
            JobAction::Delete { force } => daemon.delete_job(id, force),
        }
    }

    /// The states of a job its page offers the action in.
    pub fn offered(self, state: JobState) -> bool {
        use JobState::*;
        match self {
            JobAction::Pause => matches!(state, Queued | Running),
            JobAction::Resume => state == Paused,
            JobAction::Cancel | JobAction::Priority(_) => !state.is_terminal(),
            JobAction::Retry => state == Failed,
            JobAction::Delete { .. } => state.is_terminal(),
        }
    }
}

/// A job's buttons (`/jobs/{id}/{action}`) and the API's actions (`/api/jobs/{id}/{action}`).
pub(super) fn routes() -> Router<Dashboard> {
    Router::new()
        .route("/jobs/{id}/{action}", post(page_action))
        .route("/api/jobs/{id}/{action}", post(api_action))
}

async fn act(dashboard: &Dashboard, id: String, action: JobAction) -> Result<Job, Failure> {
    run(&dashboard.daemon, move |daemon| action.apply(daemon, &id)).await
}

/// A button of a job's page.
pub async fn page_action(
    State(dashboard): State<Dashboard>,
    Path((id, name)): Path<(String, String)>,
    RawQuery(query): RawQuery,
    form: Bytes,
) -> Response {
    let query = query.unwrap_or_default().into_bytes();
    let action = match JobAction::parse(&name, &query, &form) {
        Ok(action) => action,
        Err(failure) => return failure_page("Jobs", failure),
    };
    let location = match action {
        JobAction::Delete { .. } => "/".to_string(),
        _ => format!("/jobs/{}", segment(&id)),
    };
    match act(&dashboard, id, action).await {
        Ok(_) => (StatusCode::SEE_OTHER, [(header::LOCATION, location)]).into_response(),
        Err(failure) => failure_page("Jobs", failure),
    }
}

/// An action by a script: the job after it (a deleted job as it was).
pub async fn api_action(
    State(dashboard): State<Dashboard>,
    Path((id, name)): Path<(String, String)>,
    RawQuery(query): RawQuery,
    form: Bytes,
) -> Result<Response, Failure> {
    let query = query.unwrap_or_default().into_bytes();
    let action = JobAction::parse(&name, &query, &form)?;
    let job = act(&dashboard, id, action).await?;
    Ok(json(&pb::Job::from(&job)))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn actions_are_read_with_their_values() {
        let parse = |name, query: &str, form: &str| {
            JobAction::parse(name, query.as_bytes(), form.as_bytes())
        };
        assert_eq!(parse("cancel", "", "").ok(), Some(JobAction::Cancel));
        assert_eq!(
            parse("priority", "", "priority=7").ok(),
            Some(JobAction::Priority(7))
        );
        assert_eq!(
            parse("priority", "priority=-3", "").ok(),
            Some(JobAction::Priority(-3))
        );
        assert_eq!(
            parse("delete", "force=true", "").ok(),
            Some(JobAction::Delete { force: true })
        );
        assert_eq!(
            parse("delete", "", "").ok(),
            Some(JobAction::Delete { force: false })
        );
        let refused = parse("priority", "", "priority=high").expect_err("not a number");
        assert_eq!(refused.http_status(), StatusCode::BAD_REQUEST);
        let refused = parse("explode", "", "").expect_err("no such action");
        assert_eq!(refused.http_status(), StatusCode::NOT_FOUND);
    }

    #[test]
    fn a_page_offers_only_what_its_state_allows() {
        assert!(JobAction::Pause.offered(JobState::Running));
        assert!(!JobAction::Pause.offered(JobState::Paused));
        assert!(JobAction::Resume.offered(JobState::Paused));
        assert!(JobAction::Retry.offered(JobState::Failed));
        assert!(!JobAction::Retry.offered(JobState::Cancelled));
        assert!(JobAction::Cancel.offered(JobState::Paused));
        assert!(!JobAction::Cancel.offered(JobState::Succeeded));
        assert!(JobAction::Delete { force: false }.offered(JobState::Succeeded));
        assert!(!JobAction::Delete { force: false }.offered(JobState::Queued));
    }
}

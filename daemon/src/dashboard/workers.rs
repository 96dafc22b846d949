//! The workers page and `GET /api/workers`: the workers heard from within the lease timeout,
//! each with the frames it renders now, its capabilities, and the unfinished jobs that have
//! blocklisted it (it failed `worker_failures_before_blocklist` of their frames, so they
//! lease it no more).

use std::collections::BTreeMap;
use std::fmt::Write;

use axum::extract::State;
use axum::response::{Html, IntoResponse, Response};
use axum::routing::get;
use axum::Router;
use pointfarm_proto::v1 as pb;
use serde::Serialize;
use serde_json::Value;

use super::api::{failure_page, json, run};
use super::failure::Failure;
use super::html::{self, escape, segment};
use super::Dashboard;
use crate::error::DaemonError;
use crate::grpc;
use crate::model::Job;
use crate::service::Daemon;

/// The page (`/workers`) and its JSON (`/api/workers`).
pub(super) fn routes() -> Router<Dashboard> {
    Router::new()
        .route("/workers", get(page))
        .route("/api/workers", get(api))
}

/// A job that leases a worker no more of its frames, as `/api/workers` writes it in the
/// worker's `blocklistedBy`.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
#[serde(rename_all = "camelCase")]
pub struct Blocklisting {
    pub job_id: String,
    /// What users call the job: its name, else its request id.
    pub job_name: String,
    /// The job's frames the worker failed.
    pub failed_frames: u32,
}

/// The unfinished jobs that have blocklisted each worker, by worker name, oldest job first.
fn blocklists(daemon: &Daemon) -> Result<BTreeMap<String, Vec<Blocklisting>>, DaemonError> {
    let mut by_worker: BTreeMap<String, Vec<Blocklisting>> = BTreeMap::new();
    let mut jobs = daemon.state.unfinished_jobs()?;
    jobs.retain(|job| !job.blocklist.is_empty());
    jobs.sort_by(|a, b| (a.created_unix_ms, &a.id).cmp(&(b.created_unix_ms, &b.id)));
    for job in &jobs {
        for worker in &job.blocklist {
            by_worker
                .entry(worker.clone())
                .or_default()
                .push(Blocklisting {
                    job_id: job.id.clone(),
                    job_name: super::filter::job_name(job).to_owned(),
                    failed_frames: failed_frames(job, worker),
                });
        }
    }
    Ok(by_worker)
}

fn failed_frames(job: &Job, worker: &str) -> u32 {
    job.worker_failures.get(worker).copied().unwrap_or_default()
}

/// The workers heard from within the lease timeout, as `ListWorkers` answers.
fn workers_message(daemon: &Daemon) -> pb::ListWorkersResponse {
    let connected = daemon.workers.connected(daemon.config.lease_timeout);
    grpc::workers_message(&connected)
}

/// `ListWorkersResponse` in proto3 JSON, each worker that a job has blocklisted with
/// `blocklistedBy`: the [`Blocklisting`]s (left out, as proto3 JSON leaves out an empty
/// list, for the others).
pub async fn api(State(dashboard): State<Dashboard>) -> Result<Response, Failure> {
    let blocklisted = run(&dashboard.daemon, blocklists).await?;
    let listed = workers_message(&dashboard.daemon);
    let mut body = serde_json::to_value(&listed)
        .map_err(|e| Failure(tonic::Status::internal(e.to_string())))?;
    if let Some(workers) = body.get_mut("workers").and_then(Value::as_array_mut) {
        for worker in workers {
            let name = worker.get("workerName").and_then(Value::as_str);
            let Some(jobs) = name.and_then(|name| blocklisted.get(name)) else {
                continue;
            };
            if let (Some(worker), Ok(jobs)) = (worker.as_object_mut(), serde_json::to_value(jobs)) {
                worker.insert("blocklistedBy".into(), jobs);
            }
        }
    }
    Ok(json(&body))
}

/// The cell that names the jobs that have blocklisted a worker.
fn blocklist_cell(jobs: Option<&Vec<Blocklisting>>) -> String {
    let Some(jobs) = jobs.filter(|jobs| !jobs.is_empty()) else {
        return "—".to_string();
    };
    let named: Vec<String> = jobs
        .iter()
        .map(|blocked| {
            format!(
                "<a href=\"/jobs/{link}\" data-blocklisted-by=\"{id}\">{name}</a> \
                 ({failed} failed frames)",
                link = segment(&blocked.job_id),
                id = escape(&blocked.job_id),
                name = escape(&blocked.job_name),
                failed = blocked.failed_frames,
            )
        })
        .collect();
    named.join(", ")
}

pub async fn page(State(dashboard): State<Dashboard>) -> Response {
    let daemon = dashboard.daemon.clone();
    let read = run(&dashboard.daemon, |daemon| {
        Ok((daemon.leases()?, blocklists(daemon)?))
    });
    let (leases, blocklisted) = match read.await {
        Ok(read) => read,
        Err(failure) => return failure_page("Workers", failure),
    };
    let timeout = daemon.config.lease_timeout;
    let can_render = daemon.workers.can_render(timeout);
    let disk = daemon.state.outage();
    let mut body = String::from("<h1>Workers</h1>");
    let health = match (&disk, can_render) {
        (Some(outage), _) => format!(
            "<p class=\"health bad\">The disk refuses writes: no frame is stored ({}).</p>",
            escape(&outage.to_string())
        ),
        (None, true) => "<p class=\"health good\">A worker can render.</p>".to_string(),
        (None, false) => "<p class=\"health bad\">No worker can render: jobs wait.</p>".to_string(),
    };
    body.push_str(&health);
    body.push_str(
        "<div class=\"table\"><table id=\"workers\"><thead><tr><th>Worker</th><th>Kind</th>\
         <th>Adapter</th><th>Capabilities</th><th>Current frame</th><th>Health</th>\
         <th>Blocklisted by</th></tr></thead><tbody>",
    );
    let listed = workers_message(&daemon);
    for worker in &listed.workers {
        let name = &worker.worker_name;
        let current: Vec<String> = leases
            .iter()
            .filter(|lease| lease.worker == *name)
            .map(|lease| {
                format!(
                    "<a href=\"/jobs/{link}/frames/{index}\">{id} #{index}</a>",
                    link = segment(&lease.job_id),
                    id = escape(&lease.job_id),
                    index = lease.index
                )
            })
            .collect();
        let caps = worker.capabilities.clone().unwrap_or_default();
        let adapter = match caps.adapter_kind() {
            pb::AdapterKind::Hardware => "GPU",
            pb::AdapterKind::Software => "software (CPU)",
            pb::AdapterKind::Unspecified => "unknown",
        };
        let mut capabilities = Vec::new();
        if caps.device_memory_bytes > 0 {
            capabilities.push(format!("{} memory", html::bytes(caps.device_memory_bytes)));
        }
        if caps.shader_int64_atomics {
            capabilities.push("64-bit atomics".to_string());
        }
        if caps.max_frame_side > 0 {
            capabilities.push(format!("frames up to {} px", caps.max_frame_side));
        }
        for tag in &caps.tags {
            capabilities.push(format!("tag {}", escape(tag)));
        }
        let _ = write!(
            body,
            "<tr data-worker=\"{name}\"><td>{name}</td><td>{kind}</td><td>{adapter}: {adapter_name}</td>\
             <td>{capabilities}</td><td>{current}</td><td>{health}</td>\
             <td class=\"blocklisted-by\">{blocklisted_by}</td></tr>",
            name = escape(name),
            kind = if worker.embedded { "embedded" } else { "remote" },
            adapter_name = escape(&caps.adapter_name),
            capabilities = capabilities.join(", "),
            health = if current.is_empty() { "idle" } else { "rendering" },
            current = if current.is_empty() {
                "—".to_string()
            } else {
                current.join(", ")
            },
            blocklisted_by = blocklist_cell(blocklisted.get(name)),
        );
    }
    body.push_str("</tbody></table></div>");
    if listed.workers.is_empty() {
        body.push_str("<p>No worker has asked for frames lately.</p>");
    }
    Html(html::layout(
        "Workers",
        "Workers",
        "workers",
        " data-refresh=\"5\"",
        &body,
    ))
    .into_response()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_workers_blocklisting_jobs_are_named_with_their_failed_frames() {
        assert_eq!(blocklist_cell(None), "—");
        assert_eq!(blocklist_cell(Some(&Vec::new())), "—");
        let jobs = vec![Blocklisting {
            job_id: "job-1".into(),
            job_name: "<nightly>".into(),
            failed_frames: 3,
        }];
        assert_eq!(
            blocklist_cell(Some(&jobs)),
            "<a href=\"/jobs/job-1\" data-blocklisted-by=\"job-1\">&lt;nightly&gt;</a> \
             (3 failed frames)"
        );
    }
}

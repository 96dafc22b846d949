//! The pages, rendered on the server from the daemon's own records: jobs (newest first,
//! filtered by state), a job with its frames as thumbnails, a frame large with its stage
//! timings, the workers, the datasets; and a job's buttons (`actions`). The script
//! (`assets/dashboard.js`) keeps them current from the event stream.

use std::collections::HashMap;
use std::fmt::Write;

use axum::extract::{Path, RawQuery, State};
use axum::response::{Html, IntoResponse, Response};
use pointfarm_render::encode::video::VideoContainer;

use super::actions::JobAction;
use super::api::{failure_page, parse_state, run, workers_message, Failure};
use super::auth::field;
use super::html::{self, escape, segment};
use super::Dashboard;
use crate::error::DaemonError;
use crate::job_control::PRIORITY_RANGE;
use crate::model::{now_unix_ms, Dataset, FrameReport, Job, JobState};
use crate::service::Daemon;

/// How many jobs the jobs page lists unless asked for more (`?limit=N`): enough for a day's
/// work, few enough to paint at once.
const JOBS_SHOWN: usize = 200;

/// The jobs matching `state`, newest first, the first `limit` of them, and how many match.
fn newest_jobs(
    daemon: &Daemon,
    state: Option<JobState>,
    limit: usize,
) -> Result<(Vec<Job>, usize), DaemonError> {
    let mut jobs = Vec::new();
    let mut token = String::new();
    loop {
        let page = daemon.list_jobs(state, 1000, &token)?;
        jobs.extend(page.items);
        if page.next_token.is_empty() {
            break;
        }
        token = page.next_token;
    }
    let matching = jobs.len();
    jobs.sort_by(|a, b| (b.created_unix_ms, &b.id).cmp(&(a.created_unix_ms, &a.id)));
    jobs.truncate(limit);
    Ok((jobs, matching))
}

/// The names of the datasets, by id.
fn dataset_names(daemon: &Daemon) -> Result<HashMap<String, String>, DaemonError> {
    Ok(daemon
        .state
        .datasets()?
        .into_iter()
        .map(|dataset| (dataset.id, dataset.name))
        .collect())
}

/// What users call a job: its name, else the request id its client chose.
fn job_name(job: &Job) -> &str {
    if job.spec.name.is_empty() {
        &job.spec.request_id
    } else {
        &job.spec.name
    }
}

/// One row of the jobs table; the script builds the same from a job event.
fn job_row(job: &Job, dataset: &str, now_ms: i64) -> String {
    let id = escape(&job.id);
    let eta = html::eta_seconds(job, now_ms)
        .map(html::duration)
        .unwrap_or_default();
    format!(
        "<tr data-job=\"{id}\" data-created=\"{created}\">\
         <td><a href=\"/jobs/{link}\">{id}</a></td><td>{name}</td><td>{dataset}</td>\
         <td class=\"job-state\">{state}</td>\
         <td><progress max=\"{total}\" value=\"{done}\"></progress></td>\
         <td class=\"frames\">{done}/{total}</td><td class=\"eta\">{eta}</td></tr>",
        created = job.created_unix_ms,
        link = segment(&job.id),
        name = escape(job_name(job)),
        dataset = escape(dataset),
        state = html::state_badge(job.state),
        total = job.frames_total,
        done = job.frames_done,
    )
}

pub async fn jobs(State(dashboard): State<Dashboard>, RawQuery(query): RawQuery) -> Response {
    let query = query.unwrap_or_default().into_bytes();
    let filter = field(&query, "state").unwrap_or_default();
    let state = match parse_state(&filter) {
        Ok(state) => state,
        Err(failure) => return failure_page("Jobs", failure),
    };
    let limit = field(&query, "limit")
        .and_then(|limit| limit.parse::<usize>().ok())
        .unwrap_or(JOBS_SHOWN)
        .max(1);
    let read = run(&dashboard.daemon, move |daemon| {
        Ok((newest_jobs(daemon, state, limit)?, dataset_names(daemon)?))
    });
    let ((jobs, matching), names) = match read.await {
        Ok(read) => read,
        Err(failure) => return failure_page("Jobs", failure),
    };
    let now_ms = now_unix_ms();
    let mut body = String::from("<h1>Jobs</h1><nav class=\"filters\" aria-label=\"State\">");
    let current = state.map_or("", JobState::name);
    for name in [
        "",
        "queued",
        "running",
        "paused",
        "succeeded",
        "failed",
        "cancelled",
    ] {
        let (href, label) = if name.is_empty() {
            ("/".to_string(), "all")
        } else {
            (format!("/?state={name}"), name)
        };
        let mark = if name == current {
            " aria-current=\"true\""
        } else {
            ""
        };
        let _ = write!(body, "<a href=\"{href}\"{mark}>{label}</a>");
    }
    let _ = write!(
        body,
        "</nav><p class=\"count\">{shown} of {matching} jobs</p>\
         <div class=\"table\"><table id=\"jobs\"><thead><tr><th>Job</th><th>Name</th>\
         <th>Dataset</th><th>State</th><th>Progress</th><th>Frames</th><th>ETA</th></tr>\
         </thead><tbody>",
        shown = jobs.len()
    );
    for job in &jobs {
        let dataset = names
            .get(&job.spec.dataset_id)
            .unwrap_or(&job.spec.dataset_id);
        body.push_str(&job_row(job, dataset, now_ms));
    }
    body.push_str("</tbody></table></div>");
    if matching > jobs.len() {
        let more = jobs.len().saturating_mul(5);
        let state_query = if current.is_empty() {
            String::new()
        } else {
            format!("state={current}&")
        };
        let _ = write!(
            body,
            "<p><a href=\"/?{state_query}limit={more}\">Show more</a></p>"
        );
    }
    let data = format!(" data-filter=\"{current}\"");
    Html(html::layout("Jobs", "Jobs", "jobs", &data, &body)).into_response()
}

/// The states a job's page offers `action` in, for the script to show it in.
fn offered_in(action: JobAction) -> String {
    use JobState::*;
    [Queued, Running, Paused, Succeeded, Failed, Cancelled]
        .into_iter()
        .filter(|state| action.offered(*state))
        .map(JobState::name)
        .collect::<Vec<_>>()
        .join(" ")
}

/// The job's buttons: each a form of its own, shown in the states it applies to.
fn actions(job: &Job) -> String {
    let link = segment(&job.id);
    let form = |action: JobAction, name: &str, extra: &str| {
        let hidden = if action.offered(job.state) {
            ""
        } else {
            " hidden"
        };
        format!(
            "<form method=\"post\" action=\"/jobs/{link}/{name}\" data-when=\"{}\"{hidden}{extra}>",
            offered_in(action)
        )
    };
    let mut out = String::from("<div class=\"actions\">");
    let buttons = [
        (JobAction::Pause, "pause", "Pause", "", ""),
        (JobAction::Resume, "resume", "Resume", "", ""),
        (JobAction::Retry, "retry", "Retry failed frames", "", ""),
        (JobAction::Cancel, "cancel", "Cancel job", "danger", ""),
        (
            JobAction::Delete { force: false },
            "delete",
            "Delete job",
            "danger",
            " data-confirm=\"Delete this job and its frames?\"",
        ),
    ];
    for (action, name, label, class, extra) in buttons {
        let _ = write!(
            out,
            "{}<button type=\"submit\" id=\"{name}\" class=\"{class}\">{label}</button></form>",
            form(action, name, extra)
        );
    }
    let _ = write!(
        out,
        "{}<input type=\"number\" name=\"priority\" min=\"{min}\" max=\"{max}\" \
         value=\"{priority}\" aria-label=\"Priority\"><button type=\"submit\" id=\"priority\">\
         Set priority</button></form></div>",
        form(JobAction::Priority(0), "priority", ""),
        min = PRIORITY_RANGE.start(),
        max = PRIORITY_RANGE.end(),
        priority = job.spec.priority,
    );
    out
}

/// The query that tells a frame's image apart from its earlier ones: a new preview or the
/// final image is a new URL, so the browser asks again.
fn image_version(frame: &FrameReport) -> String {
    match frame.preview {
        Some(completeness) => format!("p{completeness:.3}"),
        None => "final".to_string(),
    }
}

/// The caption under a frame's thumbnail.
fn frame_caption(index: u32, frame: Option<&FrameReport>) -> String {
    match frame.and_then(|frame| frame.preview) {
        Some(completeness) => format!("#{index} · preview {:.0}%", completeness * 100.0),
        None if frame.is_some() => format!("#{index}"),
        None => format!("#{index} · pending"),
    }
}

pub async fn job(State(dashboard): State<Dashboard>, Path(id): Path<String>) -> Response {
    let read = super::api::job_message(&dashboard.daemon, id);
    let (message, job, frames) = match read.await {
        Ok(read) => read,
        Err(failure) => return failure_page("Jobs", failure),
    };
    let dataset_id = job.spec.dataset_id.clone();
    let dataset = run(&dashboard.daemon, move |daemon| daemon.dataset(&dataset_id))
        .await
        .map(|dataset| dataset.name)
        .unwrap_or_else(|_| job.spec.dataset_id.clone());
    let id = escape(&job.id);
    let link = segment(&job.id);
    let eta = html::eta_seconds(&job, now_unix_ms())
        .map(html::duration)
        .unwrap_or_default();
    let mut body = format!(
        "<h1>Job <code>{id}</code></h1><dl class=\"facts\">\
         <dt>Name</dt><dd>{name}</dd><dt>Dataset</dt><dd>{dataset}</dd>\
         <dt>State</dt><dd class=\"job-state\">{state}</dd>\
         <dt>Frames</dt><dd><progress max=\"{total}\" value=\"{done}\"></progress> \
         <span class=\"frames\">{done}/{total}</span></dd>\
         <dt>ETA</dt><dd class=\"eta\">{eta}</dd>\
         <dt>Size</dt><dd>{width}×{height}</dd>\
         <dt>Priority</dt><dd class=\"priority\">{priority}</dd>\
         <dt>Submitted</dt><dd>{created} UTC</dd>",
        name = escape(job_name(&job)),
        dataset = escape(&dataset),
        state = html::state_badge(job.state),
        total = job.frames_total,
        done = job.frames_done,
        width = job.spec.request.width,
        height = job.spec.request.height,
        priority = job.spec.priority,
        created = html::time(job.created_unix_ms),
    );
    if let Some(error) = &job.error {
        let _ = write!(
            body,
            "<dt>Error</dt><dd class=\"error\">{}</dd>",
            escape(error)
        );
    }
    if !message.waiting_reason.is_empty() {
        let _ = write!(
            body,
            "<dt class=\"waiting\">Waiting</dt><dd class=\"waiting\">{}</dd>",
            escape(&message.waiting_reason)
        );
    }
    body.push_str("</dl>");
    if let (Some(video), Some(_)) = (&job.spec.video, job.video_size_bytes()) {
        let source = format!("/jobs/{link}/video");
        let _ = match video.container {
            VideoContainer::Gif => write!(
                body,
                "<section class=\"video\"><img src=\"{source}\" alt=\"the job's video\"></section>"
            ),
            container => write!(
                body,
                "<section class=\"video\"><video controls preload=\"metadata\">\
                 <source src=\"{source}\" type=\"{media}\"></video> \
                 <a href=\"{source}\" download>download</a></section>",
                media = container.media_type()
            ),
        };
    }
    body.push_str(&actions(&job));
    let by_index: HashMap<u32, &FrameReport> = frames.iter().map(|f| (f.index, f)).collect();
    body.push_str("<section class=\"thumbnails\" id=\"frames\">");
    for index in 0..job.frames_total {
        let frame = by_index.get(&index).copied();
        let picture = match frame {
            Some(frame) => format!(
                "<img src=\"/jobs/{link}/frames/{index}/thumbnail?v={version}\" \
                 alt=\"frame {index}\" loading=\"lazy\">",
                version = image_version(frame)
            ),
            None => "<span class=\"placeholder\"></span>".to_string(),
        };
        let _ = write!(
            body,
            "<a class=\"frame\" href=\"/jobs/{link}/frames/{index}\" data-index=\"{index}\" \
             data-state=\"{state}\">{picture}<span class=\"caption\">{caption}</span></a>",
            state = match frame {
                Some(f) if f.preview.is_some() => "preview",
                Some(_) => "final",
                None => "pending",
            },
            caption = frame_caption(index, frame),
        );
    }
    body.push_str("</section>");
    let data = format!(
        " data-job=\"{id}\" data-created=\"{}\"",
        job.created_unix_ms
    );
    Html(html::layout(
        &format!("Job {}", job.id),
        "Jobs",
        "job",
        &data,
        &body,
    ))
    .into_response()
}

pub async fn frame(
    State(dashboard): State<Dashboard>,
    Path((id, index)): Path<(String, u32)>,
) -> Response {
    let read = run(&dashboard.daemon, move |daemon| daemon.job_with_frames(&id));
    let (job, frames) = match read.await {
        Ok(read) => read,
        Err(failure) => return failure_page("Jobs", failure),
    };
    if index >= job.frames_total {
        let message = format!("job {} has {} frames", job.id, job.frames_total);
        return failure_page("Jobs", Failure(tonic::Status::not_found(message)));
    }
    let link = segment(&job.id);
    let id = escape(&job.id);
    let frame = frames.iter().find(|frame| frame.index == index);
    let mut body = format!(
        "<p><a href=\"/jobs/{link}\">← Job <code>{id}</code></a></p>\
         <h1>Frame {index}</h1>"
    );
    match frame {
        None => body.push_str("<p class=\"pending\">Not rendered yet.</p>"),
        Some(frame) => {
            let _ = write!(
                body,
                "<img class=\"large\" src=\"/jobs/{link}/frames/{index}/image?v={version}\" \
                 alt=\"frame {index}\"><dl class=\"facts\"><dt>Image</dt><dd>{kind}</dd>\
                 <dt>Worker</dt><dd>{worker}</dd><dt>Failed attempts</dt><dd>{attempts}</dd>",
                version = image_version(frame),
                kind = match frame.preview {
                    Some(completeness) =>
                        format!("preview, {:.0}% of the points", completeness * 100.0),
                    None => "final".to_string(),
                },
                worker = escape(&frame.worker),
                attempts = frame.failed_attempts,
            );
            if let Some(hit) = frame.dataset_cache_hit {
                let _ = write!(
                    body,
                    "<dt>Dataset cache</dt><dd>{}</dd>",
                    if hit { "hit" } else { "miss" }
                );
            }
            if let Some(cut) = &frame.cut {
                let _ = write!(
                    body,
                    "<dt>Points drawn</dt><dd>{} of {} in {} nodes</dd>",
                    cut.points_rendered, cut.points_total, cut.nodes
                );
            }
            body.push_str(
                "</dl><h2>Stage timings</h2><table class=\"timings\"><thead><tr><th>Stage</th>\
                 <th>ms</th><th>Clock</th></tr></thead><tbody>",
            );
            for timing in &frame.timings {
                let _ = write!(
                    body,
                    "<tr><td>{}</td><td class=\"number\">{:.2}</td><td>{}</td></tr>",
                    escape(&timing.stage),
                    timing.ms,
                    if timing.gpu_clock { "GPU" } else { "host" }
                );
            }
            body.push_str("</tbody></table>");
        }
    }
    let state = match frame {
        Some(frame) if frame.preview.is_some() => "preview",
        Some(_) => "final",
        None => "pending",
    };
    let data = format!(" data-job=\"{id}\" data-frame=\"{index}\" data-state=\"{state}\"");
    let title = format!("Frame {index} of {}", job.id);
    Html(html::layout(&title, "Jobs", "frame", &data, &body)).into_response()
}

pub async fn workers(State(dashboard): State<Dashboard>) -> Response {
    let daemon = dashboard.daemon.clone();
    let leases = match run(&dashboard.daemon, |daemon| daemon.leases()).await {
        Ok(leases) => leases,
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
         <th>Adapter</th><th>Capabilities</th><th>Current frame</th><th>Health</th></tr>\
         </thead><tbody>",
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
            pointfarm_proto::v1::AdapterKind::Hardware => "GPU",
            pointfarm_proto::v1::AdapterKind::Software => "software (CPU)",
            pointfarm_proto::v1::AdapterKind::Unspecified => "unknown",
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
             <td>{capabilities}</td><td>{current}</td><td>{health}</td></tr>",
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

/// A dataset's points from its files' headers; `None` for an object by URL or a file that
/// cannot be read now.
fn dataset_points(daemon: &Daemon, dataset: &Dataset) -> Option<u64> {
    if dataset.remote.is_some() {
        return None;
    }
    let reports = daemon.describe_dataset(&dataset.id, false).ok()?;
    reports
        .iter()
        .map(|report| report.outcome.as_ref().ok().map(|(info, _)| info.points))
        .sum()
}

/// Where a dataset's level-of-detail store stands.
fn store_state(daemon: &Daemon, dataset: &Dataset) -> String {
    if let Some(version) = daemon.stores.building_version(&dataset.sha256) {
        return format!("building ({}%)", version * 10);
    }
    let folder = daemon.config.data_dir.join("lod").join(&dataset.sha256);
    if pointfarm_render::cut::StoredLod::is_built(&folder) {
        "built".to_string()
    } else {
        "none (built when a frame needs it)".to_string()
    }
}

pub async fn datasets(State(dashboard): State<Dashboard>) -> Response {
    let read = run(&dashboard.daemon, |daemon| {
        let mut datasets = daemon.state.datasets()?;
        datasets.sort_by(|a, b| (b.created_unix_ms, &b.id).cmp(&(a.created_unix_ms, &a.id)));
        Ok(datasets
            .into_iter()
            .map(|dataset| {
                let points = dataset_points(daemon, &dataset);
                let store = store_state(daemon, &dataset);
                (dataset, points, store)
            })
            .collect::<Vec<_>>())
    });
    let datasets = match read.await {
        Ok(datasets) => datasets,
        Err(failure) => return failure_page("Datasets", failure),
    };
    let mut body = String::from(
        "<h1>Datasets</h1><div class=\"table\"><table id=\"datasets\"><thead><tr>\
         <th>Dataset</th><th>Name</th><th>Files</th><th>Points</th><th>Size</th>\
         <th>Store</th></tr></thead><tbody>",
    );
    for (dataset, points, store) in &datasets {
        let files = dataset.files();
        let file_names: Vec<String> = files.iter().map(|file| escape(&file.name)).collect();
        let _ = write!(
            body,
            "<tr><td><code>{id}</code></td><td>{name}</td>\
             <td><details><summary>{count}</summary>{names}</details></td>\
             <td class=\"number\">{points}</td><td class=\"number\">{size}</td>\
             <td>{store}</td></tr>",
            id = escape(&dataset.id),
            name = escape(&dataset.name),
            count = files.len(),
            names = file_names.join("<br>"),
            points = points.map_or("—".to_string(), |p| p.to_string()),
            size = html::bytes(dataset.size_bytes),
            store = escape(store),
        );
    }
    body.push_str("</tbody></table></div>");
    if datasets.is_empty() {
        body.push_str(
            "<p>No datasets yet: <code>pointfarm render --server</code> uploads one.</p>",
        );
    }
    Html(html::layout("Datasets", "Datasets", "datasets", "", &body)).into_response()
}

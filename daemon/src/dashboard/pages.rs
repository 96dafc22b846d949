//! The job pages, rendered on the server from the daemon's own records: jobs (newest first,
//! filtered by state, each with its stage), a job with its frames as thumbnails, a frame
//! large with its stage timings; and a job's buttons (`actions`). The script
//! (`assets/dashboard.js`) keeps them current from the event stream.

use std::collections::HashMap;
use std::fmt::Write;
use std::sync::Arc;

use axum::extract::{Path, RawQuery, State};
use axum::response::{Html, IntoResponse, Response};
use axum::routing::get;
use axum::Router;
use pointfarm_render::encode::video::VideoContainer;

use super::actions::JobAction;
use super::api::{failure_page, run};
use super::auth::field;
use super::failure::Failure;
use super::filter::{job_name, JobQuery};
use super::html::{self, escape, segment};
use super::Dashboard;
use crate::error::DaemonError;
use crate::job_control::PRIORITY_RANGE;
use crate::model::{now_unix_ms, FrameReport, Job, JobState};
use crate::service::Daemon;

/// How many jobs the jobs page lists unless asked for more (`?limit=N`): enough for a day's
/// work, few enough to paint at once.
const JOBS_SHOWN: usize = 200;

/// How many jobs the state database is asked for at once while the jobs page is read.
const JOBS_READ_AT_ONCE: u32 = 1000;

/// The jobs `query` takes, newest first, the first `limit` of them, and how many it takes.
/// Every job is read, a page at a time, and only the newest `limit` are kept between pages.
fn newest_jobs(
    daemon: &Daemon,
    query: &JobQuery,
    limit: usize,
) -> Result<(Vec<Job>, usize), DaemonError> {
    let newest_first =
        |a: &Job, b: &Job| (b.created_unix_ms, &b.id).cmp(&(a.created_unix_ms, &a.id));
    let mut jobs = Vec::new();
    let mut matching = 0;
    let mut token = String::new();
    loop {
        let page = daemon.find_jobs(&query.stored, JOBS_READ_AT_ONCE, &token)?;
        let before = jobs.len();
        jobs.extend(page.items.into_iter().filter(|job| query.matches_name(job)));
        matching += jobs.len() - before;
        if jobs.len() > limit.saturating_mul(2) {
            jobs.sort_by(newest_first);
            jobs.truncate(limit);
        }
        if page.next_token.is_empty() {
            break;
        }
        token = page.next_token;
    }
    jobs.sort_by(newest_first);
    jobs.truncate(limit);
    Ok((jobs, matching))
}

/// `/` (the jobs), `/jobs/{id}` (a job) and `/jobs/{id}/frames/{index}` (a frame).
pub(super) fn routes() -> Router<Dashboard> {
    Router::new()
        .route("/", get(jobs))
        .route("/jobs/{id}", get(job))
        .route("/jobs/{id}/frames/{index}", get(frame))
}

/// What the jobs page says of each dataset, by id: its name and whether its store builds.
fn dataset_names(daemon: &Daemon) -> Result<HashMap<String, (String, bool)>, DaemonError> {
    Ok(daemon
        .state
        .datasets()?
        .into_iter()
        .map(|dataset| {
            let building = daemon.stores.building_version(&dataset.sha256).is_some();
            (dataset.id, (dataset.name, building))
        })
        .collect())
}

/// What a job is doing, for users: waiting for its dataset's store to be built ("store
/// build"), drawing previews while it builds ("previews"), rendering its final frames
/// ("final frames"), making its video ("video"); empty once it has ended. Each live event
/// carries it (`events`), so a row the script adds shows it at once.
pub(super) fn job_stage(job: &Job, store_building: bool) -> &'static str {
    match job.stage() {
        "frames" if store_building && job.spec.preview => "previews",
        "frames" if store_building => "store build",
        "frames" => "final frames",
        other => other,
    }
}

/// Dataset `dataset_id`'s name, and whether its store is being built now.
pub(super) fn dataset_building(
    daemon: &Daemon,
    dataset_id: &str,
) -> Result<(String, bool), DaemonError> {
    let dataset = daemon.dataset(dataset_id)?;
    let building = daemon.stores.building_version(&dataset.sha256).is_some();
    Ok((dataset.name, building))
}

/// The stage `job` shows now ([`job_stage`]), its dataset's store read if it renders frames.
pub(super) async fn shown_stage(daemon: &Arc<Daemon>, job: &Job) -> &'static str {
    if job.stage() != "frames" {
        return job_stage(job, false);
    }
    let dataset_id = job.spec.dataset_id.clone();
    let building = run(daemon, move |daemon| dataset_building(daemon, &dataset_id))
        .await
        .is_ok_and(|(_, building)| building);
    job_stage(job, building)
}

/// One row of the jobs table, its label chips linking to `query` narrowed by each; the
/// script builds the same from a job event.
fn job_row(job: &Job, dataset: &str, stage: &str, query: &JobQuery, now_ms: i64) -> String {
    let id = escape(&job.id);
    let eta = html::eta_seconds(job, now_ms)
        .map(html::duration)
        .unwrap_or_default();
    let chips = html::label_chips(&job.spec.labels, |key, value| {
        list_link(&query.query_with(query.state(), Some((key, value))))
    });
    format!(
        "<tr data-job=\"{id}\" data-created=\"{created}\">\
         <td><a href=\"/jobs/{link}\">{id}</a></td><td>{name}</td><td>{chips}</td>\
         <td data-dataset=\"{dataset_id}\">{dataset}</td><td class=\"job-state\">{state}</td><td class=\"stage\">{stage}</td>\
         <td><progress max=\"{total}\" value=\"{done}\"></progress></td>\
         <td class=\"frames\">{done}/{total}</td><td class=\"eta\">{eta}</td></tr>",
        created = job.created_unix_ms,
        link = segment(&job.id),
        name = escape(job_name(job)),
        dataset = escape(dataset),
        dataset_id = escape(&job.spec.dataset_id),
        state = html::state_badge(job.state),
        total = job.frames_total,
        done = job.frames_done,
    )
}

/// The jobs list with the filter `query` (a URL's query, without `?`).
fn list_link(query: &str) -> String {
    if query.is_empty() {
        "/".to_string()
    } else {
        format!("/?{query}")
    }
}

/// The list's filters: a link per state, the filter box (name and one label more, the
/// current ones kept) and the labels filtered by, each a chip that drops it.
fn filters(query: &JobQuery) -> String {
    use JobState::*;
    let mut out = String::from("<nav class=\"filters\" aria-label=\"State\">");
    let current = query.state();
    let states = [Queued, Running, Paused, Succeeded, Failed, Cancelled].map(Some);
    for state in [None].into_iter().chain(states) {
        let mark = if state == current {
            " aria-current=\"true\""
        } else {
            ""
        };
        let _ = write!(
            out,
            "<a href=\"{href}\"{mark}>{label}</a>",
            href = escape(&list_link(&query.query_with(state, None))),
            label = state.map_or("all", JobState::name),
        );
    }
    out.push_str("</nav><form class=\"filter\" method=\"get\" action=\"/\" role=\"search\">");
    if let Some(state) = current {
        let _ = write!(
            out,
            "<input type=\"hidden\" name=\"state\" value=\"{}\">",
            state.name()
        );
    }
    for (key, value) in query.labels() {
        let _ = write!(
            out,
            "<input type=\"hidden\" name=\"label\" value=\"{}\">",
            escape(&format!("{key}={value}"))
        );
    }
    let _ = write!(
        out,
        "<input type=\"search\" id=\"filter-name\" name=\"name\" value=\"{name}\" \
         placeholder=\"name contains\" aria-label=\"Name contains\">\
         <input type=\"text\" id=\"filter-label\" name=\"label\" placeholder=\"label key=value\" \
         aria-label=\"Label (key=value)\"><button type=\"submit\" id=\"filter-apply\">Filter</button>",
        name = escape(&query.name),
    );
    if !query.is_empty() {
        out.push_str("<a href=\"/\" class=\"clear\">clear</a>");
    }
    out.push_str("</form>");
    if !query.labels().is_empty() {
        out.push_str("<p class=\"filtered\">Labels: ");
        for (key, value) in query.labels() {
            let _ = write!(
                out,
                "<a class=\"chip remove\" href=\"{href}\" title=\"Show jobs without this \
                 filter\">{key}={value} ×</a>",
                href = escape(&list_link(&query.without_label(key).query())),
                key = escape(key),
                value = escape(value),
            );
        }
        out.push_str("</p>");
    }
    out
}

pub async fn jobs(State(dashboard): State<Dashboard>, RawQuery(query): RawQuery) -> Response {
    let raw = query.unwrap_or_default().into_bytes();
    let query = match JobQuery::parse(&raw) {
        Ok(query) => query,
        Err(failure) => return failure_page("Jobs", failure),
    };
    let limit = field(&raw, "limit")
        .and_then(|limit| limit.parse::<usize>().ok())
        .unwrap_or(JOBS_SHOWN)
        .max(1);
    let read = run(&dashboard.daemon, {
        let query = query.clone();
        move |daemon| Ok((newest_jobs(daemon, &query, limit)?, dataset_names(daemon)?))
    });
    let ((jobs, matching), names) = match read.await {
        Ok(read) => read,
        Err(failure) => return failure_page("Jobs", failure),
    };
    let now_ms = now_unix_ms();
    let mut body = format!("<h1>Jobs</h1>{}", filters(&query));
    let _ = write!(
        body,
        "<p class=\"count\">{shown} of {matching} jobs</p>\
         <div class=\"table\"><table id=\"jobs\"><thead><tr><th>Job</th><th>Name</th>\
         <th>Labels</th><th>Dataset</th><th>State</th><th>Stage</th><th>Progress</th>\
         <th>Frames</th><th>ETA</th></tr></thead><tbody>",
        shown = jobs.len()
    );
    for job in &jobs {
        let (dataset, building) = match names.get(&job.spec.dataset_id) {
            Some((name, building)) => (name.as_str(), *building),
            None => (job.spec.dataset_id.as_str(), false),
        };
        let stage = job_stage(job, building);
        body.push_str(&job_row(job, dataset, stage, &query, now_ms));
    }
    body.push_str("</tbody></table></div>");
    if matching > jobs.len() {
        let more = jobs.len().saturating_mul(5);
        let filter = query.query();
        let and = if filter.is_empty() { "" } else { "&" };
        let _ = write!(
            body,
            "<p><a href=\"/?{filter}{and}limit={more}\">Show more</a></p>",
            filter = escape(&filter),
        );
    }
    let labels = serde_json::to_string(query.labels()).unwrap_or_default();
    let data = format!(
        " data-filter=\"{state}\" data-labels=\"{labels}\" data-name=\"{name}\" \
         data-shown=\"{shown}\" data-matching=\"{matching}\"",
        state = query.state().map_or("", JobState::name),
        labels = escape(&labels),
        name = escape(&query.name),
        shown = jobs.len(),
    );
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
    let (dataset, building) = run(&dashboard.daemon, move |daemon| {
        dataset_building(daemon, &dataset_id)
    })
    .await
    .unwrap_or_else(|_| (job.spec.dataset_id.clone(), false));
    let id = escape(&job.id);
    let link = segment(&job.id);
    let eta = html::eta_seconds(&job, now_unix_ms())
        .map(html::duration)
        .unwrap_or_default();
    let mut body = format!(
        "<h1>Job <code>{id}</code></h1><dl class=\"facts\">\
         <dt>Name</dt><dd>{name}</dd><dt>Labels</dt><dd>{labels}</dd>\
         <dt>Dataset</dt><dd>{dataset}</dd>\
         <dt>State</dt><dd class=\"job-state\">{state}</dd>\
         <dt>Stage</dt><dd class=\"stage\">{stage}</dd>\
         <dt>Frames</dt><dd><progress max=\"{total}\" value=\"{done}\"></progress> \
         <span class=\"frames\">{done}/{total}</span></dd>\
         <dt>ETA</dt><dd class=\"eta\">{eta}</dd>\
         <dt>Size</dt><dd>{width}×{height}</dd>\
         <dt>Priority</dt><dd class=\"priority\">{priority}</dd>\
         <dt>Submitted</dt><dd>{created} UTC</dd>",
        name = escape(job_name(&job)),
        labels = html::label_chips(&job.spec.labels, |key, value| {
            list_link(&JobQuery::default().query_with(None, Some((key, value))))
        }),
        dataset = escape(&dataset),
        state = html::state_badge(job.state),
        stage = job_stage(&job, building),
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
    if !message.preview_video.is_empty() {
        let _ = write!(
            body,
            "<dt>Preview video</dt><dd class=\"preview-video\">{}</dd>",
            message.preview_video
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

#[cfg(test)]
mod tests {
    use pointfarm_render::encode::video::{VideoContainer, VideoSettings};
    use pointfarm_render::request::RenderRequest;

    use super::*;
    use crate::model::JobSpec;

    fn job(state: JobState, frames_done: u32, preview: bool, video: bool) -> Job {
        let request = RenderRequest::turntable(8, 8, 4);
        let mut spec = JobSpec::new("nightly".into(), "ds-1".into(), request);
        spec.preview = preview;
        spec.video =
            video.then(|| VideoSettings::new(VideoContainer::Webm, None, 24, 30).expect("a video"));
        Job {
            id: "job-1".into(),
            spec,
            state,
            frames_total: 4,
            frames_done,
            error: None,
            created_unix_ms: 0,
            updated_unix_ms: 0,
            worker_failures: Default::default(),
            blocklist: Default::default(),
            encode: None,
            outputs: Default::default(),
        }
    }

    #[test]
    fn a_jobs_stage_follows_its_store_its_frames_and_its_video() {
        use JobState::*;
        assert_eq!(
            job_stage(&job(Queued, 0, false, false), true),
            "store build"
        );
        assert_eq!(job_stage(&job(Running, 0, true, false), true), "previews");
        assert_eq!(
            job_stage(&job(Running, 2, true, false), false),
            "final frames"
        );
        assert_eq!(job_stage(&job(Running, 4, false, true), false), "video");
        assert_eq!(job_stage(&job(Running, 4, false, true), true), "video");
        assert_eq!(job_stage(&job(Succeeded, 4, false, true), false), "");
        assert_eq!(job_stage(&job(Cancelled, 1, true, false), true), "");
    }
}

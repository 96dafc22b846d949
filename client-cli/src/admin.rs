//! `pointfarm dataset|jobs|frames`: managing a server's datasets and jobs. Human-readable
//! tables by default, `--json` for scripts (one JSON value on stdout: the API's messages in
//! their proto3 JSON mapping, or the wrappers of `admin_json.rs`).

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::{Args, Subcommand};
use pointfarm_proto::v1 as pb;

use pointfarm_render::ingest::dataset_files;

use crate::admin_json::{
    json_line, Deleted, ExportedDataset, FetchedFrames, JobDetails, StageStatistics,
};
use crate::credentials::ClientCredentials;
use crate::remote::{answer, state_name, status_error, Client};

/// Items asked for per page of a listing.
const PAGE_SIZE: u32 = 100;

/// Every item of a paged listing: `page` fetches the page at a token and returns its items and
/// the next token, empty after the last page.
async fn every_page<T, Page>(mut page: impl FnMut(String) -> Page) -> Result<Vec<T>>
where
    Page: std::future::Future<Output = Result<(Vec<T>, String)>>,
{
    let (mut all, mut token) = (Vec::new(), String::new());
    loop {
        let (items, next) = page(token).await?;
        all.extend(items);
        if next.is_empty() {
            return Ok(all);
        }
        token = next;
    }
}

#[derive(Args, Clone)]
pub struct ServerArgs {
    /// The pointfarm server.
    #[arg(
        long,
        env = "POINTFARM_SERVER",
        default_value = "http://127.0.0.1:50051",
        global = true
    )]
    pub server: String,
    #[command(flatten)]
    pub credentials: ClientCredentials,
    /// Print JSON instead of tables: the API's messages in the proto3 JSON mapping.
    #[arg(long, global = true)]
    pub json: bool,
}

#[derive(Subcommand)]
pub enum DatasetCommand {
    /// Upload LAS/LAZ files or folders of them as one dataset (a file the server already
    /// has is not sent again).
    Add {
        /// LAS/LAZ files, or folders of them.
        #[arg(required = true, value_name = "INPUT")]
        inputs: Vec<PathBuf>,
    },
    /// Register files or folders that are already on the server, under its data roots, as
    /// one dataset; or one COPC object by its URL (s3://, http://, https://) under a prefix
    /// the server allows (`serve --allow-url-prefix`), which the server never copies.
    Register {
        /// Files or folders on the server, under one of its `--data-root`s, or one URL.
        #[arg(required = true, value_name = "PATH|URL")]
        paths: Vec<String>,
    },
    /// The server's datasets.
    List,
    /// One dataset: its size, files, and URL where it is read by one.
    Get {
        /// The dataset's id.
        id: String,
    },
    /// Write a dataset as a COPC 1.0 file, made by the server from its levels of detail
    /// (built first when it has none).
    Export {
        /// The dataset's id.
        id: String,
        #[command(flatten)]
        output: crate::export::OutputArgs,
    },
    /// Delete a dataset (files other datasets share stay).
    Rm {
        /// The dataset's id.
        id: String,
    },
}

#[derive(Subcommand)]
pub enum JobsCommand {
    /// The server's jobs, with their state and progress, and the jobs each runs after.
    List {
        /// Only jobs in this state: queued, running, succeeded, failed, cancelled.
        #[arg(long)]
        state: Option<String>,
    },
    /// A job with per-stage timing statistics (median and p95) over its frames.
    Show {
        /// The job's id.
        id: String,
    },
    /// Cancel a queued or running job; its workers drop their frames. A job that has ended
    /// is left as it is (exit status 0).
    Cancel {
        /// The job's id.
        id: String,
    },
    /// Follow a job until it ends (with --json: each of its events on a line of its own).
    Watch {
        /// The job's id.
        id: String,
    },
    /// Frames being rendered now: which worker holds each, and until when.
    Leases,
    /// Workers connected now: their adapters, the largest image side each draws, their tags.
    Workers,
}

#[derive(Subcommand)]
pub enum FramesCommand {
    /// Download a job's finished frames.
    Fetch {
        /// The job's id.
        job: String,
        /// Folder to write the frames to (frame_00000.png, ...).
        #[arg(long, short)]
        out: PathBuf,
        /// First frame index to fetch (to resume a download).
        #[arg(long, default_value_t = 0)]
        from: u32,
    },
}

fn runtime() -> Result<tokio::runtime::Runtime> {
    tokio::runtime::Runtime::new().context("starting the async runtime")
}

/// One line on a job's preview frames (drawn from the dataset's chunk starts while the
/// server builds its store), which final frames replace: how many, and how complete.
fn preview_summary(job: &pb::Job) -> Option<String> {
    let previews: Vec<&pb::FrameFinished> = job.frames.iter().filter(|f| f.preview).collect();
    let first = previews.first()?;
    let (low, high) = previews
        .iter()
        .fold((first.completeness, first.completeness), |(l, h), f| {
            (l.min(f.completeness), h.max(f.completeness))
        });
    Some(format!(
        "previews: {} of {} frames, {:.3}% to {:.3}% of the points; final: {}/{}",
        previews.len(),
        job.frames_total,
        low * 100.0,
        high * 100.0,
        job.frames_done,
        job.frames_total
    ))
}

/// One line on the frames rendered from levels of detail: the median cut and what was read.
fn cut_summary(frames: &[pb::FrameFinished]) -> Option<String> {
    let cuts: Vec<&pb::FrameCut> = frames.iter().filter_map(|f| f.cut.as_ref()).collect();
    let first = cuts.first()?;
    let median = |value: fn(&pb::FrameCut) -> u64| {
        let mut values: Vec<u64> = cuts.iter().map(|c| value(c)).collect();
        values.sort_unstable();
        values[values.len() / 2]
    };
    let sum = |value: fn(&pb::FrameCut) -> u64| cuts.iter().map(|c| value(c)).sum::<u64>();
    Some(format!(
        "levels of detail, {} frames: median cut {} nodes, {} of {} points; {} nodes read ({:.1} MiB, {:.1} MiB ahead), {} host and {} GPU cache hits{}",
        cuts.len(), median(|c| c.nodes), median(|c| c.points_rendered), first.points_total,
        sum(|c| c.nodes_read), sum(|c| c.bytes_read) as f64 / f64::from(1 << 20),
        sum(|c| c.read_ahead_bytes) as f64 / f64::from(1 << 20), sum(|c| c.host_hits), sum(|c| c.gpu_hits),
        if cuts.iter().any(|c| c.limited_by_budget) { "; some cuts bounded by the GPU budget" } else { "" },
    ))
}

pub fn dataset(server: &ServerArgs, command: DatasetCommand) -> Result<()> {
    runtime()?.block_on(async {
        let mut client = Client::connect(&server.server, &server.credentials).await?;
        match command {
            DatasetCommand::Add { inputs } => {
                let files = dataset_files(&inputs)?;
                print_dataset(server, &client.ensure_dataset(&files).await?)?
            }
            DatasetCommand::Register { paths } => {
                let request = pb::RegisterDatasetRequest {
                    path: String::new(),
                    name: String::new(),
                    paths,
                };
                let dataset = answer(client.datasets.register_dataset(request).await)?;
                print_dataset(server, &dataset)?
            }
            DatasetCommand::Get { id } => {
                let request = pb::GetDatasetRequest { id };
                let dataset = answer(client.datasets.get_dataset(request).await)?;
                print_dataset(server, &dataset)?
            }
            DatasetCommand::List => {
                let all = every_page(|page_token| {
                    let mut datasets = client.datasets.clone();
                    let request = pb::ListDatasetsRequest {
                        page_size: PAGE_SIZE,
                        page_token,
                    };
                    async move {
                        answer(datasets.list_datasets(request).await)
                            .map(|p| (p.datasets, p.next_page_token))
                    }
                })
                .await?;
                if server.json {
                    // Every page in one response, as the API would return it with no limit.
                    let response = pb::ListDatasetsResponse {
                        datasets: all,
                        next_page_token: String::new(),
                    };
                    outln!("{}", json_line(&response)?);
                } else {
                    outln!("{:<20} {:>12}  name", "id", "bytes");
                    for d in &all {
                        outln!("{:<20} {:>12}  {}{}", d.id, d.size_bytes, d.name, source(d));
                    }
                }
            }
            DatasetCommand::Export { id, output } => {
                output.check()?;
                let summary = client.export_dataset(&id, &output.copc).await?;
                if server.json {
                    let file = output.copc.display().to_string();
                    outln!("{}", json_line(&ExportedDataset { file, summary: &summary })?);
                } else {
                    outln!(
                        "{}: {} points in {} nodes, {:.1} MB, COPC 1.0 (point format {}, scale {}), in {:.1} s on the server",
                        output.copc.display(),
                        summary.points,
                        summary.nodes,
                        summary.size_bytes as f64 / 1e6,
                        summary.point_format,
                        summary.scale.first().copied().unwrap_or_default(),
                        summary.seconds,
                    );
                }
            }
            DatasetCommand::Rm { id } => {
                client
                    .datasets
                    .delete_dataset(pb::DeleteDatasetRequest { id: id.clone() })
                    .await
                    .map_err(status_error)?;
                if server.json {
                    outln!("{}", json_line(&Deleted { deleted: &id })?);
                } else {
                    outln!("deleted {id}");
                }
            }
        }
        Ok(())
    })
}

fn print_dataset(server: &ServerArgs, d: &pb::Dataset) -> Result<()> {
    if server.json {
        outln!("{}", json_line(d)?);
    } else {
        let files = match d.files.len() {
            0 | 1 => String::new(),
            n => format!(", {n} files"),
        };
        outln!(
            "{}  {} ({} bytes{files}){}",
            d.id,
            d.name,
            d.size_bytes,
            source(d)
        );
    }
    Ok(())
}

/// Where a dataset by URL is read from, after its name; nothing for files on the server.
fn source(d: &pb::Dataset) -> String {
    match (d.url.as_str(), d.version.as_str()) {
        ("", _) => String::new(),
        (url, "") => format!("  {url}"),
        (url, version) => format!("  {url} (version {version})"),
    }
}

fn parse_state(state: &str) -> Result<pb::JobState> {
    Ok(match state.to_ascii_lowercase().as_str() {
        "queued" => pb::JobState::Queued,
        "running" => pb::JobState::Running,
        "succeeded" => pb::JobState::Succeeded,
        "failed" => pb::JobState::Failed,
        "cancelled" | "canceled" => pb::JobState::Cancelled,
        other => anyhow::bail!(
            "'{other}' is not a job state (queued, running, succeeded, failed, cancelled)"
        ),
    })
}

/// Median and 95th percentile of each stage over a job's frames, in stage order.
pub fn stage_statistics(frames: &[pb::FrameFinished]) -> Vec<StageStatistics> {
    let mut stages: Vec<(String, Vec<f64>)> = Vec::new();
    for timing in frames.iter().flat_map(|f| &f.timings) {
        match stages.iter_mut().find(|(name, _)| *name == timing.stage) {
            Some((_, values)) => values.push(timing.ms),
            None => stages.push((timing.stage.clone(), vec![timing.ms])),
        }
    }
    stages
        .into_iter()
        .map(|(name, mut values)| {
            values.sort_by(f64::total_cmp);
            let at = |q: f64| values[((values.len() - 1) as f64 * q).round() as usize];
            StageStatistics {
                stage: name,
                median_ms: at(0.5),
                p95_ms: at(0.95),
            }
        })
        .collect()
}

pub fn jobs(server: &ServerArgs, command: JobsCommand) -> Result<()> {
    runtime()?.block_on(async {
        let mut client = Client::connect(&server.server, &server.credentials).await?;
        match command {
            JobsCommand::List { state } => {
                let state = state
                    .as_deref()
                    .map(parse_state)
                    .transpose()?
                    .unwrap_or(pb::JobState::Unspecified);
                let all = every_page(|page_token| {
                    let mut jobs = client.jobs.clone();
                    let request = pb::ListJobsRequest {
                        state: state as i32,
                        page_size: PAGE_SIZE,
                        page_token,
                    };
                    async move {
                        answer(jobs.list_jobs(request).await).map(|p| (p.jobs, p.next_page_token))
                    }
                })
                .await?;
                if server.json {
                    // Every page in one response, as the API would return it with no limit.
                    outln!(
                        "{}",
                        json_line(&pb::ListJobsResponse {
                            jobs: all,
                            next_page_token: String::new()
                        })?
                    );
                } else {
                    outln!(
                        "{:<18} {:<10} {:>9} {:>8}  dataset",
                        "id",
                        "state",
                        "frames",
                        "priority"
                    );
                    for j in &all {
                        let frames = format!("{}/{}", j.frames_done, j.frames_total);
                        let after = match j.after_job_ids.as_slice() {
                            [] => String::new(),
                            ids => format!("  after {}", ids.join(", ")),
                        };
                        outln!(
                            "{:<18} {:<10} {:>9} {:>8}  {}{after}",
                            j.id,
                            state_name(j.state),
                            frames,
                            j.priority,
                            j.dataset_id
                        );
                    }
                }
            }
            JobsCommand::Show { id } => {
                let job = answer(client.jobs.get_job(pb::GetJobRequest { id }).await)?;
                let stats = stage_statistics(&job.frames);
                if server.json {
                    outln!(
                        "{}",
                        json_line(&JobDetails {
                            job: &job,
                            stage_statistics: stats
                        })?
                    );
                } else {
                    outln!(
                        "job {}  {}  {}/{} frames  dataset {}",
                        job.id,
                        state_name(job.state),
                        job.frames_done,
                        job.frames_total,
                        job.dataset_id
                    );
                    if !job.error.is_empty() {
                        outln!("error: {}", job.error);
                    }
                    for line in scheduling_lines(&job) {
                        outln!("{line}");
                    }
                    let retried: Vec<String> = job
                        .frames
                        .iter()
                        .filter(|f| f.failed_attempts > 0)
                        .map(|f| format!("{} ({} failed)", f.index, f.failed_attempts))
                        .collect();
                    if !retried.is_empty() {
                        outln!(
                            "frames that needed more than one attempt: {}",
                            retried.join(", ")
                        );
                    }
                    if let Some(line) = cut_summary(&job.frames) {
                        outln!("{line}");
                    }
                    if let Some(line) = preview_summary(&job) {
                        outln!("{line}");
                    }
                    if !stats.is_empty() {
                        outln!("{:<12} {:>10} {:>10}", "stage", "median ms", "p95 ms");
                        for s in &stats {
                            outln!("{:<12} {:>10.2} {:>10.2}", s.stage, s.median_ms, s.p95_ms);
                        }
                    }
                }
            }
            JobsCommand::Cancel { id } => {
                let request = pb::CancelJobRequest { id: id.clone() };
                let (job, cancelled) = match client.jobs.cancel_job(request).await {
                    Ok(reply) => (reply.into_inner(), true),
                    // A job that has ended has nothing left to cancel: it is shown as it is.
                    Err(status) if status.code() == tonic::Code::FailedPrecondition => {
                        let mut job = answer(client.jobs.get_job(pb::GetJobRequest { id }).await)?;
                        if !has_ended(job.state) {
                            return Err(status_error(status));
                        }
                        // Shown as a cancel answers: the job, without its frames.
                        job.frames.clear();
                        (job, false)
                    }
                    Err(status) => return Err(status_error(status)),
                };
                if server.json {
                    outln!("{}", json_line(&job)?);
                } else if cancelled {
                    outln!("job {} {}", job.id, state_name(job.state));
                } else {
                    outln!(
                        "job {} already {}; nothing to cancel",
                        job.id,
                        state_name(job.state)
                    );
                }
            }
            JobsCommand::Watch { id } => {
                if server.json {
                    // Each event as it comes, one line each, so a script sees the progress;
                    // the last one's job has ended.
                    client
                        .watch(&id, |event| {
                            outln!("{}", json_line(event)?);
                            Ok(())
                        })
                        .await?;
                } else {
                    let job = client.follow(&id, false, |_| {}).await?;
                    outln!(
                        "job {} {} ({}/{} frames){}",
                        job.id,
                        state_name(job.state),
                        job.frames_done,
                        job.frames_total,
                        if job.error.is_empty() {
                            String::new()
                        } else {
                            format!(": {}", job.error)
                        }
                    );
                }
            }
            JobsCommand::Workers => {
                let workers =
                    answer(client.jobs.list_workers(pb::ListWorkersRequest {}).await)?.workers;
                if server.json {
                    outln!("{}", json_line(&pb::ListWorkersResponse { workers })?);
                } else {
                    outln!(
                        "{:<24} {:<9} {:>10}  {:<32} tags",
                        "worker",
                        "adapter",
                        "max side",
                        "name"
                    );
                    for w in &workers {
                        let caps = w.capabilities.clone().unwrap_or_default();
                        let kind = match pb::AdapterKind::try_from(caps.adapter_kind) {
                            Ok(pb::AdapterKind::Hardware) => "GPU",
                            Ok(pb::AdapterKind::Software) => "software",
                            _ => "unknown",
                        };
                        let side = if caps.max_frame_side == 0 {
                            "any".to_string()
                        } else {
                            caps.max_frame_side.to_string()
                        };
                        let name = worker_label(&w.worker_name, w.embedded);
                        outln!(
                            "{name:<24} {kind:<9} {side:>10}  {:<32} {}",
                            caps.adapter_name,
                            caps.tags.join(", ")
                        );
                    }
                }
            }
            JobsCommand::Leases => {
                let leases =
                    answer(client.jobs.list_leases(pb::ListLeasesRequest {}).await)?.leases;
                let now = std::time::SystemTime::now()
                    .duration_since(std::time::UNIX_EPOCH)
                    .map(|d| d.as_millis() as i64)
                    .unwrap_or(0);
                if server.json {
                    outln!("{}", json_line(&pb::ListLeasesResponse { leases })?);
                } else {
                    outln!(
                        "{:<38} {:<18} {:>6}  {:<24} expires",
                        "lease",
                        "job",
                        "frame",
                        "worker"
                    );
                    for l in &leases {
                        let expires = (l.expires_unix_ms - now) as f64 / 1e3;
                        let worker = worker_label(&l.worker_name, l.embedded);
                        outln!(
                            "{:<38} {:<18} {:>6}  {:<24} in {expires:.1} s",
                            l.lease_id,
                            l.job_id,
                            l.frame_index,
                            worker
                        );
                    }
                }
            }
        }
        Ok(())
    })
}

/// A worker's name as the tables show it, marked when it is the daemon's embedded worker.
fn worker_label(name: &str, embedded: bool) -> String {
    if embedded {
        format!("{name} (embedded)")
    } else {
        name.to_string()
    }
}

/// What `jobs show` says of a job's workers: what it requires of them, who rendered its
/// frames, who is blocklisted, the jobs it runs after, and why it waits (for one of those, or
/// for a connected worker that can render it).
fn scheduling_lines(job: &pb::Job) -> Vec<String> {
    let mut lines = Vec::new();
    if let Some(required) = job.requirements.as_ref() {
        let mut parts = Vec::new();
        if required.gpu {
            parts.push("a GPU".to_string());
        }
        if !required.tags.is_empty() {
            parts.push(format!("tags {}", required.tags.join(", ")));
        }
        if !parts.is_empty() {
            lines.push(format!("requires: {}", parts.join(" and ")));
        }
    }
    let mut rendered: std::collections::BTreeMap<&str, u32> = Default::default();
    for frame in &job.frames {
        if !frame.worker_name.is_empty() {
            *rendered.entry(frame.worker_name.as_str()).or_default() += 1;
        }
    }
    if !rendered.is_empty() {
        let by: Vec<String> = rendered
            .iter()
            .map(|(worker, frames)| format!("{worker} {frames}"))
            .collect();
        lines.push(format!("frames by worker: {}", by.join(", ")));
    }
    if !job.blocklisted_workers.is_empty() {
        let listed: Vec<String> = job
            .blocklisted_workers
            .iter()
            .map(|w| format!("{} ({} failed frames)", w.worker_name, w.failed_frames))
            .collect();
        lines.push(format!("blocklisted workers: {}", listed.join(", ")));
    }
    if !job.after_job_ids.is_empty() {
        lines.push(format!("runs after: {}", job.after_job_ids.join(", ")));
    }
    if !job.waiting_reason.is_empty() {
        lines.push(format!("waiting: {}", job.waiting_reason));
    }
    for refusal in &job.refusals {
        lines.push(format!(
            "  worker {} cannot render it: {}",
            refusal.worker_name, refusal.reason
        ));
    }
    lines
}

/// Whether a job in `state` has ended (succeeded, failed or cancelled).
fn has_ended(state: i32) -> bool {
    matches!(
        pb::JobState::try_from(state),
        Ok(pb::JobState::Succeeded | pb::JobState::Failed | pb::JobState::Cancelled)
    )
}

pub fn frames(server: &ServerArgs, command: FramesCommand) -> Result<()> {
    runtime()?.block_on(async {
        let mut client = Client::connect(&server.server, &server.credentials).await?;
        match command {
            FramesCommand::Fetch { job, out, from } => {
                let written = client.fetch_frames(&job, from, &out).await?;
                if server.json {
                    outln!("{}", json_line(&FetchedFrames::new(&job, &out, &written))?);
                } else {
                    outln!("{} frames in {}", written.len(), out.display());
                }
            }
        }
        Ok(())
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stage_statistics_give_median_and_p95_per_stage() {
        let frames: Vec<pb::FrameFinished> = (0..20)
            .map(|i| pb::FrameFinished {
                index: i,
                dataset_cache_hit: None,
                failed_attempts: 0,
                cut: None,
                worker_name: String::new(),
                preview: false,
                completeness: 0.0,
                timings: vec![
                    pb::StageTiming {
                        stage: "rasterize".into(),
                        ms: i as f64,
                        gpu_clock: true,
                    },
                    pb::StageTiming {
                        stage: "encode".into(),
                        ms: 1.0,
                        gpu_clock: false,
                    },
                ],
            })
            .collect();
        let stats = stage_statistics(&frames);
        assert_eq!(stats[0].stage, "rasterize");
        assert_eq!(stats[0].median_ms, 10.0);
        assert_eq!(stats[0].p95_ms, 18.0);
        assert_eq!(
            stats[1],
            StageStatistics {
                stage: "encode".to_string(),
                median_ms: 1.0,
                p95_ms: 1.0
            }
        );
    }
}

//! `pointfarm jobs`: listing, showing and following a server's jobs, and controlling them
//! (cancel, retry, pause, resume, priority, rm).

use std::collections::{BTreeMap, HashMap};

use anyhow::Result;
use clap::Subcommand;
use pointfarm_daemon::job_control::{check_labels, check_priority};
use pointfarm_proto::v1 as pb;

use super::job_lines::{
    cut_summary, has_ended, lease_table, preview_summary, scheduling_lines, stage_statistics,
    worker_table,
};
use super::{every_page, runtime, ServerArgs, PAGE_SIZE};
use crate::admin_json::{json_line, JobDetails};
use crate::remote::{answer, state_name, status_error, Client};

#[derive(Subcommand)]
pub enum JobsCommand {
    /// The server's jobs, with their state, progress, priority and name, and the jobs each
    /// runs after.
    #[command(visible_alias = "ls")]
    List {
        /// Only jobs in this state: queued, running, paused, succeeded, failed, cancelled.
        #[arg(long)]
        state: Option<String>,
        /// Only jobs with this label (KEY=VALUE; repeatable, each must match).
        #[arg(long = "label", value_name = "KEY=VALUE", value_parser = parse_label)]
        labels: Vec<(String, String)>,
    },
    /// A job with per-stage timing statistics (median and p95) over its frames.
    Show {
        /// The job's id.
        id: String,
    },
    /// Cancel a queued, running or paused job; its workers drop their frames. A job that has
    /// ended is left as it is (exit status 0).
    Cancel {
        /// The job's id.
        id: String,
    },
    /// Queue the frames of a failed job that did not finish again, their attempts counted
    /// from zero: the job runs again.
    Retry {
        /// The job's id.
        id: String,
    },
    /// Lease no more frames of a queued or running job (frames being rendered finish) until
    /// it is resumed.
    Pause {
        /// The job's id.
        id: String,
    },
    /// Put a paused job back in the queue.
    Resume {
        /// The job's id.
        id: String,
    },
    /// Change the priority of a job that has not ended: its frames are leased before those
    /// of jobs of lower priority.
    Priority {
        /// The job's id.
        id: String,
        /// -100 to 100; higher runs first.
        #[arg(allow_negative_numbers = true, value_parser = parse_priority)]
        priority: i32,
    },
    /// Delete a job that has ended with its frames; jobs that run after it fail.
    Rm {
        /// The job's id.
        id: String,
        /// Cancel a job that has not ended, then delete it.
        #[arg(long)]
        force: bool,
    },
    /// Follow a job until it ends (with --json: each of its events on a line of its own).
    Watch {
        /// The job's id.
        id: String,
    },
    /// Download the video the server made of a job's frames (a job submitted with a video,
    /// e.g. `render --server URL --video spin.mp4`), once it has succeeded.
    Video {
        /// The job's id.
        id: String,
        /// The file to write, ending as the job's container does (.mp4, .webm, ...).
        #[arg(long, value_name = "FILE")]
        out: std::path::PathBuf,
        /// The preview video instead, made of a preview job's previews.
        #[arg(long)]
        preview: bool,
    },
    /// Frames being rendered now: which worker holds each, and until when.
    Leases,
    /// Workers connected now: their adapters, the largest image side each draws, their tags.
    Workers,
}

fn parse_state(state: &str) -> Result<pb::JobState> {
    Ok(match state.to_ascii_lowercase().as_str() {
        "queued" => pb::JobState::Queued,
        "running" => pb::JobState::Running,
        "paused" => pb::JobState::Paused,
        "succeeded" => pb::JobState::Succeeded,
        "failed" => pb::JobState::Failed,
        "cancelled" | "canceled" => pb::JobState::Cancelled,
        other => anyhow::bail!(
            "'{other}' is not a job state (queued, running, paused, succeeded, failed, \
             cancelled)"
        ),
    })
}

/// A label as `--label` gives it: `KEY=VALUE`, checked as the server checks it.
pub fn parse_label(value: &str) -> Result<(String, String), String> {
    let (key, value) = value
        .split_once('=')
        .ok_or_else(|| format!("{value:?} is not KEY=VALUE"))?;
    let label = BTreeMap::from([(key.to_string(), value.to_string())]);
    check_labels("label", &label).map_err(|e| e.to_string())?;
    Ok((key.to_string(), value.to_string()))
}

/// A job's priority, within the range the server accepts.
pub fn parse_priority(value: &str) -> Result<i32, String> {
    let priority: i32 = value
        .parse()
        .map_err(|_| format!("{value:?} is not a whole number"))?;
    check_priority("priority", priority).map_err(|e| e.to_string())?;
    Ok(priority)
}

pub fn jobs(server: &ServerArgs, command: JobsCommand) -> Result<()> {
    runtime()?.block_on(async {
        let mut client = Client::connect(&server.server, &server.credentials).await?;
        match command {
            JobsCommand::List { state, labels } => {
                let labels: HashMap<String, String> = labels.into_iter().collect();
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
                        labels: labels.clone(),
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
                        "{:<18} {:<10} {:>9} {:>8}  {:<24} dataset",
                        "id",
                        "state",
                        "frames",
                        "priority",
                        "name"
                    );
                    for j in &all {
                        let frames = format!("{}/{}", j.frames_done, j.frames_total);
                        let after = match j.after_job_ids.as_slice() {
                            [] => String::new(),
                            ids => format!("  after {}", ids.join(", ")),
                        };
                        outln!(
                            "{:<18} {:<10} {:>9} {:>8}  {:<24} {}{after}",
                            j.id,
                            state_name(j.state),
                            frames,
                            j.priority,
                            j.name,
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
                    if !job.name.is_empty() {
                        outln!("name: {}", job.name);
                    }
                    if !job.labels.is_empty() {
                        let mut labels: Vec<String> =
                            job.labels.iter().map(|(k, v)| format!("{k}={v}")).collect();
                        labels.sort();
                        outln!("labels: {}", labels.join(", "));
                    }
                    outln!("priority: {}", job.priority);
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
                // A job that has ended has nothing left to cancel: it is shown as it is, as a
                // cancel answers (without its frames). The server's cancel of a cancelled job
                // answers it unchanged, so the state is asked first to say which it was.
                let ended = |mut job: pb::Job| {
                    job.frames.clear();
                    (job, false)
                };
                let shown = answer(
                    client
                        .jobs
                        .get_job(pb::GetJobRequest { id: id.clone() })
                        .await,
                )?;
                let request = pb::CancelJobRequest { id: id.clone() };
                let (job, cancelled) = if has_ended(shown.state) {
                    ended(shown)
                } else {
                    match client.jobs.cancel_job(request).await {
                        Ok(reply) => (reply.into_inner(), true),
                        // It ended between the two calls.
                        Err(status) if status.code() == tonic::Code::FailedPrecondition => {
                            let job = answer(client.jobs.get_job(pb::GetJobRequest { id }).await)?;
                            if !has_ended(job.state) {
                                return Err(status_error(status));
                            }
                            ended(job)
                        }
                        Err(status) => return Err(status_error(status)),
                    }
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
            JobsCommand::Retry { id } => {
                let job = answer(client.jobs.retry_job(pb::RetryJobRequest { id }).await)?;
                print_changed(server, &job, "running again")?;
            }
            JobsCommand::Pause { id } => {
                let job = answer(client.jobs.pause_job(pb::PauseJobRequest { id }).await)?;
                print_changed(server, &job, "paused")?;
            }
            JobsCommand::Resume { id } => {
                let job = answer(client.jobs.resume_job(pb::ResumeJobRequest { id }).await)?;
                print_changed(server, &job, "resumed")?;
            }
            JobsCommand::Priority { id, priority } => {
                let request = pb::SetJobPriorityRequest { id, priority };
                let job = answer(client.jobs.set_job_priority(request).await)?;
                print_changed(server, &job, &format!("priority {}", job.priority))?;
            }
            JobsCommand::Rm { id, force } => {
                let request = pb::DeleteJobRequest { id, force };
                let job = answer(client.jobs.delete_job(request).await)?;
                print_changed(server, &job, "deleted")?;
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
            JobsCommand::Video { id, out, preview } => {
                crate::jobs_video::run(&mut client, &id, preview, &out, server.json).await?;
            }
            JobsCommand::Workers => {
                let workers =
                    answer(client.jobs.list_workers(pb::ListWorkersRequest {}).await)?.workers;
                let listed = pb::ListWorkersResponse { workers };
                print_listing(server, &listed, || worker_table(&listed.workers))?;
            }
            JobsCommand::Leases => {
                let leases =
                    answer(client.jobs.list_leases(pb::ListLeasesRequest {}).await)?.leases;
                let now = std::time::SystemTime::now()
                    .duration_since(std::time::UNIX_EPOCH)
                    .map(|d| d.as_millis() as i64)
                    .unwrap_or(0);
                let listed = pb::ListLeasesResponse { leases };
                print_listing(server, &listed, || lease_table(&listed.leases, now))?;
            }
        }
        Ok(())
    })
}

/// What a listing prints: the server's answer as one JSON object (with --json), or the lines
/// of its table.
fn print_listing<T: serde::Serialize>(
    server: &ServerArgs,
    listed: &T,
    table: impl FnOnce() -> Vec<String>,
) -> Result<()> {
    if server.json {
        outln!("{}", json_line(listed)?);
    } else {
        for line in table() {
            outln!("{line}");
        }
    }
    Ok(())
}

/// What a command that changed `job` prints: the job as the server answered (with --json),
/// or a line saying what became of it, with its state.
fn print_changed(server: &ServerArgs, job: &pb::Job, what: &str) -> Result<()> {
    if server.json {
        outln!("{}", json_line(job)?);
    } else {
        outln!("job {} {what} ({})", job.id, state_name(job.state));
    }
    Ok(())
}

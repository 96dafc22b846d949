//! `JobService`: submitting, reading, listing and watching jobs, controlling them (cancel,
//! retry, pause, resume, priority, delete: `job_control`), and streaming their finished
//! frames.

use std::collections::HashSet;
use std::sync::Arc;

use pointfarm_proto::v1 as pb;
use pointfarm_proto::v1::job_service_server::JobService;
use tokio::sync::broadcast::error::RecvError;
use tonic::{Request, Response, Status};

use super::conversions::{
    invalid, job_filter, job_with_frames_message, page_messages, workers_message,
};
use super::streaming::{chunks, send_each, spawn_stream, ResponseStream};
use super::Api;
use crate::model::{FrameReport, FrameState, Job, JobSpec};
use crate::service::Daemon;

#[tonic::async_trait]
impl JobService for Api {
    async fn submit_job(
        &self,
        request: Request<pb::SubmitJobRequest>,
    ) -> Result<Response<pb::Job>, Status> {
        let r = request.into_inner();
        let spec = JobSpec::try_from(&r)?;
        let job = self.run(move |daemon| daemon.submit_job(spec)).await?;
        let mut message = pb::Job::from(&job);
        message.spec = Some(r);
        Ok(Response::new(message))
    }

    async fn get_job(
        &self,
        request: Request<pb::GetJobRequest>,
    ) -> Result<Response<pb::Job>, Status> {
        let id = request.into_inner().id;
        let (job, frames) = self.run(move |daemon| daemon.job_with_frames(&id)).await?;
        let availability = self.daemon.job_availability(&job);
        Ok(Response::new(job_with_frames_message(
            &job,
            &frames,
            availability,
        )))
    }

    async fn list_jobs(
        &self,
        request: Request<pb::ListJobsRequest>,
    ) -> Result<Response<pb::ListJobsResponse>, Status> {
        let r = request.into_inner();
        let filter = job_filter(&r)?;
        let page = self
            .run(move |daemon| daemon.find_jobs(&filter, r.page_size, &r.page_token))
            .await?;
        let (jobs, next_page_token) = page_messages(page);
        Ok(Response::new(pb::ListJobsResponse {
            jobs,
            next_page_token,
        }))
    }

    async fn cancel_job(
        &self,
        request: Request<pb::CancelJobRequest>,
    ) -> Result<Response<pb::Job>, Status> {
        let id = request.into_inner().id;
        self.answer(move |daemon| daemon.cancel_job(&id)).await
    }

    async fn retry_job(
        &self,
        request: Request<pb::RetryJobRequest>,
    ) -> Result<Response<pb::Job>, Status> {
        let id = request.into_inner().id;
        self.answer(move |daemon| daemon.retry_job(&id)).await
    }

    async fn pause_job(
        &self,
        request: Request<pb::PauseJobRequest>,
    ) -> Result<Response<pb::Job>, Status> {
        let id = request.into_inner().id;
        self.answer(move |daemon| daemon.pause_job(&id)).await
    }

    async fn resume_job(
        &self,
        request: Request<pb::ResumeJobRequest>,
    ) -> Result<Response<pb::Job>, Status> {
        let id = request.into_inner().id;
        self.answer(move |daemon| daemon.resume_job(&id)).await
    }

    async fn set_job_priority(
        &self,
        request: Request<pb::SetJobPriorityRequest>,
    ) -> Result<Response<pb::Job>, Status> {
        let r = request.into_inner();
        self.answer(move |daemon| daemon.set_job_priority(&r.id, r.priority))
            .await
    }

    async fn delete_job(
        &self,
        request: Request<pb::DeleteJobRequest>,
    ) -> Result<Response<pb::Job>, Status> {
        let r = request.into_inner();
        self.answer(move |daemon| daemon.delete_job(&r.id, r.force))
            .await
    }

    type WatchJobStream = ResponseStream<pb::JobEvent>;

    async fn watch_job(
        &self,
        request: Request<pb::WatchJobRequest>,
    ) -> Result<Response<Self::WatchJobStream>, Status> {
        let id = request.into_inner().id;
        // Subscribe before reading the state, so no event falls between the two.
        let mut events = self.daemon.subscribe();
        let daemon = self.daemon.clone();
        let first = catch_up(daemon.clone(), id.clone(), HashSet::new()).await?;
        let stream = spawn_stream(64, move |sender| async move {
            // The first event carries the frames finished so far: a watcher that comes late
            // (or back) still learns of every frame, each once.
            let (mut reported, mut ended) = (first.reported, first.ended);
            if sender.send(Ok(first.event)).await.is_err() || ended {
                return;
            }
            while !ended {
                let event = match events.recv().await {
                    Ok(event) if event.job.id == id => {
                        ended = event.job.state.is_terminal();
                        let frame = event
                            .frame
                            .as_ref()
                            .filter(|frame| reported.insert(report_key(frame)))
                            .map(pb::FrameFinished::from);
                        Ok(pb::JobEvent {
                            job: Some(pb::Job::from(&event.job)),
                            frame,
                            stage: String::new(),
                        })
                    }
                    Ok(_) => continue,
                    // A reader too slow for the event channel is brought up to date from the
                    // state database: it misses no frame, whatever it skipped.
                    Err(RecvError::Lagged(missed)) => {
                        tracing::debug!(job = %id, missed, "a watcher fell behind; catching up");
                        match catch_up(daemon.clone(), id.clone(), reported).await {
                            Ok(caught_up) => {
                                (reported, ended) = (caught_up.reported, caught_up.ended);
                                Ok(caught_up.event)
                            }
                            Err(status) => {
                                let _ = sender.send(Err(status)).await;
                                return;
                            }
                        }
                    }
                    Err(RecvError::Closed) => return,
                };
                if sender.send(event).await.is_err() {
                    return;
                }
            }
        });
        Ok(Response::new(stream))
    }

    type FetchVideoStream = ResponseStream<pb::VideoChunk>;

    async fn fetch_video(
        &self,
        request: Request<pb::FetchVideoRequest>,
    ) -> Result<Response<Self::FetchVideoStream>, Status> {
        self.fetch_video_call(request).await
    }

    type FetchFramesStream = ResponseStream<pb::FrameChunk>;

    async fn fetch_frames(
        &self,
        request: Request<pb::FetchFramesRequest>,
    ) -> Result<Response<Self::FetchFramesStream>, Status> {
        let r = request.into_inner();
        let job = self.daemon.job(&r.job_id)?;
        // A pending frame's preview is its latest image until the final one.
        let stream = frames_from(&self.daemon, job, r.from_index, |daemon, job, index| {
            matches!(
                daemon.state.frame(&job.id, index),
                Ok(Some(FrameState::Done { .. }))
            ) || daemon.state.has_preview(&job.id, index).unwrap_or(false)
        })?;
        Ok(Response::new(stream))
    }

    async fn list_workers(
        &self,
        _request: Request<pb::ListWorkersRequest>,
    ) -> Result<Response<pb::ListWorkersResponse>, Status> {
        let connected = self
            .daemon
            .workers
            .connected(self.daemon.config.lease_timeout);
        Ok(Response::new(workers_message(&connected)))
    }

    async fn list_leases(
        &self,
        _request: Request<pb::ListLeasesRequest>,
    ) -> Result<Response<pb::ListLeasesResponse>, Status> {
        let leases = self.run(|daemon| daemon.leases()).await?;
        Ok(Response::new(pb::ListLeasesResponse {
            leases: leases.iter().map(pb::Lease::from).collect(),
        }))
    }
}

/// A watcher brought up to date: one event with the job as stored and every finished frame
/// it has not been sent yet.
struct CaughtUp {
    event: pb::JobEvent,
    reported: HashSet<(u32, Option<u32>)>,
    ended: bool,
}

/// Reads job `id` and its finished frames under the scheduling lock (as a crash would leave
/// them) and adds the frames not in `reported` to one event.
/// What a watcher is told once: a frame's preview of each version (a redraw is news), and
/// its final report.
fn report_key(frame: &FrameReport) -> (u32, Option<u32>) {
    (frame.index, frame.preview.map(|_| frame.preview_version))
}

async fn catch_up(
    daemon: Arc<Daemon>,
    id: String,
    mut reported: HashSet<(u32, Option<u32>)>,
) -> Result<CaughtUp, Status> {
    let (job, finished) = super::blocking_within(super::BLOCKING_CALL_BOUND, move || {
        daemon.job_with_frames(&id)
    })
    .await??;
    let mut snapshot = pb::Job::from(&job);
    snapshot.frames = finished
        .iter()
        .filter(|frame| reported.insert(report_key(frame)))
        .map(pb::FrameFinished::from)
        .collect();
    Ok(CaughtUp {
        event: pb::JobEvent {
            job: Some(snapshot),
            frame: None,
            stage: String::new(),
        },
        reported,
        ended: job.state.is_terminal(),
    })
}

/// Job `job`'s frames from `from` on, each PNG read from the daemon's disk and sent in chunks,
/// those `has_image` refuses skipped; a frame that cannot be read ends the stream with
/// INTERNAL. `from` past the job's frames is refused.
pub(super) fn frames_from(
    daemon: &Arc<Daemon>,
    job: Job,
    from: u32,
    has_image: impl Fn(&Daemon, &Job, u32) -> bool + Send + 'static,
) -> Result<ResponseStream<pb::FrameChunk>, Status> {
    if from > job.frames_total {
        return Err(invalid(
            "from_index",
            format!("job {} has {} frames", job.id, job.frames_total),
        )
        .into());
    }
    let daemon = daemon.clone();
    Ok(spawn_stream(4, move |sender| async move {
        for index in from..job.frames_total {
            if !has_image(&daemon, &job, index) {
                continue;
            }
            let read = tokio::fs::read(daemon.config.frame_path(&job.id, index));
            let bytes = match super::io_within(read).await {
                Ok(bytes) => bytes,
                Err(e) => {
                    let status = Status::internal(format!("frame {index}: {e}"));
                    let _ = sender.send(Err(status)).await;
                    return;
                }
            };
            let messages: Vec<_> = chunks(&bytes)
                .map(|(chunk, last)| pb::FrameChunk {
                    index,
                    png: chunk.to_vec(),
                    last,
                })
                .collect();
            if !send_each(&sender, messages).await {
                return;
            }
        }
    }))
}

//! The calls of a job's video: a worker's encode lease (leased by long poll, renewed, the
//! frames fetched under it, the video handed in as a size-bounded stream, the failure
//! reported, or the lease given back by a worker stopping) and a client's download of the stored video
//! or preview video. The scheduling and the storing are
//! the daemon's (`encodes`); these only check and convert.

use pointfarm_proto::v1 as pb;
use tokio::sync::broadcast::error::RecvError;
use tonic::{Request, Response, Status, Streaming};

use super::conversions::invalid;
use super::streaming::{first_part, read_chunk, spawn_stream, ResponseStream};
use super::Api;
use crate::limits::{check_id, check_length, failure_reason, MAX_WORKER_NAME_BYTES};

/// Most encoders a worker lists.
const MAX_ENCODERS: usize = 32;

impl Api {
    pub(super) async fn lease_encode_call(
        &self,
        r: pb::LeaseEncodeRequest,
        embedded: bool,
        peer: Option<std::net::SocketAddr>,
    ) -> Result<Response<pb::LeaseEncodeResponse>, Status> {
        let name = super::workers::worker_name(r.worker_name, peer)?;
        if r.encoders.len() > MAX_ENCODERS {
            return Err(invalid("encoders", format!("at most {MAX_ENCODERS}")).into());
        }
        for encoder in &r.encoders {
            check_length("encoders", encoder, MAX_WORKER_NAME_BYTES)?;
        }
        let deadline = super::workers::long_poll_deadline(r.wait_ms);
        let encoders = std::sync::Arc::new(r.encoders);
        // Subscribed before looking, so work that arrives in between is not missed: a job's
        // last frame is an event of the job, a lease given back a change of work.
        let mut work = self.daemon.work.subscribe();
        let mut events = self.daemon.subscribe();
        loop {
            work.borrow_and_update();
            if self.daemon.is_stopping() {
                return Ok(Response::new(pb::LeaseEncodeResponse { task: None }));
            }
            let (worker, encoders) = (name.clone(), encoders.clone());
            let leased = self
                .run(move |daemon| daemon.lease_encode(&worker, embedded, &encoders))
                .await?;
            if let Some(task) = leased {
                return Ok(Response::new(pb::LeaseEncodeResponse {
                    task: Some(pb::EncodeTask::from(&task)),
                }));
            }
            let woken = loop {
                tokio::select! {
                    changed = work.changed() => break changed.is_ok(),
                    event = events.recv() => match event {
                        Ok(event)
                            if !event.job.awaits_video()
                                && !event.job.may_make_preview_video() =>
                        {
                            continue
                        }
                        Err(RecvError::Closed) => break false,
                        // A lagged receiver may have missed the event that matters.
                        Ok(_) | Err(RecvError::Lagged(_)) => break true,
                    },
                    () = tokio::time::sleep_until(deadline) => break false,
                }
            };
            if !woken {
                return Ok(Response::new(pb::LeaseEncodeResponse { task: None }));
            }
        }
    }

    pub(super) async fn renew_encode_call(
        &self,
        r: pb::RenewEncodeRequest,
        embedded: bool,
    ) -> Result<Response<pb::HeartbeatResponse>, Status> {
        let lease_id = r.lease_id;
        check_id("lease_id", &lease_id)?;
        let answer = self
            .run(move |daemon| daemon.renew_encode(&lease_id, embedded))
            .await?;
        Ok(Response::new(pb::HeartbeatResponse::from(answer)))
    }

    pub(super) async fn fetch_encode_frames_call(
        &self,
        r: pb::FetchEncodeFramesRequest,
        embedded: bool,
    ) -> Result<Response<ResponseStream<pb::FrameChunk>>, Status> {
        check_id("lease_id", &r.lease_id)?;
        let lease_id = r.lease_id.clone();
        let job = self
            .run(move |daemon| daemon.encode_job(&lease_id, embedded))
            .await?;
        // Every frame of a job whose video is leased has its image: a final one, or for a
        // preview video, a preview or a final one.
        let stream = super::jobs::frames_from(&self.daemon, job, r.from_index, |_, _, _| true)?;
        Ok(Response::new(stream))
    }

    pub(super) async fn complete_encode_call(
        &self,
        mut stream: Streaming<pb::CompleteEncodeRequest>,
        embedded: bool,
    ) -> Result<Response<pb::CompleteEncodeResponse>, Status> {
        use pb::complete_encode_request::Part;
        let result = first_part(&mut stream, "result", |m| match m.part {
            Some(Part::Result(result)) => Some(result),
            _ => None,
        })
        .await?;
        check_id("result.lease_id", &result.lease_id)?;
        // A lost lease or a video too large is refused before its bytes are received.
        let (lease_id, size) = (result.lease_id.clone(), result.size_bytes);
        let mut upload = self
            .run(move |daemon| daemon.start_video_upload(&lease_id, embedded, size))
            .await?;
        while let Some(message) = stream.message().await? {
            let Some(Part::Data(chunk)) = message.part else {
                return Err(invalid("data", "only the first message may be the result").into());
            };
            upload = self
                .run(move |_| upload.write(&chunk).map(|()| upload))
                .await?;
        }
        self.done(move |daemon| daemon.finish_video_upload(upload).map(drop))
            .await
    }

    pub(super) async fn fail_encode_call(
        &self,
        r: pb::FailEncodeRequest,
        embedded: bool,
    ) -> Result<Response<pb::FailEncodeResponse>, Status> {
        check_id("lease_id", &r.lease_id)?;
        let reason = failure_reason(&r.reason);
        self.done(move |daemon| daemon.fail_encode(&r.lease_id, embedded, &reason))
            .await
    }

    pub(super) async fn release_encode_call(
        &self,
        r: pb::ReleaseEncodeRequest,
        embedded: bool,
    ) -> Result<Response<pb::ReleaseEncodeResponse>, Status> {
        check_id("lease_id", &r.lease_id)?;
        self.done(move |daemon| daemon.release_encode(&r.lease_id, embedded))
            .await
    }

    pub(super) async fn fetch_video_call(
        &self,
        request: Request<pb::FetchVideoRequest>,
    ) -> Result<Response<ResponseStream<pb::VideoChunk>>, Status> {
        let pb::FetchVideoRequest { job_id, preview } = request.into_inner();
        check_id("job_id", &job_id)?;
        let (path, size, container) = self
            .run(move |daemon| match preview {
                true => daemon.preview_video(&job_id),
                false => daemon.video(&job_id),
            })
            .await?;
        let mut file = super::io_within(tokio::fs::File::open(path))
            .await
            .map_err(|e| Status::internal(format!("opening the video: {e}")))?;
        let stream = spawn_stream(4, move |sender| async move {
            let mut first = true;
            loop {
                let data = match read_chunk(&mut file).await {
                    Ok(Some(data)) => data,
                    Ok(None) => return,
                    Err(e) => {
                        let status = Status::internal(format!("reading the video: {e}"));
                        let _ = sender.send(Err(status)).await;
                        return;
                    }
                };
                let chunk = pb::VideoChunk {
                    data,
                    size_bytes: if first { size } else { 0 },
                    container: if first {
                        container.extension().to_owned()
                    } else {
                        String::new()
                    },
                };
                first = false;
                if sender.send(Ok(chunk)).await.is_err() {
                    return;
                }
            }
        });
        Ok(Response::new(stream))
    }
}

//! `WorkerService`: the workers' side of frame leases — long-polled leasing, heartbeats,
//! handing in (a size-checked PNG stream), failing and releasing frames — and the download of
//! a task's dataset. Every call tells the daemon's `WorkerPresence` that a worker is there;
//! calls of the daemon's own embedded worker process carry [`EmbeddedWorkerCall`].

use std::net::SocketAddr;

use pointfarm_proto::v1 as pb;
use pointfarm_proto::v1::worker_service_server::WorkerService;
use tonic::{Request, Response, Status, Streaming};

use super::conversions::{
    failure_kind, frame_cut_of_message, frame_task_message, invalid, node_key,
    preview_completeness, preview_sample_header, stage_timings,
};
use super::lease_guard::LeaseGuard;
use super::streaming::{chunks, first_part, read_chunk, spawn_stream, stream_each, ResponseStream};
use super::Api;
use crate::capabilities::WorkerCapabilities;
use crate::error::DaemonError;
use crate::lease::FrameOutcome;
use crate::limits::{check_id, check_length, failure_reason, MAX_WORKER_NAME_BYTES};
use crate::stores::MAX_NODES_PER_REQUEST;
use pointfarm_render::lod::NodeKey;

/// Longest wait of a worker's long poll for a lease (`LeaseFrame`, `LeaseEncode`).
const MAX_LEASE_WAIT_MS: u32 = 30_000;

/// When a worker's long poll for a lease gives up: after the wait it asks for, at most
/// [`MAX_LEASE_WAIT_MS`].
pub(super) fn long_poll_deadline(wait_ms: u32) -> tokio::time::Instant {
    let wait = std::time::Duration::from_millis(u64::from(wait_ms.min(MAX_LEASE_WAIT_MS)));
    tokio::time::Instant::now() + wait
}

/// The name a worker leases under, shown in leases and logs: the one it gives, checked, or
/// its address when it gives none.
pub(super) fn worker_name(given: String, peer: Option<SocketAddr>) -> Result<String, Status> {
    check_length("worker_name", &given, MAX_WORKER_NAME_BYTES)?;
    if !given.is_empty() {
        return Ok(given);
    }
    Ok(peer.map_or_else(|| "unnamed".into(), |address| address.to_string()))
}

/// Marks a call of the daemon's embedded worker process (the authentication layer knows it by
/// its token): its leases are the embedded worker's.
#[derive(Debug, Clone, Copy)]
pub struct EmbeddedWorkerCall;

fn is_embedded<T>(request: &Request<T>) -> bool {
    request.extensions().get::<EmbeddedWorkerCall>().is_some()
}

/// Largest PNG accepted for a frame: the raw RGBA size and room for PNG's overhead.
fn max_png_bytes(width: u32, height: u32) -> u64 {
    width as u64 * height as u64 * 5 + (1 << 20)
}

impl Api {
    /// The message of a worker's call, which tells the daemon that a worker is there, and
    /// whether the call is the embedded worker's.
    fn heard<T>(&self, request: Request<T>) -> (T, bool) {
        let embedded = is_embedded(&request);
        self.daemon.workers.heard_from(embedded);
        (request.into_inner(), embedded)
    }

    /// A lease id as a worker sends it: refused when no lease of ours could have it, or when
    /// the other kind of worker holds it.
    async fn own_lease(
        &self,
        field: &'static str,
        lease_id: String,
        embedded: bool,
    ) -> Result<String, Status> {
        check_id(field, &lease_id)?;
        let id = lease_id.clone();
        self.run(move |daemon| daemon.check_lease_holder(&id, embedded))
            .await?;
        Ok(lease_id)
    }

    /// A worker's call about a lease it holds, by its top-level `lease_id` field: the message,
    /// and the lease id once [`Api::own_lease`] accepts it.
    async fn about_own_lease<T: Send>(
        &self,
        request: Request<T>,
        lease_id: fn(&T) -> &str,
    ) -> Result<(T, String), Status> {
        let (message, embedded) = self.heard(request);
        let id = lease_id(&message).to_owned();
        let id = self.own_lease("lease_id", id, embedded).await?;
        Ok((message, id))
    }
}

#[tonic::async_trait]
impl WorkerService for Api {
    async fn lease_frame(
        &self,
        request: Request<pb::LeaseFrameRequest>,
    ) -> Result<Response<pb::LeaseFrameResponse>, Status> {
        let peer = request.remote_addr();
        let embedded = is_embedded(&request);
        let r = request.into_inner();
        let name = worker_name(r.worker_name, peer)?;
        let capabilities = WorkerCapabilities::try_from(r.capabilities.as_ref())?;
        let _present = self.daemon.workers.poll_named(
            embedded,
            &name,
            capabilities.clone(),
            self.daemon.config.lease_timeout,
        );
        let capabilities = std::sync::Arc::new(capabilities);
        let deadline = long_poll_deadline(r.wait_ms);
        // Subscribed before looking, so work that arrives in between is not missed.
        let mut work = self.daemon.work.subscribe();
        loop {
            work.borrow_and_update();
            if self.daemon.is_stopping() {
                return Ok(Response::new(pb::LeaseFrameResponse { task: None }));
            }
            let guard = LeaseGuard::new(self.daemon.clone());
            let (worker, slot) = (name.clone(), guard.slot.clone());
            let capabilities = capabilities.clone();
            let leased = self
                .run(move |daemon| {
                    let task = daemon.lease_frame(&worker, embedded, &capabilities)?;
                    Ok(task.and_then(|task| slot.keep(daemon, task)))
                })
                .await?;
            if let Some(task) = leased {
                guard.disarm();
                return Ok(Response::new(pb::LeaseFrameResponse {
                    task: Some(frame_task_message(&task)),
                }));
            }
            match tokio::time::timeout_at(deadline, work.changed()).await {
                Ok(Ok(())) => {}
                Ok(Err(_)) | Err(_) => {
                    return Ok(Response::new(pb::LeaseFrameResponse { task: None }))
                }
            }
        }
    }

    async fn heartbeat(
        &self,
        request: Request<pb::HeartbeatRequest>,
    ) -> Result<Response<pb::HeartbeatResponse>, Status> {
        let (_, lease_id) = self.about_own_lease(request, |r| &r.lease_id).await?;
        let answer = self.run(move |daemon| daemon.heartbeat(&lease_id)).await?;
        Ok(Response::new(pb::HeartbeatResponse::from(answer)))
    }

    async fn complete_frame(
        &self,
        request: Request<Streaming<pb::CompleteFrameRequest>>,
    ) -> Result<Response<pb::CompleteFrameResponse>, Status> {
        use pb::complete_frame_request::Part;
        let (mut stream, embedded) = self.heard(request);
        let result = first_part(&mut stream, "result", |m| match m.part {
            Some(Part::Result(result)) => Some(result),
            _ => None,
        })
        .await?;
        // A stale lease is refused before the image is received.
        let lease_id = self
            .own_lease("result.lease_id", result.lease_id.clone(), embedded)
            .await?;
        let (_, width, height) = self.run(move |daemon| daemon.held_lease(&lease_id)).await?;
        let limit = max_png_bytes(width, height);
        if result.png_size_bytes > limit {
            return Err(DaemonError::ResourceExhausted(format!(
                "a {width}x{height} frame's PNG may have at most {limit} bytes, got {}",
                result.png_size_bytes
            ))
            .into());
        }
        let mut png = Vec::with_capacity(result.png_size_bytes as usize);
        while let Some(message) = stream.message().await? {
            let Some(Part::Png(chunk)) = message.part else {
                return Err(invalid("png", "only the first message may be the result").into());
            };
            if png.len() as u64 + chunk.len() as u64 > result.png_size_bytes {
                return Err(invalid(
                    "result.png_size_bytes",
                    format!("more than the declared {} bytes", result.png_size_bytes),
                )
                .into());
            }
            png.extend_from_slice(&chunk);
        }
        if png.len() as u64 != result.png_size_bytes {
            return Err(invalid(
                "result.png_size_bytes",
                format!(
                    "declared {} bytes, received {}",
                    result.png_size_bytes,
                    png.len()
                ),
            )
            .into());
        }
        let outcome = FrameOutcome {
            timings: stage_timings(&result.timings),
            dataset_cache_hit: result.dataset_cache_hit,
            cut: result.cut.as_ref().map(frame_cut_of_message),
            preview: preview_completeness(&result)?,
        };
        let lease_id = result.lease_id;
        self.done(move |daemon| daemon.complete_frame(&lease_id, &png, outcome).map(drop))
            .await
    }

    async fn fail_frame(
        &self,
        request: Request<pb::FailFrameRequest>,
    ) -> Result<Response<pb::FailFrameResponse>, Status> {
        let (r, lease_id) = self.about_own_lease(request, |r| &r.lease_id).await?;
        let reason = failure_reason(&r.reason);
        let kind = failure_kind(r.kind);
        self.done(move |daemon| daemon.fail_frame(&lease_id, &reason, kind))
            .await
    }

    async fn release_frame(
        &self,
        request: Request<pb::ReleaseFrameRequest>,
    ) -> Result<Response<pb::ReleaseFrameResponse>, Status> {
        let (_, lease_id) = self.about_own_lease(request, |r| &r.lease_id).await?;
        self.done(move |daemon| daemon.release_frame(&lease_id))
            .await
    }

    type FetchDatasetStream = ResponseStream<pb::DatasetChunk>;

    async fn fetch_dataset(
        &self,
        request: Request<pb::FetchDatasetRequest>,
    ) -> Result<Response<Self::FetchDatasetStream>, Status> {
        let r = request.into_inner();
        let dataset = self.daemon.dataset(&r.dataset_id)?;
        let files = dataset.files();
        let Some(wanted) = files.get(r.file_index as usize) else {
            return Err(invalid(
                "file_index",
                format!("dataset {} has {} files", dataset.id, files.len()),
            )
            .into());
        };
        // Named to the worker by the dataset's id and where the file lies under its data root
        // (an upload by its name); the log has its full path.
        let about = format!(
            "dataset {}, file {}",
            dataset.id,
            self.daemon.shown_path(&wanted.path)
        );
        let path = wanted.path.clone();
        let opened = self
            .run(move |daemon| Ok(daemon.open_dataset_file(&path)))
            .await?;
        let mut file = match opened {
            Ok(file) => tokio::fs::File::from_std(file),
            Err(error) => {
                tracing::warn!(path = %wanted.path.display(), %error, "a dataset's file cannot be served");
                return Err(Status::failed_precondition(format!("{about}: {error}")));
            }
        };
        let stream = spawn_stream(4, move |sender| async move {
            loop {
                let message = match super::io_within(read_chunk(&mut file)).await {
                    Ok(None) => return,
                    Ok(Some(data)) => Ok(pb::DatasetChunk { data }),
                    Err(e) => Err(Status::internal(format!("{about}: {e}"))),
                };
                let failed = message.is_err();
                if sender.send(message).await.is_err() || failed {
                    return;
                }
            }
        });
        Ok(Response::new(stream))
    }

    async fn open_dataset_store(
        &self,
        request: Request<pb::OpenDatasetStoreRequest>,
    ) -> Result<Response<pb::OpenDatasetStoreResponse>, Status> {
        let (r, _) = self.heard(request);
        self.answer(move |daemon| daemon.open_dataset_store(&r.dataset_id, r.levels_of_detail))
            .await
    }

    type FetchStoreHierarchyStream = ResponseStream<pb::StoreHierarchyChunk>;

    async fn fetch_store_hierarchy(
        &self,
        request: Request<pb::FetchStoreHierarchyRequest>,
    ) -> Result<Response<Self::FetchStoreHierarchyStream>, Status> {
        let (r, _) = self.heard(request);
        let store = self
            .run(move |daemon| daemon.ready_dataset_store(&r.dataset_id))
            .await?;
        let chunks = chunks(&store.hierarchy_record)
            .map(|(data, _)| pb::StoreHierarchyChunk {
                data: data.to_vec(),
            })
            .collect();
        Ok(Response::new(stream_each(chunks)))
    }

    type FetchPreviewSampleStream = ResponseStream<pb::PreviewSampleChunk>;

    async fn fetch_preview_sample(
        &self,
        request: Request<pb::FetchPreviewSampleRequest>,
    ) -> Result<Response<Self::FetchPreviewSampleStream>, Status> {
        let (r, _) = self.heard(request);
        let sample = self
            .run(move |daemon| daemon.preview_sample(&r.dataset_id))
            .await?;
        let mut header = Some(preview_sample_header(&sample));
        let mut messages: Vec<pb::PreviewSampleChunk> = chunks(&sample.cloud)
            .map(|(data, _)| pb::PreviewSampleChunk {
                header: header.take(),
                data: data.to_vec(),
            })
            .collect();
        if let Some(header) = header {
            // An empty sample: the header alone.
            messages.push(pb::PreviewSampleChunk {
                header: Some(header),
                data: Vec::new(),
            });
        }
        Ok(Response::new(stream_each(messages)))
    }

    type FetchNodesStream = ResponseStream<pb::NodeRecord>;

    async fn fetch_nodes(
        &self,
        request: Request<pb::FetchNodesRequest>,
    ) -> Result<Response<Self::FetchNodesStream>, Status> {
        let (r, _) = self.heard(request);
        if r.nodes.len() > MAX_NODES_PER_REQUEST {
            return Err(invalid(
                "nodes",
                format!(
                    "{} nodes asked for; at most {MAX_NODES_PER_REQUEST} a request",
                    r.nodes.len()
                ),
            )
            .into());
        }
        let keys: Vec<NodeKey> = r.nodes.iter().map(node_key).collect::<Result<_, _>>()?;
        // Checked as they are read: a store whose bytes fail their checks is built again.
        let records = self
            .run(move |daemon| {
                check_id("dataset_id", &r.dataset_id)?;
                let dataset = daemon.store_dataset(&r.dataset_id)?;
                daemon.stores.node_records(&dataset, &keys, r.coarse)
            })
            .await?;
        let records = records.into_iter().map(|data| pb::NodeRecord { data });
        Ok(Response::new(stream_each(records.collect())))
    }

    async fn lease_encode(
        &self,
        request: Request<pb::LeaseEncodeRequest>,
    ) -> Result<Response<pb::LeaseEncodeResponse>, Status> {
        let peer = request.remote_addr();
        let (r, embedded) = self.heard(request);
        self.lease_encode_call(r, embedded, peer).await
    }

    async fn renew_encode(
        &self,
        request: Request<pb::RenewEncodeRequest>,
    ) -> Result<Response<pb::HeartbeatResponse>, Status> {
        let (r, embedded) = self.heard(request);
        self.renew_encode_call(r, embedded).await
    }

    type FetchEncodeFramesStream = ResponseStream<pb::FrameChunk>;

    async fn fetch_encode_frames(
        &self,
        request: Request<pb::FetchEncodeFramesRequest>,
    ) -> Result<Response<Self::FetchEncodeFramesStream>, Status> {
        let (r, embedded) = self.heard(request);
        self.fetch_encode_frames_call(r, embedded).await
    }

    async fn complete_encode(
        &self,
        request: Request<Streaming<pb::CompleteEncodeRequest>>,
    ) -> Result<Response<pb::CompleteEncodeResponse>, Status> {
        let (stream, embedded) = self.heard(request);
        self.complete_encode_call(stream, embedded).await
    }

    async fn fail_encode(
        &self,
        request: Request<pb::FailEncodeRequest>,
    ) -> Result<Response<pb::FailEncodeResponse>, Status> {
        let (r, embedded) = self.heard(request);
        self.fail_encode_call(r, embedded).await
    }

    async fn release_encode(
        &self,
        request: Request<pb::ReleaseEncodeRequest>,
    ) -> Result<Response<pb::ReleaseEncodeResponse>, Status> {
        let (r, embedded) = self.heard(request);
        self.release_encode_call(r, embedded).await
    }
}

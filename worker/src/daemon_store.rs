//! The daemon's level-of-detail store of a dataset, read node by node over the worker
//! service: the worker asks for the store, fetches its hierarchy once, and then reads only
//! the nodes each frame's cut needs — checked against their own checksums as a local store's
//! are — instead of downloading the dataset's files and building a store of its own. The
//! daemon checks each record before it sends it, and builds a store that fails its checks
//! again itself (the daemon's `stores.rs`): a record failing here was damaged on the way, and
//! the frame fails and is tried again with the store opened anew. A dataset of one COPC file
//! comes the same way, its records the file's LAZ chunks, decoded here with what the daemon
//! sends of its header. While the daemon builds a store, a preview job's frames render from
//! the daemon's preview sample of the dataset (`fetch_preview`), fetched again when a task
//! asks for a later version of it than the one loaded.

use std::sync::Arc;
use std::time::Duration;

use pointfarm_daemon::grpc::{
    copc_chunks, node_key_message, preview_sample_bounds, store_elevation,
};
use pointfarm_daemon::lease::FrameTask;
use pointfarm_daemon::stores::{CopcServed, MAX_NODES_PER_REQUEST};
use pointfarm_proto::v1 as pb;
use pointfarm_render::cloud::{PointCloud, WorldBounds};
use pointfarm_render::color::Stretch;
use pointfarm_render::copc::CopcDecoder;
use pointfarm_render::lod::{
    LodError, LodHierarchy, NodeInfo, NodePoints, NodeRecords, RootCube, PREVIEW_STORED_POINTS,
};
use tonic::{Code, Status};

use crate::client::Client;

/// The longest a fetch of one request's nodes may take before the frame fails (and is tried
/// again): a daemon that stopped answering must not hold a frame for ever.
const FETCH_TIMEOUT: Duration = Duration::from_secs(120);

/// The most bytes of hierarchy a worker accepts; about 50 M nodes.
const MAX_HIERARCHY_BYTES: u64 = 2 << 30;

/// What the daemon says of a task's dataset.
pub enum DaemonStore {
    /// Rendered resident from the dataset's files, or a daemon that keeps no stores.
    NotNeeded,
    /// Being built: the frame goes back, and the worker asks again later.
    Building,
    Ready(Box<RemoteStore>),
}

/// A ready store of the daemon's, opened by this worker.
pub struct RemoteStore {
    pub hierarchy: LodHierarchy,
    pub bounds: WorldBounds,
    /// How long the daemon took to build it; 0 when it opened one built before.
    pub build_ms: f64,
    pub records: Arc<RemoteNodes>,
    /// Set when the dataset is one COPC file read through its own hierarchy.
    pub copc: Option<CopcServed>,
    /// The elevation range of the store's coarsest nodes as the daemon read them; absent
    /// when the daemon did not say, and the worker reads them itself.
    pub elevation: Option<Stretch>,
}

/// Asks the daemon for the store of `task`'s dataset, and fetches its hierarchy when it is
/// ready. A status error is the daemon's refusal (FAILED_PRECONDITION: it cannot be built).
pub async fn open(client: &mut Client, task: &FrameTask) -> Result<DaemonStore, Status> {
    use pb::open_dataset_store_response::State;
    let request = pb::OpenDatasetStoreRequest {
        dataset_id: task.dataset.id.clone(),
        // What the request asks; the daemon adds the dataset's facts and decides with
        // `frame_points`, as a local render does.
        levels_of_detail: task.request.render.lod_error.is_some(),
    };
    let answer = match client.open_dataset_store(request).await {
        Ok(answer) => answer.into_inner(),
        Err(status) if status.code() == Code::Unimplemented => return Ok(DaemonStore::NotNeeded),
        Err(status) => return Err(status),
    };
    match State::try_from(answer.state) {
        Ok(State::NotNeeded) => return Ok(DaemonStore::NotNeeded),
        Ok(State::Building) => return Ok(DaemonStore::Building),
        Ok(State::Ready) => {}
        _ => {
            return Err(Status::internal(
                "the daemon's store answer has no known state",
            ))
        }
    }
    let bounds = match (answer.bounds_min, answer.bounds_max) {
        (Some(min), Some(max)) => WorldBounds {
            min: glam::DVec3::new(min.x, min.y, min.z),
            max: glam::DVec3::new(max.x, max.y, max.z),
        },
        _ => return Err(Status::internal("the daemon's ready store has no bounds")),
    };
    if answer.hierarchy_bytes > MAX_HIERARCHY_BYTES {
        return Err(Status::internal(format!(
            "the daemon's store hierarchy of {} bytes is more than a worker takes",
            answer.hierarchy_bytes
        )));
    }
    let mut stream = client
        .fetch_store_hierarchy(pb::FetchStoreHierarchyRequest {
            dataset_id: task.dataset.id.clone(),
        })
        .await?
        .into_inner();
    let mut record = Vec::with_capacity(answer.hierarchy_bytes as usize);
    while let Some(chunk) = stream.message().await? {
        if (record.len() + chunk.data.len()) as u64 > answer.hierarchy_bytes {
            return Err(Status::internal(
                "the daemon sent more hierarchy than it announced",
            ));
        }
        record.extend_from_slice(&chunk.data);
    }
    let hierarchy = LodHierarchy::decode(&record)
        .map_err(|e| Status::internal(format!("the daemon's store: {e}")))?;
    let copc = answer
        .copc
        .as_ref()
        .map(copc_chunks)
        .transpose()
        .map_err(|e| Status::internal(format!("the daemon's COPC answer: {e}")))?;
    let elevation = store_elevation(&answer)
        .map_err(|e| Status::internal(format!("the daemon's store answer: {e}")))?;
    let hierarchy = match &copc {
        Some(copc) => hierarchy.with_root_spacing(copc.root_spacing),
        None => hierarchy,
    };
    if hierarchy.point_count != answer.point_count {
        return Err(Status::internal(format!(
            "the daemon's store holds {} points, its answer says {}",
            hierarchy.point_count, answer.point_count
        )));
    }
    Ok(DaemonStore::Ready(Box::new(RemoteStore {
        hierarchy,
        bounds,
        build_ms: answer.build_ms,
        records: Arc::new(RemoteNodes {
            client: client.clone(),
            dataset_id: task.dataset.id.clone(),
            runtime: tokio::runtime::Handle::current(),
            decoder: copc.as_ref().map(|copc| copc.decoder.clone()),
        }),
        copc,
        elevation,
    })))
}

/// The most bytes of preview sample a worker accepts: about 2 M chunk starts (a dataset of
/// 100 G points) and the most points of stored nodes a redraw carries.
const MAX_PREVIEW_BYTES: u64 =
    pointfarm_render::cache::encoded_cloud_bytes(2_000_000 + PREVIEW_STORED_POINTS);

/// A preview sample as the daemon sends it.
pub struct PreviewSample {
    pub cloud: PointCloud,
    pub points_in_files: u64,
    /// The files' header bounds.
    pub bounds: WorldBounds,
    /// The build's version when the daemon read it: the whole tenths of the points whose
    /// stored nodes it carries beyond the chunk starts.
    pub version: u32,
}

/// The daemon's preview sample of `task`'s dataset. A status error is the daemon's refusal
/// (FAILED_PRECONDITION naming the file whose chunks cannot be sampled).
pub async fn fetch_preview(client: &mut Client, task: &FrameTask) -> Result<PreviewSample, Status> {
    let request = pb::FetchPreviewSampleRequest {
        dataset_id: task.dataset.id.clone(),
    };
    let mut stream = client.fetch_preview_sample(request).await?.into_inner();
    let mut header = None;
    let mut bytes = Vec::new();
    while let Some(chunk) = stream.message().await? {
        if let Some(first) = chunk.header {
            if header.is_some() {
                return Err(Status::internal(
                    "the daemon's preview sample has two headers",
                ));
            }
            if first.sample_bytes > MAX_PREVIEW_BYTES {
                return Err(Status::internal(format!(
                    "the daemon's preview sample of {} bytes is more than a worker takes",
                    first.sample_bytes
                )));
            }
            bytes.reserve(first.sample_bytes as usize);
            header = Some(first);
        }
        let Some(announced) = &header else {
            return Err(Status::internal(
                "the daemon's preview sample has no header",
            ));
        };
        if (bytes.len() + chunk.data.len()) as u64 > announced.sample_bytes {
            return Err(Status::internal(
                "the daemon sent more preview sample than it announced",
            ));
        }
        bytes.extend_from_slice(&chunk.data);
    }
    let header = header.ok_or_else(|| Status::internal("the daemon sent no preview sample"))?;
    if bytes.len() as u64 != header.sample_bytes {
        return Err(Status::internal("the daemon's preview sample ended short"));
    }
    let bounds = preview_sample_bounds(&header)
        .map_err(|e| Status::internal(format!("the daemon's preview sample: {e}")))?;
    let cloud = pointfarm_render::cache::decode_cloud(&bytes)
        .map_err(|e| Status::internal(format!("the daemon's preview sample: {e}")))?;
    Ok(PreviewSample {
        cloud,
        points_in_files: header.points_in_files,
        bounds,
        version: header.version,
    })
}

/// Node records fetched from the daemon, a request per wave of nodes. Called from the
/// renderer's blocking threads (never an async one), it waits on the worker's runtime.
pub struct RemoteNodes {
    client: Client,
    dataset_id: String,
    runtime: tokio::runtime::Handle,
    /// How a COPC file's chunks decode; `None` for a store's records.
    decoder: Option<CopcDecoder>,
}

impl RemoteNodes {
    /// `nodes`' records, or only their coarse sections where `coarse`.
    async fn fetch(&self, nodes: &[NodeInfo], coarse: bool) -> Result<Vec<Vec<u8>>, Status> {
        let request = pb::FetchNodesRequest {
            dataset_id: self.dataset_id.clone(),
            nodes: nodes.iter().map(|n| node_key_message(n.key)).collect(),
            coarse,
        };
        let mut client = self.client.clone();
        let mut stream = client.fetch_nodes(request).await?.into_inner();
        let mut records = Vec::with_capacity(nodes.len());
        while let Some(record) = stream.message().await? {
            let Some(info) = nodes.get(records.len()) else {
                return Err(Status::internal(
                    "the daemon sent more nodes than asked for",
                ));
            };
            let expected = if coarse { info.head_len } else { info.byte_len };
            if record.data.len() != expected as usize {
                return Err(Status::internal(format!(
                    "node {} came with {} bytes, its hierarchy says {expected}",
                    info.key,
                    record.data.len(),
                )));
            }
            records.push(record.data);
        }
        Ok(records)
    }
}

impl RemoteNodes {
    /// `nodes`' records (or coarse sections), a request per wave of nodes.
    fn fetch_all(&self, nodes: &[NodeInfo], coarse: bool) -> Result<Vec<Vec<u8>>, LodError> {
        let mut records = Vec::with_capacity(nodes.len());
        for wave in nodes.chunks(MAX_NODES_PER_REQUEST) {
            // The timeout is made inside the runtime: a thread of the renderer's own (the
            // read-ahead) is outside any.
            let fetched = self.runtime.block_on(async {
                tokio::time::timeout(FETCH_TIMEOUT, self.fetch(wave, coarse)).await
            });
            match fetched {
                Ok(Ok(mut fetched)) if fetched.len() == wave.len() => records.append(&mut fetched),
                Ok(Ok(fetched)) => {
                    return Err(LodError::Records(format!(
                        "the daemon sent {} of {} nodes",
                        fetched.len(),
                        wave.len()
                    )))
                }
                Ok(Err(status)) => {
                    return Err(LodError::Records(format!(
                        "fetching nodes from the daemon: {}: {}",
                        pointfarm_proto::code_words(status.code()),
                        status.message()
                    )))
                }
                Err(_) => {
                    return Err(LodError::Records(format!(
                        "the daemon sent no nodes within {} s",
                        FETCH_TIMEOUT.as_secs()
                    )))
                }
            }
        }
        Ok(records)
    }
}

impl NodeRecords for RemoteNodes {
    fn read_records(&self, nodes: &[NodeInfo]) -> Result<Vec<Vec<u8>>, LodError> {
        self.fetch_all(nodes, false)
    }

    /// A store's coarse sections, sent alone; a COPC file's chunks have none.
    fn read_coarse_records(&self, nodes: &[NodeInfo]) -> Option<Result<Vec<Vec<u8>>, LodError>> {
        match self.decoder {
            Some(_) => None,
            None => Some(self.fetch_all(nodes, true)),
        }
    }

    fn decode(
        &self,
        cube: &RootCube,
        info: &NodeInfo,
        bytes: &[u8],
    ) -> Result<NodePoints, LodError> {
        match &self.decoder {
            Some(decoder) => decoder
                .decode_chunk(cube, info, bytes)
                .map_err(LodError::from),
            None => {
                pointfarm_render::lod::codec::decode_node(cube, info.key, info.point_count, bytes)
            }
        }
    }
}

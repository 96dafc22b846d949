//! A level-of-detail store published to object storage (`lod::published`), opened by URL: its
//! hierarchy object read once, then only the node records each cut needs, by range (near ones
//! coalesced, the requests in parallel, as every object is read), through the caller's range
//! cache, each record checked when decoded as a store's own are. Both objects are pinned to
//! the versions they were published at: an object replaced since is refused, never read as
//! the store.

use std::sync::Arc;

use crate::copc::{CopcBytes, CopcError, RangeCache};
use crate::lod::published::{
    PublishedHierarchy, HIERARCHY_OBJECT, MAX_HIERARCHY_OBJECT_BYTES, PAYLOAD_OBJECT,
};
use crate::lod::{LodDataset, LodError, NodeInfo, NodeRecords};
use crate::remote::{ObjectUrl, RemoteClient, RemoteError, RemoteObject};

/// Where a published store lies and the versions its objects were published at.
#[derive(Debug, Clone, Copy)]
pub struct PublishedObjects<'a> {
    /// The store's prefix, `STORE_URL/SHA256/`.
    pub prefix: &'a ObjectUrl,
    pub hierarchy_version: &'a str,
    pub payload_version: &'a str,
}

/// Why a published store could not be opened.
#[derive(Debug, thiserror::Error)]
pub enum PublishedStoreError {
    #[error(transparent)]
    Remote(#[from] RemoteError),
    /// An object is not the one published, or says what no store is.
    #[error("{url}: {reason}")]
    Refused { url: String, reason: String },
    #[error("{url}: {source}")]
    Damaged { url: String, source: LodError },
}

/// Opens the published store at `objects` for cuts, its ranges kept in `cache` when given.
pub fn open_published_store(
    client: &RemoteClient,
    objects: PublishedObjects<'_>,
    cache: Option<Arc<dyn RangeCache>>,
) -> Result<LodDataset, PublishedStoreError> {
    let hierarchy_url = objects.prefix.join(HIERARCHY_OBJECT)?;
    let hierarchy_object = open_at(client, &hierarchy_url, objects.hierarchy_version)?;
    let refused = |url: &ObjectUrl, reason: String| PublishedStoreError::Refused {
        url: url.to_string(),
        reason,
    };
    if hierarchy_object.size() > MAX_HIERARCHY_OBJECT_BYTES {
        return Err(refused(
            &hierarchy_url,
            format!(
                "{} bytes of hierarchy is more than a worker takes",
                hierarchy_object.size()
            ),
        ));
    }
    let size = hierarchy_object.size();
    let bytes = cached(hierarchy_object, cache.clone())
        .read_at(0, size)
        .map_err(|e| copc_error(&hierarchy_url, e))?;
    let damaged = |url: &ObjectUrl, source: LodError| PublishedStoreError::Damaged {
        url: url.to_string(),
        source,
    };
    let published = PublishedHierarchy::decode(&bytes).map_err(|e| damaged(&hierarchy_url, e))?;
    let hierarchy = published
        .hierarchy()
        .map_err(|e| damaged(&hierarchy_url, e))?;
    let payload_url = objects.prefix.join(PAYLOAD_OBJECT)?;
    if published.payload_version != objects.payload_version {
        return Err(refused(
            &payload_url,
            format!(
                "the hierarchy was published with payload version {}, the store names {}",
                published.payload_version, objects.payload_version
            ),
        ));
    }
    let payload = open_at(client, &payload_url, objects.payload_version)?;
    if payload.size() != published.payload_bytes {
        return Err(refused(
            &payload_url,
            format!(
                "{} bytes, the hierarchy says {}",
                payload.size(),
                published.payload_bytes
            ),
        ));
    }
    let records = Arc::new(PublishedNodes {
        payload: cached(payload, cache),
    });
    LodDataset::with_records(records, hierarchy, published.bounds)
        .map_err(|e| damaged(&payload_url, e))
}

/// The object at `url`, refused unless it is still at `version`.
fn open_at(
    client: &RemoteClient,
    url: &ObjectUrl,
    version: &str,
) -> Result<RemoteObject, PublishedStoreError> {
    let object = client.open(url)?;
    let now = object.version().unwrap_or_default();
    if now != version {
        return Err(PublishedStoreError::Refused {
            url: url.to_string(),
            reason: format!(
                "the object changed since it was published (version {version}, now {now})"
            ),
        });
    }
    Ok(object)
}

fn cached(object: RemoteObject, cache: Option<Arc<dyn RangeCache>>) -> CopcBytes {
    let bytes = CopcBytes::remote(object);
    match cache {
        Some(cache) => bytes.with_cache(cache),
        None => bytes,
    }
}

fn copc_error(url: &ObjectUrl, error: CopcError) -> PublishedStoreError {
    match error {
        CopcError::Remote(remote) => PublishedStoreError::Remote(remote),
        other => PublishedStoreError::Refused {
            url: url.to_string(),
            reason: other.to_string(),
        },
    }
}

/// A published store's node records, read by range from its payload object.
struct PublishedNodes {
    payload: CopcBytes,
}

impl PublishedNodes {
    /// The first `len(node)` bytes of each of `nodes`' records, their pieces read together.
    fn read_parts(
        &self,
        nodes: &[NodeInfo],
        len: impl Fn(&NodeInfo) -> u32,
    ) -> Result<Vec<Vec<u8>>, LodError> {
        let pieces: Vec<Vec<std::ops::Range<u64>>> =
            nodes.iter().map(|n| n.pieces(len(n)).collect()).collect();
        let ranges: Vec<std::ops::Range<u64>> = pieces.iter().flatten().cloned().collect();
        let read = self
            .payload
            .read_many(&ranges)
            .map_err(|e| LodError::Records(format!("reading the published payload: {e}")))?;
        let mut read = read.into_iter();
        Ok(pieces
            .iter()
            .map(|node_pieces| {
                let mut record = Vec::new();
                for bytes in read.by_ref().take(node_pieces.len()) {
                    if record.is_empty() {
                        record = bytes;
                    } else {
                        record.extend_from_slice(&bytes);
                    }
                }
                record
            })
            .collect())
    }
}

impl NodeRecords for PublishedNodes {
    fn read_records(&self, nodes: &[NodeInfo]) -> Result<Vec<Vec<u8>>, LodError> {
        self.read_parts(nodes, |n| n.byte_len)
    }

    /// The records' coarse sections: their heads, stored apart from the rest.
    fn read_coarse_records(&self, nodes: &[NodeInfo]) -> Option<Result<Vec<Vec<u8>>, LodError>> {
        Some(self.read_parts(nodes, |n| n.head_len))
    }
}

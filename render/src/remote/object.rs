//! `RemoteObject`: one object opened by URL, read by ranges that all come from the version
//! seen when it was opened.

use std::ops::Range;
use std::sync::Arc;

use futures_util::{StreamExt, TryStreamExt};
use object_store::path::Path as ObjectPath;
use object_store::{GetOptions, GetRange, ObjectMeta, ObjectStore, ObjectStoreExt};

use super::client::RemoteClient;
use super::coalesce::{coalesce, locate};
use super::counters::FetchCounters;
use super::error::{causes, RemoteError};
use super::settings::RemoteSettings;
use super::url::ObjectUrl;

/// An object whose size and version were read by a HEAD request; every range read of it asks
/// the server for that version (`If-Match` on its ETag, or its version id), so an object
/// replaced meanwhile is `ObjectChanged`, never bytes of two versions.
#[derive(Clone)]
pub struct RemoteObject {
    client: RemoteClient,
    store: Arc<dyn ObjectStore>,
    url: ObjectUrl,
    pin: Pin,
}

/// What identifies the opened version of an object.
#[derive(Clone, Debug)]
struct Pin {
    path: ObjectPath,
    meta: ObjectMeta,
}

impl RemoteClient {
    /// Opens one object: a HEAD request for its size and version, which every later read
    /// of it is pinned to.
    pub fn open(&self, url: &ObjectUrl) -> Result<RemoteObject, RemoteError> {
        RemoteObject::open(self.clone(), url)
    }
}

impl RemoteObject {
    fn open(client: RemoteClient, url: &ObjectUrl) -> Result<Self, RemoteError> {
        if url.is_prefix() {
            return Err(RemoteError::InvalidUrl {
                url: url.to_string(),
                reason: "names a prefix, not an object".to_owned(),
            });
        }
        let store = client.store(url)?;
        let path = url.object_path();
        let counters = client.counters();
        let head_store = Arc::clone(&store);
        let head_path = path.clone();
        let shown = url.to_string();
        let meta = client.run(url, async move {
            counters.add(1, 0);
            head_store
                .head(&head_path)
                .await
                .map_err(|error| RemoteError::from_store(&shown, error))
        })?;
        Ok(Self {
            client,
            store,
            url: url.clone(),
            pin: Pin { path, meta },
        })
    }

    pub fn url(&self) -> &ObjectUrl {
        &self.url
    }

    /// The settings of the client that opened it, which bound its reads.
    pub fn settings(&self) -> &RemoteSettings {
        self.client.settings()
    }

    /// The object's size in bytes, as the server reported it at open.
    pub fn size(&self) -> u64 {
        self.pin.meta.size
    }

    /// The version every read is pinned to: the store's version id, else the ETag.
    pub fn version(&self) -> Option<&str> {
        self.pin
            .meta
            .version
            .as_deref()
            .or(self.pin.meta.e_tag.as_deref())
    }

    /// One byte range of the object.
    pub fn read_range(&self, range: Range<u64>) -> Result<Vec<u8>, RemoteError> {
        let mut parts = self.read_ranges(std::slice::from_ref(&range))?;
        Ok(parts.pop().unwrap_or_default())
    }

    /// Several byte ranges, in the order asked; ranges closer than the settings'
    /// `coalesce_gap` are fetched as one request, and the requests run in parallel.
    pub fn read_ranges(&self, ranges: &[Range<u64>]) -> Result<Vec<Vec<u8>>, RemoteError> {
        self.read_ranges_within(ranges, self.client.settings().coalesce_gap)
    }

    /// Small ranges scattered over the object, as [`Self::read_ranges`] reads them but merged
    /// only when closer than the settings' `sparse_gap`, so that what is fetched stays near
    /// what was asked.
    pub fn read_sparse(&self, ranges: &[Range<u64>]) -> Result<Vec<Vec<u8>>, RemoteError> {
        self.read_ranges_within(ranges, self.client.settings().sparse_gap)
    }

    fn read_ranges_within(
        &self,
        ranges: &[Range<u64>],
        gap: u64,
    ) -> Result<Vec<Vec<u8>>, RemoteError> {
        let settings = self.client.settings();
        let mut total: u64 = 0;
        for range in ranges {
            if range.start > range.end || range.end > self.size() {
                return Err(RemoteError::RangeOutOfBounds {
                    url: self.url.to_string(),
                    range: range.clone(),
                    size: self.size(),
                });
            }
            total = total.saturating_add(range.end - range.start);
        }
        if total > settings.max_read_bytes {
            return Err(RemoteError::ReadTooLarge {
                url: self.url.to_string(),
                requested: total,
                limit: settings.max_read_bytes,
            });
        }
        let merged = coalesce(ranges, gap, settings.max_coalesced_bytes);
        let store = Arc::clone(&self.store);
        let pin = self.pin.clone();
        let counters = self.client.counters();
        let shown = self.url.to_string();
        let parallel = settings.parallel_requests.max(1);
        let requests = merged.clone();
        let fetched: Vec<Vec<u8>> = self.client.run(&self.url, async move {
            futures_util::stream::iter(requests)
                .map(|range| fetch(&store, &pin, &counters, &shown, range))
                .buffered(parallel)
                .try_collect()
                .await
        })?;
        ranges
            .iter()
            .map(|range| {
                if range.start == range.end {
                    return Ok(Vec::new());
                }
                let (index, within) =
                    locate(&merged, range).ok_or_else(|| RemoteError::Runtime {
                        message: format!("bytes {}..{} were not fetched", range.start, range.end),
                    })?;
                Ok(fetched[index][within].to_vec())
            })
            .collect()
    }
}

impl std::fmt::Debug for RemoteObject {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RemoteObject")
            .field("url", &self.url)
            .field("size", &self.size())
            .field("version", &self.version())
            .finish_non_exhaustive()
    }
}

/// One GET of a range of the pinned version, checked against what was asked.
async fn fetch(
    store: &Arc<dyn ObjectStore>,
    pin: &Pin,
    counters: &FetchCounters,
    url: &str,
    range: Range<u64>,
) -> Result<Vec<u8>, RemoteError> {
    let expected = range.end - range.start;
    let changed = || RemoteError::ObjectChanged {
        url: url.to_owned(),
        version: pinned_version(&pin.meta),
    };
    let version = pin.meta.version.clone();
    // A weak ETag never matches `If-Match`, which compares strongly; the time and size pin it instead.
    let if_match = pin.meta.e_tag.clone().filter(|tag| !tag.starts_with("W/"));
    let if_unmodified_since =
        (if_match.is_none() && version.is_none()).then_some(pin.meta.last_modified);
    let options = GetOptions {
        range: Some(GetRange::Bounded(range.clone())),
        version,
        if_match,
        if_unmodified_since,
        ..GetOptions::default()
    };
    counters.add(1, 0);
    let answer = store
        .get_opts(&pin.path, options)
        .await
        .map_err(|error| match error {
            object_store::Error::Precondition { .. } => changed(),
            // A GET of the version seen at open finds none where that version was replaced
            // or deleted since (GCS's generations, S3's version ids).
            object_store::Error::NotFound { .. } if pin.meta.version.is_some() => changed(),
            // object_store refuses a `200` to a ranged GET at its headers and drops the body
            // unread, so a server ignoring ranges costs one answer's headers, never the object.
            other if is_range_ignored(&other) => RemoteError::RangeIgnored {
                url: url.to_owned(),
                range: range.clone(),
            },
            other => RemoteError::from_store(url, other),
        })?;
    // A server that ignores the conditions still tells what it sent.
    let same_tag = match (&pin.meta.e_tag, &answer.meta.e_tag) {
        (Some(opened), Some(now)) => opened == now,
        _ => true,
    };
    if !same_tag || answer.meta.size != pin.meta.size {
        return Err(changed());
    }
    if answer.range != range {
        return Err(RemoteError::ShortRead {
            url: url.to_owned(),
            range,
            got: answer.range.end.saturating_sub(answer.range.start),
        });
    }
    let bytes = answer
        .bytes()
        .await
        .map_err(|error| RemoteError::from_store(url, error))?;
    counters.add(0, bytes.len() as u64);
    if bytes.len() as u64 != expected {
        return Err(RemoteError::ShortRead {
            url: url.to_owned(),
            range,
            got: bytes.len() as u64,
        });
    }
    Ok(bytes.to_vec())
}

/// Whether object_store refused an answer to a ranged GET for not being partial content: an
/// HTTP store says the range is not supported, the others that the answer is not partial (its
/// error types are private; their messages are the one way to tell).
fn is_range_ignored(error: &object_store::Error) -> bool {
    causes(error).any(|cause| {
        let text = cause.to_string();
        text.starts_with("Range request not supported by ")
            || text == "Received non-partial response when range requested"
    })
}

fn pinned_version(meta: &ObjectMeta) -> String {
    meta.version
        .clone()
        .or_else(|| meta.e_tag.clone())
        .unwrap_or_else(|| meta.last_modified.to_rfc3339())
}

//! Publishing the daemon's level-of-detail stores to object storage (`serve --store-url`), so
//! that workers read their nodes from there rather than through the daemon, whose disk and
//! network would otherwise bound the farm.
//!
//! A store is published once it is ready here, off the scheduler's path on a thread of its
//! own, one store at a time: its payload by multipart upload (a grown store's layers and its
//! own file streamed as the one object they make together, so the published format is one),
//! then its hierarchy object
//! (`lod::published`), last, so a store whose upload stopped part way is never read. The
//! objects' versions (ETags) are then recorded in a sled database of their own
//! (`DATA/published-stores`), which leases read to name the store to workers; a restarted
//! daemon finds the record and publishes nothing again. A failed upload is logged (the error
//! names the URL, never a credential) and tried again with backoff, as many tries as the
//! operator allows (`serve --store-publish-attempts`); meanwhile, and after the last try,
//! workers read the store through the daemon. A store whose tries all failed is kept aside and
//! offered again when a frame of it is next leased, so a farm whose object storage comes back
//! publishes it on its next job without a restart. A store whose last dataset is deleted is taken down again on the
//! same thread (`unpublish`). Where each store stands, the last failure's error included, is
//! read from these records (`state`).

use std::collections::{HashMap, HashSet, VecDeque};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Condvar, Mutex};
use std::time::Duration;

use pointfarm_render::lod::layers::PayloadReader;
use pointfarm_render::lod::published::{PublishedHierarchy, HIERARCHY_OBJECT, PAYLOAD_OBJECT};
use pointfarm_render::remote::{ObjectUrl, RemoteClient, RemoteError, RemoteSettings};

use super::{DatasetStores, ReadyStore};
use crate::error::DaemonError;
use crate::model::PublishedStore;

/// Tries at publishing a store (or taking one down) before it is given up until a frame of it
/// is next leased (`serve --store-publish-attempts`): 8 tries wait about two minutes in all.
pub const DEFAULT_PUBLISH_ATTEMPTS: u32 = 8;
/// The most tries an operator may set: with the backoff capped at a minute, about an hour and
/// a half of waiting.
pub const MAX_PUBLISH_ATTEMPTS: u32 = 100;
/// The wait after the first failed try, doubled after each, up to [`MAX_BACKOFF`].
const FIRST_BACKOFF: Duration = Duration::from_secs(1);
const MAX_BACKOFF: Duration = Duration::from_secs(60);
/// sled's page cache for the records: one small record per store.
const RECORDS_CACHE_BYTES: u64 = 4 << 20;

/// `serve --store-url`: an `s3://` prefix (a `/` is added where it has none), checked before
/// the daemon starts.
pub fn store_url(text: &str) -> Result<ObjectUrl, DaemonError> {
    let prefix = match text.ends_with('/') {
        true => text.to_owned(),
        false => format!("{text}/"),
    };
    let url =
        ObjectUrl::parse(&prefix).map_err(|e| DaemonError::invalid("store URL", e.to_string()))?;
    if url.is_object_storage() {
        return Ok(url);
    }
    Err(DaemonError::invalid(
        "store URL",
        format!("{url}: stores are published to object storage (s3://, gs:// or az://bucket/prefix) only"),
    ))
}

/// Publishes ready stores under one store URL and remembers which are published.
pub struct StorePublisher {
    shared: Arc<Shared>,
}

struct Shared {
    store_url: ObjectUrl,
    client: RemoteClient,
    /// Tries at one publish or takedown, 1 to [`MAX_PUBLISH_ATTEMPTS`].
    attempts: u32,
    /// Published stores by content: their [`PublishedStore`] as JSON.
    records: sled::Db,
    queue: Mutex<Queue>,
    wake: Condvar,
}

#[derive(Default)]
struct Queue {
    waiting: VecDeque<(String, Arc<ReadyStore>)>,
    /// Contents waiting or being published now, offered once.
    offered: HashSet<String>,
    /// Contents no dataset has any more: their objects are deleted before any store is
    /// published, and a publish of one under way stops at its next try.
    unpublishing: VecDeque<String>,
    /// Contents deleted while their store was building: the offer that build ends with is
    /// dropped, once.
    unwanted: HashSet<String>,
    /// Stores whose every try failed, offered again when a frame of them is next leased.
    given_up: HashMap<String, Arc<ReadyStore>>,
    closed: bool,
}

/// What the publishing thread does next.
enum Work {
    Publish(String, Arc<ReadyStore>),
    Unpublish(String),
}

impl StorePublisher {
    /// Publishes under `store_url` (an `s3://` prefix), with `settings`' timeouts and part
    /// sizes, `attempts` tries at each store (at least one), recording what it published in
    /// the database at `records`.
    pub fn start(
        store_url: ObjectUrl,
        settings: RemoteSettings,
        attempts: u32,
        records: &Path,
    ) -> Result<Self, DaemonError> {
        let config = sled::Config::new()
            .path(records)
            .cache_capacity(RECORDS_CACHE_BYTES);
        // A publisher restarted in this process may find the last one's lock not yet let go.
        let records = pointfarm_render::sled_open::open_waiting(&config)
            .map_err(|e| DaemonError::Internal(format!("opening {}: {e}", records.display())))?;
        let shared = Arc::new(Shared {
            client: RemoteClient::new(settings)?,
            attempts: attempts.clamp(1, MAX_PUBLISH_ATTEMPTS),
            store_url,
            records,
            queue: Mutex::default(),
            wake: Condvar::new(),
        });
        let publishing = Arc::clone(&shared);
        std::thread::Builder::new()
            .name("pointfarm-store-publish".into())
            .spawn(move || publishing.run())
            .map_err(|e| DaemonError::Internal(format!("starting the store publisher: {e}")))?;
        tracing::info!(store_url = %shared.store_url, "stores are published for workers to read");
        Ok(Self { shared })
    }

    /// Where the store of content `sha256` lies and its objects' versions, once published
    /// under this daemon's store URL. Asked as a frame of it is leased: a store whose tries
    /// all failed is then offered again.
    pub fn published(&self, sha256: &str) -> Option<PublishedStore> {
        let published = self.shared.published(sha256);
        if published.is_none() {
            let given_up = self.shared.lock().given_up.remove(sha256);
            if let Some(store) = given_up {
                tracing::info!(
                    sha256,
                    "publishing a store again that every try failed to publish"
                );
                self.offer(sha256, &store);
            }
        }
        published
    }

    /// Publishes `store`, of content `sha256`, unless it is published or on its way.
    pub fn offer(&self, sha256: &str, store: &Arc<ReadyStore>) {
        if store.payload_path().is_none() || self.published(sha256).is_some() {
            return;
        }
        let mut queue = self.shared.lock();
        if queue.closed || queue.unwanted.remove(sha256) || !queue.offered.insert(sha256.to_owned())
        {
            return;
        }
        queue
            .waiting
            .push_back((sha256.to_owned(), Arc::clone(store)));
        self.shared.wake.notify_all();
    }
}

impl Drop for StorePublisher {
    /// The publishing thread ends after the store it is publishing, if any.
    fn drop(&mut self) {
        self.shared.lock().closed = true;
        self.shared.wake.notify_all();
    }
}

impl Shared {
    fn lock(&self) -> std::sync::MutexGuard<'_, Queue> {
        self.queue.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// The store's prefix under the store URL.
    fn prefix(&self, sha256: &str) -> Result<ObjectUrl, RemoteError> {
        self.store_url.join(&format!("{sha256}/"))
    }

    fn published(&self, sha256: &str) -> Option<PublishedStore> {
        let published = self.record(sha256)?;
        // A store published under another store URL is published again under this one.
        let here = self.prefix(sha256).ok()?;
        (published.url == here.as_str()).then_some(published)
    }

    /// The record of the store of content `sha256`, under whichever store URL it names.
    fn record(&self, sha256: &str) -> Option<PublishedStore> {
        let record = match self.records.get(sha256.as_bytes()) {
            Ok(record) => record?,
            Err(error) => {
                tracing::warn!(%error, "reading the published stores' records");
                return None;
            }
        };
        let published: PublishedStore = match serde_json::from_slice(&record) {
            Ok(published) => published,
            Err(error) => {
                tracing::warn!(%error, sha256, "an unreadable published store's record");
                return None;
            }
        };
        Some(published)
    }

    /// Publishes the stores offered and takes down those unpublished, one at a time, until
    /// the publisher is dropped.
    fn run(&self) {
        loop {
            let work = {
                let mut queue = self.lock();
                loop {
                    if queue.closed {
                        return;
                    }
                    if let Some(sha256) = queue.unpublishing.front() {
                        break Work::Unpublish(sha256.clone());
                    }
                    if let Some((sha256, store)) = queue.waiting.pop_front() {
                        break Work::Publish(sha256, store);
                    }
                    queue = self.wake.wait(queue).unwrap_or_else(|e| e.into_inner());
                }
            };
            match work {
                Work::Publish(sha256, store) => {
                    self.publish_with_retries(&sha256, &store);
                    self.lock().offered.remove(&sha256);
                }
                Work::Unpublish(sha256) => {
                    self.unpublish_with_retries(&sha256);
                    let mut queue = self.lock();
                    queue.unpublishing.retain(|waiting| *waiting != sha256);
                }
            }
        }
    }

    /// Publishes `store`; workers read it through the daemon until it is published.
    fn publish_with_retries(&self, sha256: &str, store: &Arc<ReadyStore>) {
        let published = self.retried("publishing a store", sha256, true, || {
            self.publish(sha256, store)
        });
        match published {
            Tried::Done(published) => {
                tracing::info!(url = %published.url, points = store.point_count(),
                    "store published: workers read its nodes from object storage");
                if let Err(error) = self.forget_failure(sha256) {
                    tracing::warn!(%error, "forgetting a failed publish");
                }
            }
            Tried::Failed(error) => {
                tracing::warn!(%error, attempts = self.attempts,
                    "publishing a store failed; tried again when a frame of it is next leased");
                self.record_failure(sha256, &error);
                let mut queue = self.lock();
                if !queue.closed && !queue.unpublishing.iter().any(|s| s == sha256) {
                    queue.given_up.insert(sha256.to_owned(), Arc::clone(store));
                }
            }
            Tried::Stopped => {}
        }
    }

    /// Runs `step` until it succeeds, `attempts` times at most with backoff between tries,
    /// logging each failure as `what`'s. It stops early when the publisher is dropped and,
    /// where `stops_when_unpublished`, when content `sha256` is being unpublished.
    pub(super) fn retried<T>(
        &self,
        what: &str,
        sha256: &str,
        stops_when_unpublished: bool,
        mut step: impl FnMut() -> Result<T, PublishError>,
    ) -> Tried<T> {
        let stopped = |queue: &Queue| {
            queue.closed
                || (stops_when_unpublished && queue.unpublishing.iter().any(|s| s == sha256))
        };
        let mut backoff = FIRST_BACKOFF;
        for attempt in 1..=self.attempts {
            if stopped(&self.lock()) {
                return Tried::Stopped;
            }
            match step() {
                Ok(done) => return Tried::Done(done),
                Err(error) if attempt == self.attempts => return Tried::Failed(error),
                Err(error) => tracing::warn!(%error, attempt, retry_in_s = backoff.as_secs(),
                    "{what} failed; trying again"),
            }
            let queue = self.lock();
            let (queue, _) = self
                .wake
                .wait_timeout_while(queue, backoff, |queue| !stopped(queue))
                .unwrap_or_else(|e| e.into_inner());
            drop(queue);
            backoff = (backoff * 2).min(MAX_BACKOFF);
        }
        Tried::Stopped
    }

    /// Uploads the payload, then the hierarchy object, then records both versions.
    fn publish(&self, sha256: &str, store: &ReadyStore) -> Result<PublishedStore, PublishError> {
        let prefix = self.prefix(sha256)?;
        let payload_path = store.payload_path().ok_or(PublishError::NotAStore)?;
        let payload_url = prefix.join(PAYLOAD_OBJECT)?;
        let payload_bytes = upload_payload(&self.client, &payload_path, &payload_url)?;
        let payload_version = self.version_of(&payload_url, payload_bytes)?;
        let hierarchy = PublishedHierarchy {
            bounds: store.bounds(),
            payload_bytes,
            payload_version: payload_version.clone(),
            hierarchy_record: store.hierarchy_record.clone(),
        }
        .encode();
        let hierarchy_url = prefix.join(HIERARCHY_OBJECT)?;
        let hierarchy_bytes = hierarchy.len() as u64;
        let mut upload = self.client.start_upload(&hierarchy_url)?;
        upload.write(&hierarchy)?;
        upload.finish()?;
        let published = PublishedStore {
            url: prefix.to_string(),
            hierarchy_version: self.version_of(&hierarchy_url, hierarchy_bytes)?,
            payload_version,
        };
        let record =
            serde_json::to_vec(&published).map_err(|e| PublishError::Record(e.to_string()))?;
        self.records
            .insert(sha256.as_bytes(), record)
            .and_then(|_| self.records.flush().map(drop))
            .map_err(|e| PublishError::Record(e.to_string()))?;
        Ok(published)
    }

    /// The version of the object just written at `url`, checked to hold `bytes`.
    fn version_of(&self, url: &ObjectUrl, bytes: u64) -> Result<String, PublishError> {
        let object = self.client.open(url)?;
        if object.size() != bytes {
            return Err(PublishError::Changed {
                url: url.to_string(),
                reason: format!("{} bytes where {bytes} were written", object.size()),
            });
        }
        match object.version() {
            Some(version) if !version.is_empty() => Ok(version.to_owned()),
            _ => Err(PublishError::Changed {
                url: url.to_string(),
                reason: "the object store gives the object no version (ETag)".into(),
            }),
        }
    }
}

/// Uploads the payload at `path` (its layers and its own file, as one) to `url` a part at a
/// time; the bytes written. Dropping the upload on a failed read aborts it.
fn upload_payload(
    client: &RemoteClient,
    path: &Path,
    url: &ObjectUrl,
) -> Result<u64, PublishError> {
    let unreadable = |error: pointfarm_render::lod::LodError| RemoteError::Transport {
        url: url.to_string(),
        message: format!("reading the store's payload: {error}"),
    };
    let payload = PayloadReader::open(path).map_err(unreadable)?;
    let mut upload = client.start_upload(url)?;
    let mut buffer = vec![0u8; client.settings().upload_part_bytes.max(1)];
    let mut at = 0u64;
    while at < payload.len() {
        let n = (payload.len() - at).min(buffer.len() as u64) as usize;
        payload
            .read_exact_at(&mut buffer[..n], at)
            .map_err(unreadable)?;
        upload.write(&buffer[..n])?;
        at += n as u64;
    }
    Ok(upload.finish()?)
}

/// How a step tried again and again ended.
pub(super) enum Tried<T> {
    Done(T),
    /// Its last try's error.
    Failed(PublishError),
    /// The publisher was dropped, or the content unpublished, first.
    Stopped,
}

/// Why a store was not published or taken down; no variant holds a credential.
#[derive(Debug, thiserror::Error)]
pub(super) enum PublishError {
    #[error(transparent)]
    Remote(#[from] RemoteError),
    #[error("{url}: {reason}")]
    Changed { url: String, reason: String },
    #[error("recording the published store: {0}")]
    Record(String),
    #[error("a COPC file's hierarchy is not a store to publish")]
    NotAStore,
}

impl DatasetStores {
    /// Ready stores are published through `publisher`, and leases name them once published.
    pub fn publishing(mut self, publisher: Option<StorePublisher>) -> Self {
        self.publisher = publisher.map(Arc::new);
        self
    }

    /// The published store of content `sha256`, which workers read themselves; `None` while
    /// it is not published, or where the daemon publishes none.
    pub fn published(&self, sha256: &str) -> Option<PublishedStore> {
        self.publisher.as_ref()?.published(sha256)
    }
}

/// Offers `store`, of content `sha256`, to `publisher` where the daemon publishes stores.
pub(super) fn offer(publisher: Option<&StorePublisher>, sha256: &str, store: &Arc<ReadyStore>) {
    if let Some(publisher) = publisher {
        publisher.offer(sha256, store);
    }
}

impl ReadyStore {
    /// The store's payload file; `None` for a COPC file's hierarchy.
    pub(crate) fn payload_path(&self) -> Option<PathBuf> {
        match &self.kept {
            super::Kept::Store(lod) => Some(lod.folder.join(pointfarm_render::cut::PAYLOAD_FILE)),
            super::Kept::Copc(_) => None,
        }
    }
}

mod state;
mod unpublish;

pub use state::StorePublication;

#[cfg(test)]
mod tests {
    use super::store_url;

    #[test]
    fn a_store_url_is_an_s3_prefix() {
        let url = store_url("s3://stores/farm").expect("an s3 prefix");
        assert_eq!(url.as_str(), "s3://stores/farm/");
        assert_eq!(
            url.join("ab/").expect("join").as_str(),
            "s3://stores/farm/ab/"
        );
        for refused in [
            "https://data.example/stores/",
            "s3://user:pw@stores/farm",
            "farm/",
        ] {
            let error = store_url(refused).expect_err(refused).to_string();
            assert!(
                error.contains("store URL") && !error.contains("pw@"),
                "{error}"
            );
        }
    }
}

//! A dataset's level-of-detail store as the daemon published it to object storage (`serve
//! --store-url`), read by this worker itself: the lease names the store's prefix and its
//! objects' versions, credentials come from the worker's own environment, and the hierarchy
//! is read once, then only the node records each cut needs, by range, through the same client
//! and range cache as datasets by URL, so a frame reports its object requests and bytes alike.
//!
//! A published store that cannot be read (no credentials here, an object replaced or damaged,
//! a record failing its checks) fails the frame, as worth another attempt, and this worker
//! reads that dataset through the daemon from then on: the daemon's copy is the one it checks
//! and builds again when damaged.

use std::collections::HashSet;

use pointfarm_daemon::lease::{FrameTask, PublishedStore};
use pointfarm_render::lod::LodDataset;
use pointfarm_render::remote::ObjectUrl;
use pointfarm_render::source::{open_published_store, PublishedObjects};

use crate::failure::FrameFailure;
use crate::url_dataset::UrlReader;

/// The contents whose published store failed on this worker, read through the daemon since.
#[derive(Debug, Default)]
pub struct PublishedFailures(HashSet<String>);

impl PublishedFailures {
    /// The published store `task` names, unless it failed here before.
    pub fn store_of<'a>(&self, task: &'a FrameTask) -> Option<&'a PublishedStore> {
        let published = task.dataset.published.as_ref()?;
        (!self.0.contains(&task.dataset.sha256)).then_some(published)
    }

    /// Reads `task`'s dataset through the daemon from now on, and makes `failure` one worth
    /// another attempt, saying which store failed.
    pub fn failed(&mut self, task: &FrameTask, failure: FrameFailure) -> FrameFailure {
        self.0.insert(task.dataset.sha256.clone());
        let url = task
            .dataset
            .published
            .as_ref()
            .map_or("", |p| p.url.as_str());
        tracing::warn!(dataset = %task.dataset.id, url, reason = %failure.reason,
            "the published store failed; the dataset is read through the daemon from now on");
        FrameFailure::transient(format!(
            "the published store {url} of dataset {}: {}",
            task.dataset.id, failure.reason
        ))
    }
}

/// Opens the published store of `task`'s dataset through `urls`' client and range cache.
pub fn open(urls: &mut UrlReader, published: &PublishedStore) -> Result<LodDataset, FrameFailure> {
    let prefix = ObjectUrl::parse(&published.url).map_err(|e| FrameFailure::from(&e))?;
    let client = urls.client()?;
    let objects = PublishedObjects {
        prefix: &prefix,
        hierarchy_version: &published.hierarchy_version,
        payload_version: &published.payload_version,
    };
    open_published_store(&client, objects, urls.range_cache())
        .map_err(|e| FrameFailure::transient(e.to_string()))
}

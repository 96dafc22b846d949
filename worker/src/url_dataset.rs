//! A dataset by URL as the worker reads it: the COPC object itself, by range, with S3
//! credentials from the worker's own environment; the daemon hands the URL and the version it
//! registered, never the bytes. A worker that finds the object replaced since then fails the
//! frame saying so, rather than render another version than the dataset's. With a
//! [`DiskRangeCache`] the ranges read are kept on disk by the object's version, so a later
//! lease of the same dataset reads them from there (`range_cache`).

use std::sync::Arc;

use pointfarm_daemon::model::RemoteSource;
use pointfarm_render::copc::{
    open_copc_object, open_copc_object_cached, CopcDataset, CopcError, RangeCache,
};
use pointfarm_render::remote::{ObjectUrl, RemoteClient, RemoteError, RemoteSettings};

use crate::failure::FrameFailure;
use crate::range_cache::DiskRangeCache;

/// The worker's client for datasets by URL, made on the first one, so that a worker that
/// never renders one starts no runtime for it.
#[derive(Default)]
pub struct UrlReader {
    client: Option<RemoteClient>,
    cache: Option<Arc<DiskRangeCache>>,
}

impl UrlReader {
    /// A reader whose objects' ranges are kept in `cache`.
    pub fn with_cache(cache: Arc<DiskRangeCache>) -> Self {
        Self {
            client: None,
            cache: Some(cache),
        }
    }

    /// Requests and payload bytes fetched from object stores, and bytes served from the
    /// cache, since the reader was made.
    pub fn counts(&self) -> UrlReadCounts {
        let fetched = self.client.as_ref().map(RemoteClient::counts);
        UrlReadCounts {
            requests: fetched.map_or(0, |f| f.requests),
            fetched_bytes: fetched.map_or(0, |f| f.bytes),
            cached_bytes: self.cache.as_ref().map_or(0, |c| c.served_bytes()),
        }
    }

    /// Opens the object of `remote` for rendering, once its version is still the one
    /// registered; every read of it is then pinned to that version.
    pub fn open(&mut self, remote: &RemoteSource) -> Result<CopcDataset, FrameFailure> {
        let url = ObjectUrl::parse(&remote.url).map_err(|e| FrameFailure::from(&e))?;
        let client = self.client()?;
        let object = client.open(&url).map_err(|e| FrameFailure::from(&e))?;
        let now = object.version().unwrap_or_default();
        if now != remote.version {
            return Err(FrameFailure::permanent(format!(
                "{url}: the object changed since it was registered (version {}, now {now}); \
                 register it again",
                remote.version
            )));
        }
        // The object checked is the one read: its reads are pinned to the version compared.
        let opened = match &self.cache {
            Some(cache) => open_copc_object_cached(object, Arc::clone(cache) as _),
            None => open_copc_object(object),
        };
        opened.map_err(|e| match &e {
            CopcError::Remote(remote) => FrameFailure::from(remote),
            CopcError::Io { .. } => FrameFailure::transient(e.to_string()),
            _ => FrameFailure::permanent(e.to_string()),
        })
    }
}

impl UrlReader {
    /// The client every object is read through, made on first use, so that one count covers
    /// every object a frame reads.
    pub(crate) fn client(&mut self) -> Result<RemoteClient, FrameFailure> {
        if let Some(client) = &self.client {
            return Ok(client.clone());
        }
        let client =
            RemoteClient::new(RemoteSettings::default()).map_err(|e| FrameFailure::from(&e))?;
        Ok(self.client.insert(client).clone())
    }

    /// The range cache objects' ranges are kept in, when the worker keeps one.
    pub(crate) fn range_cache(&self) -> Option<Arc<dyn RangeCache>> {
        self.cache.clone().map(|cache| cache as Arc<dyn RangeCache>)
    }
}

/// What a [`UrlReader`] read, by the object store and by its cache.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct UrlReadCounts {
    pub requests: u64,
    pub fetched_bytes: u64,
    pub cached_bytes: u64,
}

/// A server that is down, slow or answered short may do better next time; a missing or
/// refused object, a bad URL or a replaced object will not.
impl From<&RemoteError> for FrameFailure {
    fn from(e: &RemoteError) -> Self {
        match e {
            RemoteError::TimedOut { .. }
            | RemoteError::Transport { .. }
            | RemoteError::ShortRead { .. }
            | RemoteError::Runtime { .. } => Self::transient(e.to_string()),
            _ => Self::permanent(e.to_string()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use pointfarm_daemon::lease::FailureKind;

    #[test]
    fn stalls_are_transient_and_missing_objects_permanent() {
        let url = || "https://data.example/a.copc.laz".to_owned();
        let cases = [
            (
                RemoteError::Transport {
                    url: url(),
                    message: "connection refused".into(),
                },
                FailureKind::Transient,
            ),
            (RemoteError::NotFound { url: url() }, FailureKind::Permanent),
            (
                RemoteError::ObjectChanged {
                    url: url(),
                    version: "\"e1\"".into(),
                },
                FailureKind::Permanent,
            ),
        ];
        for (error, kind) in cases {
            let failure = FrameFailure::from(&error);
            assert_eq!(failure.kind, kind, "{}", failure.reason);
            assert!(failure.reason.contains(&url()), "{}", failure.reason);
        }
    }
}

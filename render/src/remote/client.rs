//! `RemoteClient`: the runtime, the settings, the counters and the stores that every remote
//! object and listing shares.

use std::collections::HashMap;
use std::fmt;
use std::future::Future;
use std::sync::{Arc, Mutex, PoisonError};

use object_store::ObjectStore;

use super::allow::AllowedPrefixes;
use super::counters::{FetchCounters, FetchCounts};
use super::error::RemoteError;
use super::list::{list_point_files, ListedObject};
use super::redirect::RedirectRule;
use super::runtime::RemoteRuntime;
use super::settings::RemoteSettings;
use super::store::build_store;
use super::url::ObjectUrl;

/// Reads objects by URL; cheap to clone, and one per process is enough, since stores (and
/// their connections) are kept per bucket or origin.
#[derive(Clone)]
pub struct RemoteClient {
    inner: Arc<ClientInner>,
}

struct ClientInner {
    runtime: RemoteRuntime,
    settings: RemoteSettings,
    counters: Arc<FetchCounters>,
    stores: Mutex<HashMap<String, Arc<dyn ObjectStore>>>,
    redirects: Arc<RedirectRule>,
}

impl RemoteClient {
    /// A client whose HTTP(S) reads follow a redirect only within the origin asked.
    pub fn new(settings: RemoteSettings) -> Result<Self, RemoteError> {
        Self::with_redirects(settings, RedirectRule::SameOrigin)
    }

    /// A client for an operator's allow-list: its HTTP(S) reads follow a redirect only within
    /// the origin asked and under one of `allowed`'s prefixes, so that a server cannot send
    /// it around the list.
    pub fn within(settings: RemoteSettings, allowed: AllowedPrefixes) -> Result<Self, RemoteError> {
        Self::with_redirects(settings, RedirectRule::WithinPrefixes(allowed))
    }

    fn with_redirects(settings: RemoteSettings, rule: RedirectRule) -> Result<Self, RemoteError> {
        Ok(Self {
            inner: Arc::new(ClientInner {
                runtime: RemoteRuntime::new()?,
                settings,
                counters: Arc::default(),
                stores: Mutex::default(),
                redirects: Arc::new(rule),
            }),
        })
    }

    pub fn settings(&self) -> &RemoteSettings {
        &self.inner.settings
    }

    /// What this client has fetched so far, over all its objects.
    pub fn counts(&self) -> FetchCounts {
        self.inner.counters.snapshot()
    }

    /// The `.las` and `.laz` objects under a prefix, sorted by URL.
    pub fn list_point_files(&self, prefix: &ObjectUrl) -> Result<Vec<ListedObject>, RemoteError> {
        let store = self.store(prefix)?;
        let limit = self.inner.settings.max_listed_objects;
        let counters = Arc::clone(&self.inner.counters);
        let url = prefix.clone();
        let found = self.run(prefix, async move {
            counters.add(1, 0);
            list_point_files(store, &url, limit).await
        })?;
        Ok(found)
    }

    /// The store of a URL's bucket or origin, built on first use.
    pub(crate) fn store(&self, url: &ObjectUrl) -> Result<Arc<dyn ObjectStore>, RemoteError> {
        let mut stores = self
            .inner
            .stores
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        let key = url.store_key();
        if let Some(store) = stores.get(&key) {
            return Ok(Arc::clone(store));
        }
        let store = build_store(url, &self.inner.settings, &self.inner.redirects)?;
        stores.insert(key, Arc::clone(&store));
        Ok(store)
    }

    pub(crate) fn counters(&self) -> Arc<FetchCounters> {
        Arc::clone(&self.inner.counters)
    }

    /// Runs one operation on the runtime within the settings' deadline.
    pub(crate) fn run<F, T>(&self, url: &ObjectUrl, operation: F) -> Result<T, RemoteError>
    where
        F: Future<Output = Result<T, RemoteError>> + Send + 'static,
        T: Send + 'static,
    {
        let deadline = self.inner.settings.operation_deadline;
        let bounded = async move { tokio::time::timeout(deadline, operation).await };
        match self.inner.runtime.run(bounded)? {
            Ok(answer) => answer,
            Err(_elapsed) => Err(RemoteError::TimedOut {
                url: url.to_string(),
                after: deadline,
            }),
        }
    }
}

impl fmt::Debug for RemoteClient {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        // Stores are left out: their builders hold credentials.
        f.debug_struct("RemoteClient")
            .field("settings", &self.inner.settings)
            .field("counts", &self.counts())
            .finish_non_exhaustive()
    }
}

//! Where a dataset's store stands with object storage, from what the publisher records: the
//! published store's record, the offers under way, and the last failure, kept in a tree of
//! the same sled database so that a restarted daemon still says why a store is not published.

use serde::{Deserialize, Serialize};

use super::{PublishError, Shared, StorePublisher};
use crate::model::now_unix_ms;
use crate::stores::DatasetStores;

/// The sled tree of failed publishes, by content.
const FAILURES_TREE: &str = "failed";

/// How the store of one content stands with the object storage stores are published to.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum StorePublication {
    /// The daemon publishes no stores (no `serve --store-url`).
    NoStoreUrl,
    /// Not offered: no store is built yet, or it is a COPC file's own hierarchy.
    NotPublished,
    /// Offered: waiting, uploading, or between tries.
    Publishing,
    /// Published under the store's prefix `url`.
    Published { url: String },
    /// Every try failed, as `failure` records.
    Failed { failure: PublishFailure },
}

/// A publish whose every try failed, as recorded: the last try's error (which never holds a
/// credential) and when.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct PublishFailure {
    /// The store's prefix it was published to.
    pub url: String,
    pub reason: String,
    pub failed_unix_ms: i64,
}

impl DatasetStores {
    /// How the store of content `sha256` stands with object storage.
    pub fn publication(&self, sha256: &str) -> StorePublication {
        match &self.publisher {
            Some(publisher) => publisher.publication(sha256),
            None => StorePublication::NoStoreUrl,
        }
    }
}

impl StorePublisher {
    /// How the store of content `sha256` stands under this daemon's store URL.
    pub fn publication(&self, sha256: &str) -> StorePublication {
        self.shared.publication(sha256)
    }
}

impl Shared {
    fn publication(&self, sha256: &str) -> StorePublication {
        let offered = self.lock().offered.contains(sha256);
        let url = self.prefix(sha256).map(|url| url.to_string()).ok();
        publication(
            self.published(sha256).map(|published| published.url),
            offered,
            self.failure(sha256)
                .filter(|failure| Some(&failure.url) == url.as_ref()),
        )
    }

    fn failures(&self) -> Result<sled::Tree, PublishError> {
        self.records
            .open_tree(FAILURES_TREE)
            .map_err(|e| PublishError::Record(e.to_string()))
    }

    /// The last failed publish of content `sha256`, under whichever store URL it names.
    fn failure(&self, sha256: &str) -> Option<PublishFailure> {
        let record = self
            .failures()
            .and_then(|tree| {
                tree.get(sha256.as_bytes())
                    .map_err(|e| PublishError::Record(e.to_string()))
            })
            .inspect_err(|error| tracing::warn!(%error, "reading the failed publishes"))
            .ok()??;
        serde_json::from_slice(&record)
            .inspect_err(|error| tracing::warn!(%error, sha256, "an unreadable failed publish"))
            .ok()
    }

    /// Records that every try at publishing content `sha256` failed with `error`.
    pub(super) fn record_failure(&self, sha256: &str, error: &PublishError) {
        let failure = PublishFailure {
            url: self
                .prefix(sha256)
                .map(|url| url.to_string())
                .unwrap_or_default(),
            reason: error.to_string(),
            failed_unix_ms: now_unix_ms(),
        };
        let recorded = serde_json::to_vec(&failure)
            .map_err(|e| PublishError::Record(e.to_string()))
            .and_then(|record| {
                let tree = self.failures()?;
                tree.insert(sha256.as_bytes(), record)
                    .and_then(|_| tree.flush().map(drop))
                    .map_err(|e| PublishError::Record(e.to_string()))
            });
        if let Err(error) = recorded {
            tracing::warn!(%error, "recording a failed publish");
        }
    }

    /// Forgets the failed publish of content `sha256`, once published or taken down.
    pub(super) fn forget_failure(&self, sha256: &str) -> Result<(), PublishError> {
        let tree = self.failures()?;
        tree.remove(sha256.as_bytes())
            .and_then(|_| tree.flush().map(drop))
            .map_err(|e| PublishError::Record(e.to_string()))
    }
}

/// The state from the publisher's records: a published store's record first, then an offer
/// under way (tried again after a failure), then the last failure.
fn publication(
    published: Option<String>,
    offered: bool,
    failure: Option<PublishFailure>,
) -> StorePublication {
    match (published, offered, failure) {
        (Some(url), _, _) => StorePublication::Published { url },
        (None, true, _) => StorePublication::Publishing,
        (None, false, Some(failure)) => StorePublication::Failed { failure },
        (None, false, None) => StorePublication::NotPublished,
    }
}

#[cfg(test)]
mod tests {
    use pointfarm_render::remote::RemoteSettings;

    use super::*;
    use crate::stores::publish::store_url;

    const SHA256: &str = "ab12";

    fn publisher(records: &std::path::Path) -> StorePublisher {
        // Nothing listens at the store URL's server: nothing is offered, so nothing is sent.
        let url = store_url("s3://stores/farm").expect("an s3 prefix");
        StorePublisher::start(url, RemoteSettings::default(), 1, records).expect("publisher")
    }

    #[test]
    fn a_failed_publish_says_why_and_when_until_it_is_tried_again_or_published() {
        let dir = tempfile::tempdir().expect("tempdir");
        let records = dir.path().join("published-stores");
        let before = now_unix_ms();
        {
            let publisher = publisher(&records);
            assert_eq!(
                publisher.publication(SHA256),
                StorePublication::NotPublished
            );
            let error = PublishError::Changed {
                url: "s3://stores/farm/ab12/nodes.bin".into(),
                reason: "connection refused".into(),
            };
            publisher.shared.record_failure(SHA256, &error);
        }
        // Recorded in sled: a restarted daemon still says why.
        let publisher = publisher(&records);
        let StorePublication::Failed { failure } = publisher.publication(SHA256) else {
            panic!("failed: {:?}", publisher.publication(SHA256));
        };
        assert_eq!(failure.url, "s3://stores/farm/ab12/");
        assert_eq!(
            failure.reason,
            "s3://stores/farm/ab12/nodes.bin: connection refused"
        );
        assert!(failure.failed_unix_ms >= before && failure.failed_unix_ms <= now_unix_ms());
        // Offered again, it is being published; published, the failure is forgotten.
        publisher.shared.lock().offered.insert(SHA256.into());
        assert_eq!(publisher.publication(SHA256), StorePublication::Publishing);
        publisher.shared.lock().offered.remove(SHA256);
        publisher.shared.forget_failure(SHA256).expect("forget");
        assert_eq!(
            publisher.publication(SHA256),
            StorePublication::NotPublished
        );
    }

    #[test]
    fn a_published_record_wins_over_an_offer_and_a_failure() {
        let failure = PublishFailure {
            url: "s3://stores/farm/ab12/".into(),
            reason: "refused".into(),
            failed_unix_ms: 1,
        };
        let url = "s3://stores/farm/ab12/".to_owned();
        assert_eq!(
            publication(Some(url.clone()), true, Some(failure.clone())),
            StorePublication::Published { url }
        );
        assert_eq!(
            publication(None, true, Some(failure.clone())),
            StorePublication::Publishing
        );
        assert_eq!(
            publication(None, false, Some(failure.clone())),
            StorePublication::Failed { failure }
        );
        assert_eq!(
            publication(None, false, None),
            StorePublication::NotPublished
        );
    }
}

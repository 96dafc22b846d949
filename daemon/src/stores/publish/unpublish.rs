//! Taking down the published store of a content no dataset has any more: its record goes
//! first, so no lease names it from then on, then its hierarchy object, so no worker opens a
//! store half deleted, then its payload. It runs on the publishing thread, after any publish
//! of the same content under way, so a store deleted while it was being published leaves no
//! object behind; a failed deletion is logged and tried again with backoff.

use pointfarm_render::lod::published::{HIERARCHY_OBJECT, PAYLOAD_OBJECT};
use pointfarm_render::remote::ObjectUrl;

use super::{PublishError, Shared, StorePublisher, Tried};
use crate::stores::{DatasetStores, Entry};

impl DatasetStores {
    /// Takes down the published store of content `sha256`, which no dataset has any more;
    /// a store still building is not published when it ends.
    pub fn unpublish(&self, sha256: &str) {
        let Some(publisher) = &self.publisher else {
            return;
        };
        let building = matches!(self.entries_now().get(sha256), Some(Entry::Building { .. }));
        publisher.unpublish(sha256, building);
    }
}

impl StorePublisher {
    /// Deletes the objects of content `sha256` and its record, after any publish of it under
    /// way; where `building`, the offer its build ends with is dropped.
    pub fn unpublish(&self, sha256: &str, building: bool) {
        let mut queue = self.shared.lock();
        if queue.closed {
            return;
        }
        let before = queue.waiting.len();
        queue.waiting.retain(|(waiting, _)| waiting != sha256);
        if queue.waiting.len() != before {
            queue.offered.remove(sha256);
        }
        queue.given_up.remove(sha256);
        if building {
            queue.unwanted.insert(sha256.to_owned());
        }
        if !queue.unpublishing.iter().any(|waiting| waiting == sha256) {
            queue.unpublishing.push_back(sha256.to_owned());
        }
        self.shared.wake.notify_all();
    }
}

impl Shared {
    pub(super) fn unpublish_with_retries(&self, sha256: &str) {
        // The prefix under this store URL, where a publish may have stopped part way, and
        // the one the record names, where it was published under another.
        let mut prefixes: Vec<ObjectUrl> = self.prefix(sha256).into_iter().collect();
        if let Some(url) = self
            .record(sha256)
            .and_then(|record| ObjectUrl::parse(&record.url).ok())
        {
            if prefixes
                .iter()
                .all(|prefix| prefix.as_str() != url.as_str())
            {
                prefixes.push(url);
            }
        }
        match self.retried("deleting a published store", sha256, false, || {
            self.unpublish(sha256, &prefixes)
        }) {
            Tried::Done(()) => {
                for prefix in &prefixes {
                    tracing::info!(url = %prefix, "published store deleted: no dataset has it");
                }
            }
            Tried::Failed(error) => tracing::warn!(%error,
                "deleting a published store failed; its objects stay in object storage"),
            Tried::Stopped => {}
        }
    }

    /// Forgets the record and any failed publish, then deletes each prefix's hierarchy
    /// object and payload.
    fn unpublish(&self, sha256: &str, prefixes: &[ObjectUrl]) -> Result<(), PublishError> {
        self.records
            .remove(sha256.as_bytes())
            .and_then(|_| self.records.flush().map(drop))
            .map_err(|e| PublishError::Record(e.to_string()))?;
        self.forget_failure(sha256)?;
        for prefix in prefixes {
            for object in [HIERARCHY_OBJECT, PAYLOAD_OBJECT] {
                self.client.delete(&prefix.join(object)?)?;
            }
        }
        Ok(())
    }
}

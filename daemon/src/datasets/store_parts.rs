//! The parts of datasets whose stores are built first for jobs (`stores::camera_first`),
//! recorded in the state database and settled when the daemon starts. More `Daemon` methods.

use std::collections::HashSet;
use std::sync::{Arc, Weak};

use crate::error::StateError;
use crate::model::CameraFirstPart;
use crate::service::Daemon;
use crate::stores::PartLedger;

/// The state database of a daemon, where its stores record their parts.
struct StateLedger(Weak<Daemon>);

impl PartLedger for StateLedger {
    fn keep(&self, part: &CameraFirstPart) {
        let Some(daemon) = self.0.upgrade() else {
            return;
        };
        if let Err(error) = daemon.state.put_camera_first_part(part) {
            // The part still serves this run; a restart only grows its whole store later.
            tracing::warn!(part = %part.part.id, %error, "recording a part built first");
        }
    }

    fn forget(&self, id: &str) {
        let Some(daemon) = self.0.upgrade() else {
            return;
        };
        if let Err(error) = daemon.state.remove_camera_first_part(id) {
            tracing::warn!(part = %id, %error, "forgetting a part built first");
        }
    }
}

impl Daemon {
    /// Has the stores record their parts in the state, and settles the parts a stopped
    /// daemon left (`DatasetStores::settle_parts`). Called once, at start-up, before any
    /// job is leased and before the stores' unfinished builds resume.
    pub(crate) fn keep_store_parts(self: &Arc<Self>) {
        self.stores
            .record_parts_in(Arc::new(StateLedger(Arc::downgrade(self))));
        let found = self
            .state
            .camera_first_parts()
            .and_then(|recorded| Ok((recorded, self.state.datasets()?, self.leased_contents()?)));
        match found {
            Ok((recorded, datasets, leased)) => {
                self.stores.settle_parts(recorded, &datasets, &leased)
            }
            Err(error) => {
                tracing::warn!(%error, "the parts built first cannot be settled: left as they are")
            }
        }
    }

    /// The contents of the datasets whose unfinished jobs hold leases.
    fn leased_contents(&self) -> Result<HashSet<String>, StateError> {
        let mut contents = HashSet::new();
        for lease in self.state.leases()? {
            let Some(job) = self.state.job(&lease.job_id)? else {
                continue;
            };
            if job.state.is_terminal() {
                continue;
            }
            if let Some(dataset) = self.state.dataset(&job.spec.dataset_id)? {
                contents.insert(dataset.sha256);
            }
        }
        Ok(contents)
    }
}

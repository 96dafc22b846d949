//! Store builds a stopped daemon left unfinished go on when it starts again. A build records
//! its finished units in a journal in the store's folder (render/src/lod/journal.rs); at
//! startup every dataset that unfinished jobs still use and whose store folder holds no
//! finished store has its build started again at once, not when a worker first asks, and the
//! build takes over what the journal lists, redoing at most the units that were in flight.
//! An update of a copied store left part way (`growth.rs`) is started again at once too.

use pointfarm_render::cut::StoredLod;
use pointfarm_render::lod::LodBuildReport;

use super::growth::growing_folder;
use super::{DatasetStores, ReadyStore};
use crate::model::Dataset;

/// The units a build took over from an earlier run; `None` when it started anew.
pub(super) fn taken_over(report: &LodBuildReport) -> Option<usize> {
    report.counting_resumed.then_some(report.resumed_units)
}

/// Says what the build of dataset `id` took over, when it resumed one.
pub(super) fn log_resumed(id: &str, ready: &ReadyStore) {
    if let Some(units) = ready.resumed {
        tracing::info!(
            dataset = %id,
            units,
            "resumed the store build of {id}: {units} units taken over"
        );
    }
}

impl DatasetStores {
    /// Starts again the builds of the stores of `waiting` (datasets that unfinished jobs use)
    /// that a stopped daemon left unfinished: those whose folder exists without a finished
    /// store. A dataset that cannot be built now (its files gone) is left to the first request,
    /// which reports why. Returns how many builds started.
    pub fn resume_builds(&self, waiting: impl IntoIterator<Item = Dataset>) -> usize {
        let mut started = 0;
        for dataset in waiting {
            let folder = self.folder(&dataset.sha256);
            let under_way = folder.is_dir() || growing_folder(&folder).is_dir();
            if !under_way || StoredLod::is_built(&folder) {
                continue;
            }
            if self.building_version(&dataset.sha256).is_some() {
                continue;
            }
            tracing::info!(dataset = %dataset.id, folder = %folder.display(),
                "resuming the store build a stopped daemon left");
            // Its jobs asked for the store: the folder exists only once a build started.
            match self.open_store(&dataset, true) {
                Ok(_) => started += 1,
                Err(error) => tracing::warn!(dataset = %dataset.id, %error,
                    "the store build a stopped daemon left cannot go on now"),
            }
        }
        started
    }
}

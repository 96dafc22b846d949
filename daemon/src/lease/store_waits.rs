//! What a job's frames wait for while the store of their dataset builds. A previewed frame
//! waits for the build's version to move past its preview's. A final frame of a job without
//! previews is not leased at all while the store its frames read builds (the whole store, or
//! the part built first for the job): its worker could only hand it back. The store's build
//! wakes the lease long poll when it ends (`DatasetStores::notifying`), so the frame goes out
//! the moment its store is ready. A dataset by URL is read by its workers themselves and never
//! waits for a store of the daemon's.

use std::cell::RefCell;
use std::collections::HashMap;

use crate::model::Job;
use crate::service::Daemon;

/// The stores the jobs of one lease scan wait for, each job's looked up once (the scan asks
/// for every previewed frame of a job).
pub(super) struct StoreWaits<'a> {
    daemon: &'a Daemon,
    jobs: RefCell<HashMap<String, Waiting>>,
}

/// What a job's frames find of their dataset's store.
#[derive(Clone, Copy)]
struct Waiting {
    /// The preview version of the store while it builds; `None` when it does not build.
    building: Option<u32>,
    /// Whether workers read the dataset by URL, not through the daemon's store.
    by_url: bool,
}

impl<'a> StoreWaits<'a> {
    pub(super) fn new(daemon: &'a Daemon) -> Self {
        Self {
            daemon,
            jobs: RefCell::default(),
        }
    }

    fn waiting(&self, job: &Job) -> Waiting {
        *self
            .jobs
            .borrow_mut()
            .entry(job.id.clone())
            .or_insert_with(|| {
                let dataset = self
                    .daemon
                    .state
                    .dataset(&job.spec.dataset_id)
                    .ok()
                    .flatten();
                // The part of the dataset its frames see while the whole store is not ready.
                let leased = dataset.map(|dataset| self.daemon.stores.leased(job, &dataset));
                Waiting {
                    building: leased
                        .as_ref()
                        .and_then(|dataset| self.daemon.stores.building_version(&dataset.sha256)),
                    by_url: leased.is_some_and(|dataset| dataset.remote.is_some()),
                }
            })
    }

    /// The preview version of the store `job`'s frames read, while it builds.
    pub(super) fn building(&self, job: &Job) -> Option<u32> {
        self.waiting(job).building
    }

    /// Whether the final frames of `job`, which asks for no previews, wait for their store.
    pub(super) fn holds_final_frames(&self, job: &Job) -> bool {
        let waiting = self.waiting(job);
        !job.spec.preview && !waiting.by_url && waiting.building.is_some()
    }

    /// The turn of a frame of a previewed job whose preview is of version `drawn` (`None`: it
    /// has none), or `None` while it waits. A frame without a preview comes first; one with a
    /// preview is drawn again when the build has stored another tenth of the points, the
    /// oldest previews first, and rendered as a final frame once the store is ready (or, for
    /// a COPC file's coarse previews, at once), after the frames without a preview.
    pub(super) fn turn(&self, job: &Job, drawn: Option<u32>) -> Option<u32> {
        let Some(drawn) = drawn else {
            return Some(0);
        };
        match self.building(job) {
            Some(current) if drawn >= current => None,
            Some(_) => Some(drawn + 1),
            None => Some(1),
        }
    }
}

impl Daemon {
    /// Whether the final frames of `job` are not leased while the store they read builds.
    pub(crate) fn store_holds_final_frames(&self, job: &Job) -> bool {
        StoreWaits::new(self).holds_final_frames(job)
    }

    /// A final frame of `job` was handed in, or the job ended: a whole store whose growth
    /// waits for the job's first frame starts growing (`DatasetStores::job_moved`).
    pub(crate) fn tell_stores_job_moved(&self, job: &Job) {
        if let Ok(Some(dataset)) = self.state.dataset(&job.spec.dataset_id) {
            self.stores.job_moved(job, &dataset);
        }
    }
}

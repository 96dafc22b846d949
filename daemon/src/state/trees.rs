//! The trees of the state database, and the start-up census of their records.

use super::{decode, INDEX_VERSION_KEY};
use crate::error::StateError;
use crate::lease_record::Lease;
use crate::manifest::Counts;
use crate::model::{CameraFirstPart, Dataset, FrameReport, FrameState, Job};
use crate::output_queue::PendingOutput;

/// A tree of records by name, with the test that a record decodes.
type RecordTree<'a> = (&'static str, &'a sled::Tree, fn(&[u8]) -> bool);

/// The trees of a database.
pub(super) struct Trees {
    pub(super) datasets: sled::Tree,
    pub(super) jobs: sled::Tree,
    /// Request ids to the jobs they created.
    pub(super) requests: sled::Tree,
    pub(super) frames: sled::Tree,
    pub(super) leases: sled::Tree,
    /// The unfinished jobs, keyed by [`super::queue_key`] (highest priority first, then oldest).
    pub(super) queue: sled::Tree,
    /// The pending frames, keyed as in `frames`; the values are empty.
    pub(super) pending: sled::Tree,
    /// The latest preview of a pending frame of a preview job, keyed as in `frames`; removed
    /// when the frame is done.
    pub(super) previews: sled::Tree,
    /// The database's own facts (the version of the scheduling index).
    pub(super) meta: sled::Tree,
    /// The outputs waiting to be uploaded to object storage, in the order they were queued.
    pub(super) outputs: sled::Tree,
    /// The parts of datasets whose stores are built first for jobs, by their dataset ids.
    pub(super) parts: sled::Tree,
}

impl Trees {
    pub(super) fn open(db: &sled::Db) -> Result<Self, StateError> {
        Ok(Self {
            datasets: db.open_tree("datasets")?,
            jobs: db.open_tree("jobs")?,
            requests: db.open_tree("requests")?,
            frames: db.open_tree("frames")?,
            leases: db.open_tree("leases")?,
            queue: db.open_tree("queue")?,
            pending: db.open_tree("pending")?,
            previews: db.open_tree("previews")?,
            meta: db.open_tree("meta")?,
            outputs: db.open_tree("outputs")?,
            parts: db.open_tree("camera-first-parts")?,
        })
    }

    /// The trees whose records must decode, by name.
    fn records(&self) -> [RecordTree<'_>; 7] {
        [
            ("datasets", &self.datasets, |v| decode::<Dataset>(v).is_ok()),
            ("jobs", &self.jobs, |v| decode::<Job>(v).is_ok()),
            ("frames", &self.frames, |v| decode::<FrameState>(v).is_ok()),
            ("leases", &self.leases, |v| decode::<Lease>(v).is_ok()),
            ("previews", &self.previews, |v| {
                decode::<FrameReport>(v).is_ok()
            }),
            ("outputs", &self.outputs, |v| {
                decode::<PendingOutput>(v).is_ok()
            }),
            ("camera-first-parts", &self.parts, |v| {
                decode::<CameraFirstPart>(v).is_ok()
            }),
        ]
    }

    /// Counts the readable jobs and datasets and lists the records that do not decode.
    pub(super) fn census(&self) -> Result<(Counts, Vec<String>), StateError> {
        let mut unreadable = Vec::new();
        for (name, tree, readable) in self.records() {
            for entry in tree.iter() {
                let (key, value) = entry?;
                if !readable(&value) {
                    unreadable.push(format!("{name}/{}", String::from_utf8_lossy(&key)));
                }
            }
        }
        let unreadable_in = |tree: &str| unreadable.iter().filter(|r| r.starts_with(tree)).count();
        let counts = Counts {
            jobs: (self.jobs.len() - unreadable_in("jobs/")) as u64,
            datasets: (self.datasets.len() - unreadable_in("datasets/")) as u64,
        };
        Ok((counts, unreadable))
    }

    /// Drops the records listed as `tree/key`; the scheduling index is rebuilt after it.
    pub(super) fn remove_unreadable(&self, unreadable: &[String]) -> Result<(), StateError> {
        for record in unreadable {
            let Some((name, key)) = record.split_once('/') else {
                continue;
            };
            if let Some((_, tree, _)) = self.records().into_iter().find(|(n, ..)| *n == name) {
                tree.remove(key.as_bytes())?;
            }
        }
        if !unreadable.is_empty() {
            self.meta.remove(INDEX_VERSION_KEY)?;
        }
        Ok(())
    }
}

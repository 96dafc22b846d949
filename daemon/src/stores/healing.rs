//! A store whose bytes fail their checks heals itself, once: the records served to workers
//! are checked as a worker checks them, and a damaged store is removed and built again the
//! first time in a run; a second failure is reported to this and every later request.

use std::sync::atomic::Ordering;
use std::sync::Arc;

use pointfarm_render::cut::StoredLod;
use pointfarm_render::lod::codec::check_node;
use pointfarm_render::lod::{LodError, NodeInfo, NodeKey};

use super::{DatasetStores, Entry, Kept, ReadyStore};
use crate::error::DaemonError;
use crate::model::Dataset;

impl ReadyStore {
    /// The stored records of `keys`, in order, or only their coarse sections where `coarse`
    /// and the store keeps them apart; each must be a node of the hierarchy with points. A
    /// COPC file's records are its LAZ chunks, byte ranges of the file, always whole. A
    /// store's records are checked as a worker checks them; one that fails is an error here
    /// ([`DatasetStores::node_records`] builds the store again).
    pub fn records(&self, keys: &[NodeKey], coarse: bool) -> Result<Vec<Vec<u8>>, DaemonError> {
        self.checked_records(keys, coarse)
            .map_err(|failure| match failure {
                RecordsFailure::Refused(error) => error,
                RecordsFailure::Damaged(damage) => {
                    DaemonError::Internal(format!("reading the store's nodes: {damage}"))
                }
            })
    }

    /// [`ReadyStore::records`], telling a store whose bytes failed their checks from the
    /// other failures.
    fn checked_records(
        &self,
        keys: &[NodeKey],
        coarse: bool,
    ) -> Result<Vec<Vec<u8>>, RecordsFailure> {
        let hierarchy = self.hierarchy();
        let infos: Vec<NodeInfo> = keys
            .iter()
            .map(|&key| match hierarchy.node(key) {
                Some(info) if info.point_count > 0 => Ok(*info),
                _ => Err(RecordsFailure::Refused(DaemonError::invalid(
                    "nodes",
                    format!("node {key} holds no points of this store"),
                ))),
            })
            .collect::<Result<_, _>>()?;
        let records = self.dataset().records();
        let read = match coarse {
            true => records.read_coarse_records(&infos),
            false => None,
        };
        let failed = |error: LodError| match error.is_damage() {
            true => RecordsFailure::Damaged(error),
            false => RecordsFailure::Refused(DaemonError::Internal(format!(
                "reading the store's nodes: {error}"
            ))),
        };
        let read = read
            .unwrap_or_else(|| records.read_records(&infos))
            .map_err(failed)?;
        // A COPC file's chunks are checked as they decode, on the worker.
        if let Kept::Store(_) = self.kept {
            for (info, bytes) in infos.iter().zip(&read) {
                check_node(info.key, info.point_count, bytes).map_err(RecordsFailure::Damaged)?;
            }
        }
        Ok(read)
    }
}

/// Why records were not served.
enum RecordsFailure {
    /// The request, or the read (named).
    Refused(DaemonError),
    /// The store's bytes failed their checks.
    Damaged(LodError),
}

impl DatasetStores {
    /// How many node records this run served to workers.
    pub fn records_served(&self) -> u64 {
        self.records_served.load(Ordering::Relaxed)
    }

    /// The records of `keys` of `dataset`'s ready store ([`ReadyStore::records`]), each
    /// checked as a worker checks it. A store whose bytes fail their checks is built again,
    /// once in this run: the request is refused meanwhile (its frame is tried again, and
    /// finds the store building); after that one rebuild, a second failure is reported to
    /// this and every later request.
    pub fn node_records(
        &self,
        dataset: &Dataset,
        keys: &[NodeKey],
        coarse: bool,
    ) -> Result<Vec<Vec<u8>>, DaemonError> {
        let store = self.ready(dataset)?;
        match store.checked_records(keys, coarse) {
            Ok(records) => {
                let served = records.len() as u64;
                self.records_served.fetch_add(served, Ordering::Relaxed);
                Ok(records)
            }
            Err(RecordsFailure::Refused(error)) => Err(error),
            Err(RecordsFailure::Damaged(damage)) => {
                let _one_decision = self.opening.lock().unwrap_or_else(|e| e.into_inner());
                let rebuilding = self.rebuild_damaged(dataset, Some(&store), &damage.to_string());
                Err(rebuilding.map_or_else(|e| e, |_| being_rebuilt(dataset)))
            }
        }
    }

    /// Removes the store of `dataset`, whose bytes failed their checks (`damage`, found in
    /// `seen` when it was open), and starts building it again, the first time in this run:
    /// its points then. A second time, or when it cannot be removed, the dataset's later
    /// requests are refused saying so, and so is this one. Called under `opening`.
    pub(super) fn rebuild_damaged(
        &self,
        dataset: &Dataset,
        seen: Option<&Arc<ReadyStore>>,
        damage: &str,
    ) -> Result<u64, DaemonError> {
        let sha = dataset.sha256.as_str();
        let points = match self.entries_now().get(sha) {
            // Another request found the damage first: its rebuild is under way, or done.
            Some(Entry::Ready(current)) if seen.is_some_and(|seen| !Arc::ptr_eq(seen, current)) => {
                return Err(being_rebuilt(dataset));
            }
            Some(Entry::Ready(current)) => Some(current.point_count()),
            Some(Entry::Building { .. }) => return Err(being_rebuilt(dataset)),
            Some(Entry::Failed(reason)) => {
                return Err(DaemonError::FailedPrecondition(reason.clone()))
            }
            Some(Entry::Counted(points)) => Some(*points),
            None => None,
        };
        let about = dataset_words(dataset);
        let folder = self.folder(sha);
        let refuse = |reason: String| {
            self.set(sha, Entry::Failed(reason.clone()));
            DaemonError::FailedPrecondition(reason)
        };
        let first = self
            .rebuilt
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .insert(sha.to_owned());
        if !first {
            tracing::warn!(dataset = %dataset.id, folder = %folder.display(), reason = %damage,
                "a store built again after it failed its checks failed them again; not built again");
            return Err(refuse(format!(
                "{about}: its level-of-detail store failed its checks again after it was \
                 rebuilt ({damage}); it is not rebuilt again"
            )));
        }
        tracing::warn!(dataset = %dataset.id, folder = %folder.display(), reason = %damage,
            "rebuilding a damaged store");
        if let Err(error) = StoredLod::remove_damaged(&folder) {
            tracing::warn!(dataset = %dataset.id, %error, "the damaged store could not be removed");
            return Err(refuse(format!(
                "{about}: its level-of-detail store failed its checks ({damage}) and could not \
                 be removed to build it again"
            )));
        }
        self.rebuilds.fetch_add(1, Ordering::Relaxed);
        let points = match points {
            Some(points) => points,
            None => self.point_count(dataset)?,
        };
        self.start_build(dataset, points).map(|_| points)
    }
}

/// A dataset as its errors name it: its id and its files' names (never a path of this server).
fn dataset_words(dataset: &Dataset) -> String {
    let names: Vec<String> = dataset.files().into_iter().map(|f| f.name).collect();
    let files = match names.as_slice() {
        [] => String::new(),
        [one] => one.clone(),
        [first, rest @ ..] => format!(
            "{first} and {} more file{}",
            rest.len(),
            if rest.len() == 1 { "" } else { "s" }
        ),
    };
    format!("dataset {} ({files})", dataset.id)
}

/// The refusal of a request for the records of `dataset`'s store while it is built again.
pub(super) fn being_rebuilt(dataset: &Dataset) -> DaemonError {
    DaemonError::FailedPrecondition(format!(
        "{}: its level-of-detail store failed its checks and is being built again; ask \
         OpenDatasetStore again",
        dataset_words(dataset)
    ))
}

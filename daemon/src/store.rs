//! The durable state of the daemon, in sled: datasets, jobs, the frames of each job, and the
//! request ids that make submission idempotent, and the leases of frames being rendered. One
//! `Store` owns the database.
//!
//! A frame is marked done only after its PNG is on disk, so after a crash (even `kill -9`)
//! every frame is either done and written, or pending and rendered again. Changes of several
//! records are one sled transaction.
//!
//! Scheduling reads an index rather than every job: `queue` holds the unfinished jobs by
//! priority and age, `pending` the frames still to render. A lease therefore costs the same
//! with one job in the history or ten thousand (`docs/perf/lease-index.md`).

use serde::de::DeserializeOwned;
use serde::Serialize;
use sled::transaction::TransactionError;
use sled::Transactional;

use crate::error::StoreError;
use crate::lease_record::Lease;
use crate::manifest::{Counts, Manifest};
use crate::model::{now_unix_ms, Dataset, FrameReport, FrameState, Job, JobSpec, JobState};

pub struct Store {
    db: sled::Db,
    trees: Trees,
    /// How many jobs and datasets the database holds, recorded beside it.
    manifest: Manifest,
}

/// What opening a damaged database found missing or unreadable.
#[derive(Debug, Default, Clone, PartialEq, Eq)]
pub struct StateLoss {
    /// Jobs and datasets the manifest counts that the database no longer holds.
    pub missing: Counts,
    /// Records that do not decode, as `tree/key`.
    pub unreadable: Vec<String>,
}

impl StateLoss {
    pub fn is_empty(&self) -> bool {
        self.missing == Counts::default() && self.unreadable.is_empty()
    }
}

impl std::fmt::Display for StateLoss {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let Counts { jobs, datasets } = self.missing;
        write!(f, "{jobs} jobs and {datasets} datasets missing")?;
        if !self.unreadable.is_empty() {
            let shown: Vec<&str> = self.unreadable.iter().take(5).map(String::as_str).collect();
            write!(
                f,
                ", {} unreadable records ({}",
                self.unreadable.len(),
                shown.join(", ")
            )?;
            if self.unreadable.len() > shown.len() {
                write!(f, ", ...")?;
            }
            write!(f, ")")?;
        }
        Ok(())
    }
}

/// The version of the scheduling index kept in `meta`; an older database has its index built
/// when it is opened.
const INDEX_VERSION: &[u8] = b"1";
const INDEX_VERSION_KEY: &[u8] = b"scheduling-index";

/// Queue keys sort by priority (highest first), then by job id (ids sort by creation).
fn queue_key(job: &Job) -> Vec<u8> {
    // Flipping the sign bit orders i32 as unsigned; inverting puts the highest first.
    let priority = !((job.spec.priority as u32) ^ 0x8000_0000);
    let mut key = priority.to_be_bytes().to_vec();
    key.extend_from_slice(job.id.as_bytes());
    key
}

/// A transaction's error as the store's.
fn transaction_error(e: TransactionError<StoreError>) -> StoreError {
    match e {
        TransactionError::Abort(e) => e,
        TransactionError::Storage(e) => StoreError::Db(e),
    }
}

/// A page of a listing and the token of the next one (empty at the end).
pub struct Page<T> {
    pub items: Vec<T>,
    pub next_token: String,
}

fn encode<T: Serialize>(value: &T) -> Result<Vec<u8>, StoreError> {
    Ok(serde_json::to_vec(value)?)
}

fn decode<T: DeserializeOwned>(bytes: &[u8]) -> Result<T, StoreError> {
    Ok(serde_json::from_slice(bytes)?)
}

/// The record stored under a key, if there is one.
fn decode_stored<T: DeserializeOwned>(value: Option<sled::IVec>) -> Result<Option<T>, StoreError> {
    value.map(|v| decode(&v)).transpose()
}

/// Frame keys sort by job, then by index.
fn frame_key(job_id: &str, index: u32) -> Vec<u8> {
    let mut key = job_id.as_bytes().to_vec();
    key.push(b'/');
    key.extend_from_slice(&index.to_be_bytes());
    key
}

impl Store {
    /// Opens the database at `path`, after checking every record and the counts in its
    /// manifest: a damaged database is refused with what it lost, unless `recover`, which
    /// drops the unreadable records and returns what was lost with the store.
    pub fn open(path: &std::path::Path, recover: bool) -> Result<(Self, StateLoss), StoreError> {
        let db = sled::open(path).map_err(|e| match e {
            // sled reports the lock held by another process only in its message.
            sled::Error::Io(io) if io.to_string().contains("could not acquire lock") => {
                StoreError::Locked(path.to_owned())
            }
            e => StoreError::Damaged(format!(
                "the state database {} cannot be opened: {e}",
                path.display()
            )),
        })?;
        let manifest_path = Manifest::beside(path);
        let recorded = Manifest::read(&manifest_path)?;
        let trees = Trees::open(&db)?;
        let (found, unreadable) = trees.census()?;
        let missing = recorded.map_or_else(Counts::default, |recorded| Counts {
            jobs: recorded.jobs.saturating_sub(found.jobs),
            datasets: recorded.datasets.saturating_sub(found.datasets),
        });
        let loss = StateLoss {
            missing,
            unreadable,
        };
        if !loss.is_empty() && !recover {
            return Err(StoreError::Damaged(format!(
                "the state database {} is damaged: {loss}",
                path.display()
            )));
        }
        trees.remove_unreadable(&loss.unreadable)?;
        let manifest = Manifest::create(manifest_path, found)?;
        let store = Self {
            db,
            trees,
            manifest,
        };
        if store.trees.meta.get(INDEX_VERSION_KEY)?.as_deref() != Some(INDEX_VERSION) {
            store.rebuild_index()?;
        }
        Ok((store, loss))
    }

    /// Builds the scheduling index from the jobs and frames (a database written before the
    /// index existed).
    fn rebuild_index(&self) -> Result<(), StoreError> {
        self.trees.queue.clear()?;
        self.trees.pending.clear()?;
        for entry in self.trees.jobs.iter() {
            let job: Job = decode(&entry?.1)?;
            if !job.state.is_terminal() {
                self.trees
                    .queue
                    .insert(queue_key(&job), job.id.as_bytes())?;
            }
        }
        for entry in self.trees.frames.iter() {
            let (key, value) = entry?;
            if let FrameState::Pending { .. } = decode::<FrameState>(&value)? {
                self.trees.pending.insert(key, &[])?;
            }
        }
        self.trees.meta.insert(INDEX_VERSION_KEY, INDEX_VERSION)?;
        self.db.flush()?;
        Ok(())
    }

    /// Writes everything to disk.
    pub fn flush(&self) -> Result<(), StoreError> {
        self.db.flush()?;
        Ok(())
    }

    // ------------------------------------------------------------------ datasets

    pub fn put_dataset(&self, dataset: &Dataset) -> Result<(), StoreError> {
        let replaced = self
            .trees
            .datasets
            .insert(dataset.id.as_bytes(), encode(dataset)?)?;
        if replaced.is_none() {
            self.db.flush()?;
            self.manifest.update(|counts| counts.datasets += 1)?;
        }
        Ok(())
    }

    pub fn dataset(&self, id: &str) -> Result<Option<Dataset>, StoreError> {
        decode_stored(self.trees.datasets.get(id.as_bytes())?)
    }

    pub fn delete_dataset(&self, id: &str) -> Result<Option<Dataset>, StoreError> {
        if !self.trees.datasets.contains_key(id.as_bytes())? {
            return Ok(None);
        }
        // Counted out first: a crash in between leaves the manifest short, never over.
        self.manifest
            .update(|counts| counts.datasets = counts.datasets.saturating_sub(1))?;
        let removed = decode_stored(self.trees.datasets.remove(id.as_bytes())?);
        self.db.flush()?;
        removed
    }

    pub fn list_datasets(
        &self,
        page_size: usize,
        token: &str,
    ) -> Result<Page<Dataset>, StoreError> {
        page(
            &self.trees.datasets,
            page_size,
            token,
            |_: &Dataset| true,
            |d| d.id.clone(),
        )
    }

    // ------------------------------------------------------------------ jobs

    /// Creates a job with all its frames pending, or returns the job that an earlier
    /// submission with the same request id created (`false`).
    pub fn submit_job(&self, spec: JobSpec) -> Result<(Job, bool), StoreError> {
        if !spec.request_id.is_empty() {
            if let Some(id) = self.trees.requests.get(spec.request_id.as_bytes())? {
                let id = String::from_utf8_lossy(&id).into_owned();
                if let Some(job) = self.job(&id)? {
                    return Ok((job, false));
                }
            }
        }
        // Ids sort by creation: a monotonic counter, zero-padded.
        let id = format!("job-{:012}", self.db.generate_id()?);
        let now = now_unix_ms();
        let frames = spec.request.frames();
        let job = Job {
            id: id.clone(),
            state: JobState::Queued,
            frames_total: frames,
            frames_done: 0,
            error: None,
            created_unix_ms: now,
            updated_unix_ms: now,
            spec,
        };
        let pending = encode(&FrameState::Pending { attempts: 0 })?;
        let (mut frame_batch, mut pending_batch) = (sled::Batch::default(), sled::Batch::default());
        for index in 0..frames {
            frame_batch.insert(frame_key(&id, index), pending.clone());
            pending_batch.insert(frame_key(&id, index), &[]);
        }
        let encoded = encode(&job)?;
        let trees = (
            &self.trees.frames,
            &self.trees.pending,
            &self.trees.jobs,
            &self.trees.requests,
            &self.trees.queue,
        );
        trees
            .transaction(|(frames, pending, jobs, requests, queue)| {
                frames.apply_batch(&frame_batch)?;
                pending.apply_batch(&pending_batch)?;
                jobs.insert(id.as_bytes(), encoded.as_slice())?;
                if !job.spec.request_id.is_empty() {
                    requests.insert(job.spec.request_id.as_bytes(), id.as_bytes())?;
                }
                queue.insert(queue_key(&job), id.as_bytes())?;
                Ok(())
            })
            .map_err(transaction_error)?;
        self.db.flush()?;
        self.manifest.update(|counts| counts.jobs += 1)?;
        Ok((job, true))
    }

    pub fn job(&self, id: &str) -> Result<Option<Job>, StoreError> {
        decode_stored(self.trees.jobs.get(id.as_bytes())?)
    }

    /// Stores `job`; a job that has ended leaves the scheduling index, with its frames.
    pub fn put_job(&self, job: &Job) -> Result<(), StoreError> {
        let encoded = encode(job)?;
        if !job.state.is_terminal() {
            self.trees.jobs.insert(job.id.as_bytes(), encoded)?;
            return Ok(());
        }
        let mut prefix = job.id.as_bytes().to_vec();
        prefix.push(b'/');
        let mut unlisted = sled::Batch::default();
        for key in self.trees.pending.scan_prefix(&prefix).keys() {
            unlisted.remove(key?);
        }
        (&self.trees.jobs, &self.trees.queue, &self.trees.pending)
            .transaction(|(jobs, queue, pending)| {
                jobs.insert(job.id.as_bytes(), encoded.as_slice())?;
                queue.remove(queue_key(job))?;
                pending.apply_batch(&unlisted)?;
                Ok(())
            })
            .map_err(transaction_error)
    }

    /// Applies `change` to the stored job and returns the result (None if there is no such
    /// job). Bumps the update time.
    pub fn update_job(
        &self,
        id: &str,
        change: impl FnOnce(&mut Job),
    ) -> Result<Option<Job>, StoreError> {
        let Some(mut job) = self.job(id)? else {
            return Ok(None);
        };
        change(&mut job);
        job.updated_unix_ms = now_unix_ms();
        self.put_job(&job)?;
        Ok(Some(job))
    }

    pub fn list_jobs(
        &self,
        state: Option<JobState>,
        page_size: usize,
        token: &str,
    ) -> Result<Page<Job>, StoreError> {
        page(
            &self.trees.jobs,
            page_size,
            token,
            |j: &Job| state.is_none_or(|s| j.state == s),
            |j| j.id.clone(),
        )
    }

    /// Whether an unfinished job renders the dataset `dataset_id`: every job is looked at.
    pub fn dataset_in_use(&self, dataset_id: &str) -> Result<bool, StoreError> {
        for entry in self.trees.jobs.iter() {
            let job: Job = decode(&entry?.1)?;
            if job.spec.dataset_id == dataset_id && !job.state.is_terminal() {
                return Ok(true);
            }
        }
        Ok(false)
    }

    /// The bytes of the datasets whose files lie in `uploads` (the ones uploaded, not
    /// registered from a data root).
    pub fn uploaded_bytes(&self, uploads: &std::path::Path) -> Result<u64, StoreError> {
        let mut total = 0u64;
        for entry in self.trees.datasets.iter() {
            let dataset: Dataset = decode(&entry?.1)?;
            if dataset.path.starts_with(uploads) {
                total = total.saturating_add(dataset.size_bytes);
            }
        }
        Ok(total)
    }

    pub fn frame(&self, job_id: &str, index: u32) -> Result<Option<FrameState>, StoreError> {
        decode_stored(self.trees.frames.get(frame_key(job_id, index))?)
    }

    pub fn set_frame(
        &self,
        job_id: &str,
        index: u32,
        state: &FrameState,
    ) -> Result<(), StoreError> {
        let key = frame_key(job_id, index);
        let encoded = encode(state)?;
        let is_pending = matches!(state, FrameState::Pending { .. });
        (&self.trees.frames, &self.trees.pending)
            .transaction(|(frames, pending)| {
                frames.insert(key.as_slice(), encoded.as_slice())?;
                if is_pending {
                    pending.insert(key.as_slice(), &[])?;
                } else {
                    pending.remove(key.as_slice())?;
                }
                Ok(())
            })
            .map_err(transaction_error)
    }

    /// The next frame to render: the first pending frame that is not `leased`, of the
    /// unfinished job with the highest priority, the oldest first among equals. Reads the
    /// scheduling index, so finished jobs cost nothing.
    pub fn next_task(
        &self,
        leased: &std::collections::HashSet<(String, u32)>,
    ) -> Result<Option<(Job, u32)>, StoreError> {
        for entry in self.trees.queue.iter() {
            let (_, job_id) = entry?;
            let mut prefix = job_id.to_vec();
            prefix.push(b'/');
            let job_id = String::from_utf8_lossy(&job_id).into_owned();
            for key in self.trees.pending.scan_prefix(&prefix).keys() {
                let key = key?;
                let index_bytes: [u8; 4] = key[prefix.len()..].try_into().unwrap_or([0; 4]);
                let index = u32::from_be_bytes(index_bytes);
                if leased.contains(&(job_id.clone(), index)) {
                    continue;
                }
                match self.job(&job_id)? {
                    Some(job) if !job.state.is_terminal() => return Ok(Some((job, index))),
                    _ => break,
                }
            }
        }
        Ok(None)
    }

    /// After a restart: jobs that were running go back to the queue (their finished frames
    /// stay finished). Returns how many.
    pub fn requeue_running(&self) -> Result<usize, StoreError> {
        let mut requeued = 0;
        for entry in self.trees.jobs.iter() {
            let (_, value) = entry?;
            let mut job: Job = decode(&value)?;
            if job.state == JobState::Running {
                job.state = JobState::Queued;
                self.put_job(&job)?;
                requeued += 1;
            }
        }
        Ok(requeued)
    }

    // ------------------------------------------------------------------ leases

    pub fn put_lease(&self, lease: &Lease) -> Result<(), StoreError> {
        self.trees
            .leases
            .insert(lease.id.as_bytes(), encode(lease)?)?;
        Ok(())
    }

    pub fn lease(&self, id: &str) -> Result<Option<Lease>, StoreError> {
        decode_stored(self.trees.leases.get(id.as_bytes())?)
    }

    pub fn remove_lease(&self, id: &str) -> Result<(), StoreError> {
        self.trees.leases.remove(id.as_bytes())?;
        Ok(())
    }

    pub fn leases(&self) -> Result<Vec<Lease>, StoreError> {
        self.trees
            .leases
            .iter()
            .map(|entry| decode(&entry?.1))
            .collect()
    }

    /// A new id, unique in this database (also across restarts).
    pub fn generate_id(&self) -> Result<u64, StoreError> {
        Ok(self.db.generate_id()?)
    }

    /// The reports of the finished frames of a job, by frame index.
    pub fn frame_reports(&self, job_id: &str) -> Result<Vec<FrameReport>, StoreError> {
        let mut prefix = job_id.as_bytes().to_vec();
        prefix.push(b'/');
        let mut out = Vec::new();
        for entry in self.trees.frames.scan_prefix(&prefix) {
            let (_, value) = entry?;
            if let FrameState::Done(report) = decode::<FrameState>(&value)? {
                out.push(report);
            }
        }
        Ok(out)
    }
}

/// A tree of records by name, with the test that a record decodes.
type RecordTree<'a> = (&'static str, &'a sled::Tree, fn(&[u8]) -> bool);

/// The trees of a database.
struct Trees {
    datasets: sled::Tree,
    jobs: sled::Tree,
    /// Request ids to the jobs they created.
    requests: sled::Tree,
    frames: sled::Tree,
    leases: sled::Tree,
    /// The unfinished jobs, keyed by [`queue_key`] (highest priority first, then oldest).
    queue: sled::Tree,
    /// The pending frames, keyed as in `frames`; the values are empty.
    pending: sled::Tree,
    /// The database's own facts (the version of the scheduling index).
    meta: sled::Tree,
}

impl Trees {
    fn open(db: &sled::Db) -> Result<Self, StoreError> {
        Ok(Self {
            datasets: db.open_tree("datasets")?,
            jobs: db.open_tree("jobs")?,
            requests: db.open_tree("requests")?,
            frames: db.open_tree("frames")?,
            leases: db.open_tree("leases")?,
            queue: db.open_tree("queue")?,
            pending: db.open_tree("pending")?,
            meta: db.open_tree("meta")?,
        })
    }

    /// The trees whose records must decode, by name.
    fn records(&self) -> [RecordTree<'_>; 4] {
        [
            ("datasets", &self.datasets, |v| decode::<Dataset>(v).is_ok()),
            ("jobs", &self.jobs, |v| decode::<Job>(v).is_ok()),
            ("frames", &self.frames, |v| decode::<FrameState>(v).is_ok()),
            ("leases", &self.leases, |v| decode::<Lease>(v).is_ok()),
        ]
    }

    /// Counts the readable jobs and datasets and lists the records that do not decode.
    fn census(&self) -> Result<(Counts, Vec<String>), StoreError> {
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
    fn remove_unreadable(&self, unreadable: &[String]) -> Result<(), StoreError> {
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

/// A page of `tree` in key order after `token`, keeping the records `keep` accepts.
fn page<T: DeserializeOwned>(
    tree: &sled::Tree,
    page_size: usize,
    token: &str,
    keep: impl Fn(&T) -> bool,
    key_of: impl Fn(&T) -> String,
) -> Result<Page<T>, StoreError> {
    let page_size = if page_size == 0 {
        100
    } else {
        page_size.min(1000)
    };
    let mut items = Vec::new();
    let start = std::ops::Bound::Excluded(token.as_bytes().to_vec());
    let range = if token.is_empty() {
        tree.range::<Vec<u8>, _>(..)
    } else {
        tree.range((start, std::ops::Bound::Unbounded))
    };
    for entry in range {
        let (_, value) = entry?;
        let item: T = decode(&value)?;
        if keep(&item) {
            items.push(item);
            if items.len() == page_size {
                break;
            }
        }
    }
    let next_token = if items.len() == page_size {
        items.last().map(&key_of).unwrap_or_default()
    } else {
        String::new()
    };
    Ok(Page { items, next_token })
}

#[cfg(test)]
mod tests;

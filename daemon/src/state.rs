//! The durable state of the daemon, in sled: datasets, jobs, the frames of each job, and the
//! request ids that make submission idempotent, and the leases of frames being rendered. One
//! `StateDb` owns the database.
//!
//! A frame is marked done only after its PNG is on disk, so after a crash (even `kill -9`)
//! every frame is either done and written, or pending and rendered again. Changes of several
//! records are one sled transaction.
//!
//! Scheduling reads an index rather than every job: `queue` holds the unfinished jobs by
//! priority and age, `pending` the frames still to render. A lease therefore costs the same
//! with one job in the history or ten thousand (`docs/perf/lease-index.md`).
//!
//! A disk that refuses a write (full, over quota, failing) starts an outage: callers get
//! [`StateError::Unwritable`], the first refusal is logged, and sled (0.34), which keeps the
//! I/O error and refuses every later write until it is opened again, is closed and reopened
//! by [`StateDb::end_outage`] once a probe write succeeds.

use std::collections::HashSet;
use std::path::{Path, PathBuf};
use std::sync::{Mutex, MutexGuard, RwLock};
use std::time::{Duration, Instant};

use serde::de::DeserializeOwned;
use serde::Serialize;
use sled::transaction::TransactionError;

use crate::error::StateError;
use crate::lease_record::Lease;
use crate::manifest::{Counts, Manifest};
use crate::model::{Dataset, FrameReport, FrameState, Job, JobSpec, JobState};

mod control;
mod health;
mod outputs;
mod parts;
mod records;
mod trees;

pub use control::JobFilter;

use health::DiskHealth;
use records::Records;
use trees::Trees;

pub struct StateDb {
    path: PathBuf,
    /// The open database. sled refuses every write after one failed until it is opened
    /// again, so after a disk outage [`StateDb::end_outage`] swaps in a new one; None only
    /// while that failed.
    records: RwLock<Option<Records>>,
    /// How many jobs and datasets the database holds, recorded beside it.
    manifest: Manifest,
    /// Whether the disk takes writes.
    disk: DiskHealth,
    /// Leases given back while the disk refused writes, removed again when it takes them.
    given_back: Mutex<HashSet<String>>,
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

/// A transaction's error as the state database's.
fn transaction_error(e: TransactionError<StateError>) -> StateError {
    match e {
        TransactionError::Abort(e) => e,
        TransactionError::Storage(e) => StateError::Db(e),
    }
}

/// A page of a listing and the token of the next one (empty at the end).
pub struct Page<T> {
    pub items: Vec<T>,
    pub next_token: String,
}

fn encode<T: Serialize>(value: &T) -> Result<Vec<u8>, StateError> {
    Ok(serde_json::to_vec(value)?)
}

fn decode<T: DeserializeOwned>(bytes: &[u8]) -> Result<T, StateError> {
    Ok(serde_json::from_slice(bytes)?)
}

/// The record stored under a key, if there is one.
fn decode_stored<T: DeserializeOwned>(value: Option<sled::IVec>) -> Result<Option<T>, StateError> {
    value.map(|v| decode(&v)).transpose()
}

/// The prefix of the keys of job `job_id`'s frames (and pending frames, and previews).
fn frames_prefix(job_id: &str) -> Vec<u8> {
    let mut prefix = job_id.as_bytes().to_vec();
    prefix.push(b'/');
    prefix
}

/// Frame keys sort by job, then by index.
fn frame_key(job_id: &str, index: u32) -> Vec<u8> {
    let mut key = frames_prefix(job_id);
    key.extend_from_slice(&index.to_be_bytes());
    key
}

impl StateDb {
    /// Opens the database at `path`, after checking every record and the counts in its
    /// manifest: a damaged database is refused with what it lost, unless `recover`, which
    /// drops the unreadable records and returns what was lost with the database.
    pub fn open(path: &Path, recover: bool) -> Result<(Self, StateLoss), StateError> {
        let db = open_database_waiting(path, OPEN_WAIT)?;
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
            return Err(StateError::Damaged(format!(
                "the state database {} is damaged: {loss}",
                path.display()
            )));
        }
        trees.remove_unreadable(&loss.unreadable)?;
        let manifest = Manifest::create(manifest_path, found)?;
        let records = Records { db, trees };
        if records.trees.meta.get(INDEX_VERSION_KEY)?.as_deref() != Some(INDEX_VERSION) {
            records.rebuild_index()?;
        }
        let state = Self {
            path: path.to_owned(),
            records: RwLock::new(Some(records)),
            manifest,
            disk: DiskHealth::new(path),
            given_back: Mutex::new(HashSet::new()),
        };
        Ok((state, loss))
    }

    /// Runs `work` on the open database; a write the disk refused is remembered (logged
    /// once) and told as [`StateError::Unwritable`].
    fn with<T>(
        &self,
        work: impl FnOnce(&Records) -> Result<T, StateError>,
    ) -> Result<T, StateError> {
        // The records are replaced whole or not at all, so a panic elsewhere leaves them usable.
        let records = self.records.read().unwrap_or_else(|e| e.into_inner());
        let Some(records) = records.as_ref() else {
            return Err(StateError::Unwritable(self.disk.outage().unwrap_or_else(
                || "the state database is being opened again after a failed write".into(),
            )));
        };
        work(records).map_err(|e| self.noted(e))
    }

    /// `error` as callers should see it: a refused write becomes part of the outage.
    fn noted(&self, error: StateError) -> StateError {
        match &error {
            StateError::Db(sled::Error::Io(io)) => {
                StateError::Unwritable(self.disk.refused(io, true))
            }
            StateError::Io(io) => StateError::Unwritable(self.disk.refused(io, false)),
            _ => error,
        }
    }

    /// Applies `change` to the manifest's counts; a refused write is part of the outage.
    fn count(&self, change: impl FnOnce(&mut Counts)) -> Result<(), StateError> {
        self.manifest.update(change).map_err(|e| self.noted(e))
    }

    /// Writes everything to disk.
    pub fn flush(&self) -> Result<(), StateError> {
        self.with(Records::flush)
    }

    // ------------------------------------------------------------------ the disk

    /// Why the disk refuses writes, while it does (a full disk, a quota, a failing device).
    pub fn outage(&self) -> Option<String> {
        self.disk.outage()
    }

    /// The disk refused to write a frame (`error`); returns what to tell the worker.
    pub fn frame_write_refused(&self, error: &std::io::Error) -> String {
        self.disk.refused(error, false)
    }

    /// Ends an outage once the disk takes writes again: a probe file is written beside the
    /// database, and if sled met the outage (it then refuses every write until it is opened
    /// again) the database is closed and opened anew. Returns whether the outage ended.
    ///
    /// What was flushed before the outage is all there after it. What the outage can lose is
    /// the write that failed and what had not been flushed when it failed: the daemon flushes
    /// after every change it reports as done, so that is at most the change the caller was
    /// told had failed, and lease renewals (which `Daemon` makes again after an outage).
    /// Leases given back meanwhile ([`StateDb::give_back_lease`]) are removed again here.
    pub fn end_outage(&self) -> Result<bool, StateError> {
        if self.disk.outage().is_none() || self.disk.probe().is_err() {
            return Ok(false);
        }
        if self.disk.database_failed() {
            self.reopen()?;
        }
        let given_back: Vec<String> = self.given_back().drain().collect();
        let removed = self.with(|records| {
            for id in &given_back {
                records.remove_lease(id)?;
            }
            records.flush()
        });
        if let Err(e) = removed {
            self.given_back().extend(given_back);
            return Err(e);
        }
        self.disk.recovered();
        Ok(true)
    }

    /// Closes the failed database and opens it again (sled resets its failure only then).
    fn reopen(&self) -> Result<(), StateError> {
        let mut slot = self.records.write().unwrap_or_else(|e| e.into_inner());
        // Dropped first: sled holds a lock on its files until then.
        drop(slot.take());
        let db = open_database_waiting(&self.path, REOPEN_WAIT)?;
        let trees = Trees::open(&db)?;
        *slot = Some(Records { db, trees });
        tracing::info!(database = %self.path.display(), "the state database was opened again after the failed write");
        Ok(())
    }

    fn given_back(&self) -> MutexGuard<'_, HashSet<String>> {
        // A plain set, consistent after any panic.
        self.given_back.lock().unwrap_or_else(|e| e.into_inner())
    }

    // ------------------------------------------------------------------ datasets

    pub fn put_dataset(&self, dataset: &Dataset) -> Result<(), StateError> {
        if self.with(|records| records.put_dataset(dataset))? {
            self.count(|counts| counts.datasets += 1)?;
        }
        Ok(())
    }

    pub fn dataset(&self, id: &str) -> Result<Option<Dataset>, StateError> {
        self.with(|records| records.dataset(id))
    }

    pub fn delete_dataset(&self, id: &str) -> Result<Option<Dataset>, StateError> {
        if self.dataset(id)?.is_none() {
            return Ok(None);
        }
        // Counted out first: a crash in between leaves the manifest short, never over.
        self.count(|counts| counts.datasets = counts.datasets.saturating_sub(1))?;
        self.with(|records| records.delete_dataset(id))
    }

    pub fn list_datasets(
        &self,
        page_size: usize,
        token: &str,
    ) -> Result<Page<Dataset>, StateError> {
        self.with(|records| records.list_datasets(page_size, token))
    }

    // ------------------------------------------------------------------ jobs

    /// Creates a job with all its frames pending, or returns the job that an earlier
    /// submission with the same request id created (`false`).
    /// A disk in an outage or without room refuses the job before it is written, so that no
    /// reader sees a job whose write then fails.
    pub fn submit_job(&self, spec: JobSpec) -> Result<(Job, bool), StateError> {
        if let Some(job) = self.with(|records| records.requested_job(&spec.request_id))? {
            return Ok((job, false));
        }
        self.disk.check_room().map_err(StateError::Unwritable)?;
        let (job, created) = self.with(|records| records.submit_job(spec))?;
        if created {
            self.count(|counts| counts.jobs += 1)?;
        }
        Ok((job, created))
    }

    pub fn job(&self, id: &str) -> Result<Option<Job>, StateError> {
        self.with(|records| records.job(id))
    }

    /// Stores `job`; a job that has ended leaves the scheduling index, with its frames.
    pub fn put_job(&self, job: &Job) -> Result<(), StateError> {
        self.with(|records| records.put_job(job))
    }

    /// Applies `change` to the stored job and returns the result (None if there is no such
    /// job). Bumps the update time.
    pub fn update_job(
        &self,
        id: &str,
        change: impl FnOnce(&mut Job),
    ) -> Result<Option<Job>, StateError> {
        self.with(|records| records.update_job(id, change))
    }

    pub fn list_jobs(
        &self,
        state: Option<JobState>,
        page_size: usize,
        token: &str,
    ) -> Result<Page<Job>, StateError> {
        let filter = JobFilter {
            state,
            ..JobFilter::default()
        };
        self.list_matching_jobs(&filter, page_size, token)
    }

    /// A page of the jobs `filter` accepts, in id order (the order of submission).
    pub fn list_matching_jobs(
        &self,
        filter: &JobFilter,
        page_size: usize,
        token: &str,
    ) -> Result<Page<Job>, StateError> {
        self.with(|records| records.list_matching_jobs(filter, page_size, token))
    }

    /// Puts every unfinished frame of job `id` back in the queue with no attempt counted and
    /// applies `change` to the job, which must leave it unfinished; one flushed transaction.
    /// None if there is no such job.
    pub fn requeue_unfinished_frames(
        &self,
        id: &str,
        change: impl FnOnce(&mut Job),
    ) -> Result<Option<Job>, StateError> {
        self.with(|records| records.requeue_unfinished_frames(id, change))
    }

    /// Gives job `id` a new priority, and an unfinished job its new place in the scheduling
    /// index; one flushed transaction. None if there is no such job.
    pub fn set_priority(&self, id: &str, priority: i32) -> Result<Option<Job>, StateError> {
        self.with(|records| records.set_priority(id, priority))
    }

    /// Removes job `id` with every record of it and returns it; None if there is no such
    /// job. Its leases stay until next used or run out, so that their holders learn why to
    /// stop.
    pub fn delete_job(&self, id: &str) -> Result<Option<Job>, StateError> {
        if self.job(id)?.is_none() {
            return Ok(None);
        }
        // Counted out first: a crash in between leaves the manifest short, never over.
        self.count(|counts| counts.jobs = counts.jobs.saturating_sub(1))?;
        self.with(|records| records.delete_job(id))
    }

    /// Every job that has ended: every job is read.
    pub fn ended_jobs(&self) -> Result<Vec<Job>, StateError> {
        self.with(Records::ended_jobs)
    }

    /// The unfinished jobs, highest priority first, then oldest: read from the scheduling
    /// index, so finished jobs cost nothing.
    pub fn unfinished_jobs(&self) -> Result<Vec<Job>, StateError> {
        self.with(Records::unfinished_jobs)
    }

    /// Whether an unfinished job renders the dataset `dataset_id`: every job is looked at.
    pub fn dataset_in_use(&self, dataset_id: &str) -> Result<bool, StateError> {
        self.with(|records| records.dataset_in_use(dataset_id))
    }

    /// The bytes of the datasets whose files lie in `uploads` (the ones uploaded, not
    /// registered from a data root).
    /// Every dataset (they are few: files, not points).
    pub fn datasets(&self) -> Result<Vec<Dataset>, StateError> {
        self.with(|records| records.datasets())
    }

    pub fn uploaded_bytes(&self, uploads: &Path) -> Result<u64, StateError> {
        self.with(|records| records.uploaded_bytes(uploads))
    }

    pub fn frame(&self, job_id: &str, index: u32) -> Result<Option<FrameState>, StateError> {
        self.with(|records| records.frame(job_id, index))
    }

    pub fn set_frame(
        &self,
        job_id: &str,
        index: u32,
        state: &FrameState,
    ) -> Result<(), StateError> {
        self.with(|records| records.set_frame(job_id, index, state))
    }

    /// Marks the frame of `lease` done with `report`, removes the lease and applies `change`
    /// to its job, as one flushed transaction. None if there is no such job.
    pub fn finish_frame(
        &self,
        lease: &Lease,
        report: &FrameReport,
        change: impl FnOnce(&mut Job),
    ) -> Result<Option<Job>, StateError> {
        self.with(|records| records.finish_frame(lease, report, change))
    }

    /// The next frame to render: the first pending frame that is not `leased`, of the
    /// unfinished job with the highest priority that `usable` accepts (the asking worker can
    /// render it), the oldest first among equals. Reads the scheduling index, so finished
    /// jobs cost nothing.
    /// A preview job's frame has its turn by `turn(job, preview_version)`, the version of its
    /// preview when it has one: `None` passes it over, `Some(0)` takes it at once, and among
    /// higher turns the job's lowest is taken (the first frame of it).
    pub fn next_task(
        &self,
        leased: &HashSet<(String, u32)>,
        usable: &dyn Fn(&Job) -> bool,
        turn: &dyn Fn(&Job, Option<u32>) -> Option<u32>,
    ) -> Result<Option<(Job, u32)>, StateError> {
        self.with(|records| records.next_task(leased, usable, turn))
    }

    /// Keeps `report` as the preview of the pending frame of `lease` and removes the lease,
    /// as one flushed transaction. None if there is no such job.
    pub fn keep_preview(
        &self,
        lease: &Lease,
        report: &FrameReport,
    ) -> Result<Option<Job>, StateError> {
        self.with(|records| records.keep_preview(lease, report))
    }

    /// Whether frame `index` of job `job_id` has a preview (and is not done).
    pub fn has_preview(&self, job_id: &str, index: u32) -> Result<bool, StateError> {
        self.with(|records| records.has_preview(job_id, index))
    }

    /// The version of the preview of frame `index` of job `job_id`, when it has one (and is
    /// not done).
    pub fn preview_version(&self, job_id: &str, index: u32) -> Result<Option<u32>, StateError> {
        self.with(|records| records.preview_version(job_id, index))
    }

    /// Sets frame `index` of job `job_id` pending after `attempts` failed attempts and applies
    /// `change` to its job (the worker's failures), as one transaction. None if there is no
    /// such job.
    pub fn count_failed_attempt(
        &self,
        job_id: &str,
        index: u32,
        attempts: u32,
        change: impl FnOnce(&mut Job),
    ) -> Result<Option<Job>, StateError> {
        self.with(|records| records.count_failed_attempt(job_id, index, attempts, change))
    }

    /// After a restart: jobs that were running go back to the queue (their finished frames
    /// stay finished). Returns how many.
    pub fn requeue_running(&self) -> Result<usize, StateError> {
        self.with(Records::requeue_running)
    }

    /// The failed attempts recorded at a job's frames, finished or pending.
    pub fn failed_attempts(&self, job_id: &str) -> Result<u64, StateError> {
        self.with(|records| records.failed_attempts(job_id))
    }

    /// The reports of the finished frames of a job and the previews of its pending ones, by
    /// frame index.
    pub fn frame_reports(&self, job_id: &str) -> Result<Vec<FrameReport>, StateError> {
        self.with(|records| records.frame_reports(job_id))
    }

    /// A new id, unique in this database (also across restarts).
    pub fn generate_id(&self) -> Result<u64, StateError> {
        self.with(Records::generate_id)
    }

    // ------------------------------------------------------------------ leases

    pub fn put_lease(&self, lease: &Lease) -> Result<(), StateError> {
        self.with(|records| records.put_lease(lease))
    }

    /// The lease `id`; one given back during an outage is not held any more.
    pub fn lease(&self, id: &str) -> Result<Option<Lease>, StateError> {
        if self.given_back().contains(id) {
            return Ok(None);
        }
        self.with(|records| records.lease(id))
    }

    pub fn remove_lease(&self, id: &str) -> Result<(), StateError> {
        self.with(|records| records.remove_lease(id))
    }

    /// Removes the lease `id` durably; while the disk refuses writes its removal is kept in
    /// memory and done again when the outage ends, so that its frame counts no attempt when
    /// the lease would have run out.
    pub fn give_back_lease(&self, id: &str) -> Result<(), StateError> {
        let removed = self.with(|records| {
            records.remove_lease(id)?;
            records.flush()
        });
        match removed {
            Err(StateError::Unwritable(_)) => {
                self.given_back().insert(id.to_owned());
                Ok(())
            }
            other => other,
        }
    }

    /// Every lease held, without those given back during an outage.
    pub fn leases(&self) -> Result<Vec<Lease>, StateError> {
        let mut leases = self.with(Records::leases)?;
        let given_back = self.given_back();
        leases.retain(|lease| !given_back.contains(&lease.id));
        Ok(leases)
    }
}

/// How long reopening waits for the old database's threads to let go of its files.
const REOPEN_WAIT: Duration = Duration::from_secs(10);
/// How long opening waits for a database just closed (by this process, or a daemon that is
/// exiting) to let go of its files; a daemon still running is refused after it.
const OPEN_WAIT: Duration = Duration::from_secs(2);

/// Opens the sled database at `path`, waiting up to `wait` while its lock is held: sled's
/// last threads of a database just dropped may still hold its files.
fn open_database_waiting(path: &Path, wait: Duration) -> Result<sled::Db, StateError> {
    let deadline = Instant::now() + wait;
    loop {
        match open_database(path) {
            Err(StateError::Locked(_)) if Instant::now() < deadline => {
                std::thread::sleep(Duration::from_millis(20))
            }
            opened => return opened,
        }
    }
}

/// Opens the sled database at `path`.
fn open_database(path: &Path) -> Result<sled::Db, StateError> {
    sled::open(path).map_err(|e| match e {
        // sled reports the lock held by another process only in its message.
        sled::Error::Io(io) if io.to_string().contains("could not acquire lock") => {
            StateError::Locked(path.to_owned())
        }
        e => StateError::Damaged(format!(
            "the state database {} cannot be opened: {e}",
            path.display()
        )),
    })
}

/// A page of `tree` in key order after `token`, keeping the records `keep` accepts.
fn page<T: DeserializeOwned>(
    tree: &sled::Tree,
    page_size: usize,
    token: &str,
    keep: impl Fn(&T) -> bool,
    key_of: impl Fn(&T) -> String,
) -> Result<Page<T>, StateError> {
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

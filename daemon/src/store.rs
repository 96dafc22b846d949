//! The durable state of the daemon, in sled: datasets, jobs, the frames of each job, and the
//! request ids that make submission idempotent, and the leases of frames being rendered. One
//! `Store` owns the database.
//!
//! A frame is marked done only after its PNG is on disk, so after a crash (even `kill -9`)
//! every frame is either done and written, or pending and rendered again.

use serde::de::DeserializeOwned;
use serde::Serialize;

use crate::error::StoreError;
use crate::lease_record::Lease;
use crate::model::{now_unix_ms, Dataset, FrameReport, FrameState, Job, JobSpec, JobState};

pub struct Store {
    db: sled::Db,
    datasets: sled::Tree,
    jobs: sled::Tree,
    requests: sled::Tree,
    frames: sled::Tree,
    leases: sled::Tree,
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
    pub fn open(path: &std::path::Path) -> Result<Self, StoreError> {
        let db = sled::open(path)?;
        Ok(Self {
            datasets: db.open_tree("datasets")?,
            jobs: db.open_tree("jobs")?,
            requests: db.open_tree("requests")?,
            frames: db.open_tree("frames")?,
            leases: db.open_tree("leases")?,
            db,
        })
    }

    /// Writes everything to disk.
    pub fn flush(&self) -> Result<(), StoreError> {
        self.db.flush()?;
        Ok(())
    }

    // ------------------------------------------------------------------ datasets

    pub fn put_dataset(&self, dataset: &Dataset) -> Result<(), StoreError> {
        self.datasets
            .insert(dataset.id.as_bytes(), encode(dataset)?)?;
        Ok(())
    }

    pub fn dataset(&self, id: &str) -> Result<Option<Dataset>, StoreError> {
        decode_stored(self.datasets.get(id.as_bytes())?)
    }

    pub fn delete_dataset(&self, id: &str) -> Result<Option<Dataset>, StoreError> {
        decode_stored(self.datasets.remove(id.as_bytes())?)
    }

    pub fn list_datasets(
        &self,
        page_size: usize,
        token: &str,
    ) -> Result<Page<Dataset>, StoreError> {
        page(
            &self.datasets,
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
            if let Some(id) = self.requests.get(spec.request_id.as_bytes())? {
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
        let mut batch = sled::Batch::default();
        for index in 0..frames {
            batch.insert(frame_key(&id, index), pending.clone());
        }
        self.frames.apply_batch(batch)?;
        self.jobs.insert(id.as_bytes(), encode(&job)?)?;
        if !job.spec.request_id.is_empty() {
            self.requests
                .insert(job.spec.request_id.as_bytes(), id.as_bytes())?;
        }
        self.db.flush()?;
        Ok((job, true))
    }

    pub fn job(&self, id: &str) -> Result<Option<Job>, StoreError> {
        decode_stored(self.jobs.get(id.as_bytes())?)
    }

    pub fn put_job(&self, job: &Job) -> Result<(), StoreError> {
        self.jobs.insert(job.id.as_bytes(), encode(job)?)?;
        Ok(())
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
            &self.jobs,
            page_size,
            token,
            |j: &Job| state.is_none_or(|s| j.state == s),
            |j| j.id.clone(),
        )
    }

    /// Whether an unfinished job renders the dataset `dataset_id`: every job is looked at.
    pub fn dataset_in_use(&self, dataset_id: &str) -> Result<bool, StoreError> {
        for entry in self.jobs.iter() {
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
        for entry in self.datasets.iter() {
            let dataset: Dataset = decode(&entry?.1)?;
            if dataset.path.starts_with(uploads) {
                total = total.saturating_add(dataset.size_bytes);
            }
        }
        Ok(total)
    }

    pub fn frame(&self, job_id: &str, index: u32) -> Result<Option<FrameState>, StoreError> {
        decode_stored(self.frames.get(frame_key(job_id, index))?)
    }

    pub fn set_frame(
        &self,
        job_id: &str,
        index: u32,
        state: &FrameState,
    ) -> Result<(), StoreError> {
        self.frames
            .insert(frame_key(job_id, index), encode(state)?)?;
        Ok(())
    }

    /// The next frame to render: the first pending frame that is not `leased`, of the
    /// unfinished job with the highest priority, the oldest first among equals.
    pub fn next_task(
        &self,
        leased: &std::collections::HashSet<(String, u32)>,
    ) -> Result<Option<(Job, u32)>, StoreError> {
        let mut candidates: Vec<Job> = Vec::new();
        for entry in self.jobs.iter() {
            let (_, value) = entry?;
            let job: Job = decode(&value)?;
            if !job.state.is_terminal() {
                candidates.push(job);
            }
        }
        candidates.sort_by(|a, b| b.spec.priority.cmp(&a.spec.priority).then(a.id.cmp(&b.id)));
        for job in candidates {
            let mut prefix = job.id.as_bytes().to_vec();
            prefix.push(b'/');
            for entry in self.frames.scan_prefix(&prefix) {
                let (key, value) = entry?;
                if let FrameState::Pending { .. } = decode::<FrameState>(&value)? {
                    let index_bytes: [u8; 4] = key[prefix.len()..].try_into().unwrap_or([0; 4]);
                    let index = u32::from_be_bytes(index_bytes);
                    if !leased.contains(&(job.id.clone(), index)) {
                        return Ok(Some((job, index)));
                    }
                }
            }
        }
        Ok(None)
    }

    /// After a restart: jobs that were running go back to the queue (their finished frames
    /// stay finished). Returns how many.
    pub fn requeue_running(&self) -> Result<usize, StoreError> {
        let mut requeued = 0;
        for entry in self.jobs.iter() {
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
        self.leases.insert(lease.id.as_bytes(), encode(lease)?)?;
        Ok(())
    }

    pub fn lease(&self, id: &str) -> Result<Option<Lease>, StoreError> {
        decode_stored(self.leases.get(id.as_bytes())?)
    }

    pub fn remove_lease(&self, id: &str) -> Result<(), StoreError> {
        self.leases.remove(id.as_bytes())?;
        Ok(())
    }

    pub fn leases(&self) -> Result<Vec<Lease>, StoreError> {
        self.leases.iter().map(|entry| decode(&entry?.1)).collect()
    }

    /// Drops the leases held by embedded workers (found at start-up, they belonged to the
    /// worker threads of the previous process); returns how many there were.
    pub fn drop_embedded_leases(&self) -> Result<usize, StoreError> {
        let mut dropped = 0;
        for lease in self.leases()? {
            if lease.embedded {
                self.remove_lease(&lease.id)?;
                dropped += 1;
            }
        }
        Ok(dropped)
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
        for entry in self.frames.scan_prefix(&prefix) {
            let (_, value) = entry?;
            if let FrameState::Done(report) = decode::<FrameState>(&value)? {
                out.push(report);
            }
        }
        Ok(out)
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

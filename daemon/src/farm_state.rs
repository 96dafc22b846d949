//! What the metrics' gauges show, read from the daemon's state at each scrape so that they
//! cannot drift from it: the frames of unfinished jobs by priority (queued, leased, or held by
//! a paused job), the leases, the workers;
//! and the stores rebuilt after damage, which the stores count.
//! More `Daemon` methods.

use std::collections::{BTreeMap, HashSet};

use crate::error::DaemonError;
use crate::metrics::{FarmState, QueueDepth};
use crate::model::JobState;
use crate::service::Daemon;

impl Daemon {
    /// The state the gauges show: the frames of unfinished jobs by priority, queued or
    /// leased; the leases; the workers that can render.
    pub fn farm_state(&self) -> Result<FarmState, DaemonError> {
        // Under the scheduling lock: a frame is then either queued or leased, never both.
        let _scheduling = self.scheduling()?;
        let jobs = self.state.unfinished_jobs()?;
        let leases = self.state.leases()?;
        let mut leased_by_job: BTreeMap<&str, u64> = BTreeMap::new();
        for lease in &leases {
            *leased_by_job.entry(lease.job_id.as_str()).or_default() += 1;
        }
        let mut queue: BTreeMap<i32, QueueDepth> = BTreeMap::new();
        for job in &jobs {
            let pending = u64::from(job.frames_total.saturating_sub(job.frames_done));
            let leased = leased_by_job
                .get(job.id.as_str())
                .copied()
                .unwrap_or(0)
                .min(pending);
            let depth = queue.entry(job.spec.priority).or_default();
            if job.state == JobState::Paused {
                depth.paused += pending - leased;
            } else {
                depth.queued += pending - leased;
            }
            depth.leased += leased;
        }
        let remote_holders: HashSet<&str> = leases
            .iter()
            .filter(|lease| !lease.embedded)
            .map(|lease| lease.worker.as_str())
            .collect();
        let workers_connected = self
            .workers
            .connected_count(self.config.lease_timeout, remote_holders);
        Ok(FarmState {
            queue,
            leases_held: leases.len() as u64,
            workers_connected: workers_connected as u64,
            store_rebuilds: self.stores.rebuilds(),
            store_updates: self.stores.updates(),
            store_records_served: self.stores.records_served(),
        })
    }

    /// The daemon's metrics in Prometheus's text format ([`CONTENT_TYPE`]).
    pub fn metrics_text(&self) -> Result<String, DaemonError> {
        let state = self.farm_state()?;
        Ok(self.metrics.text(&state))
    }
}

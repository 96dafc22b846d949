//! Leases whose worker was lost: the embedded worker's when it exits (or died with the
//! previous daemon) and every lease not renewed in time. Each frame goes back to the queue
//! with an attempt counted; nothing runs out while the disk refuses writes, since no holder
//! could renew meanwhile.

use crate::error::DaemonError;
use crate::lease_record::Lease;
use crate::model::now_unix_ms;
use crate::service::Daemon;

impl Daemon {
    /// The embedded worker `worker` exited (`how`: its exit status): each frame it held
    /// counts a failed attempt (and a failed frame of its job for the worker) and goes back
    /// to the queue. Returns how many it held.
    pub fn embedded_worker_exited(&self, worker: &str, how: &str) -> Result<usize, DaemonError> {
        let _scheduling = self.scheduling()?;
        self.count_embedded_leases_locked(true, |lease| {
            (lease.worker == worker).then(|| {
                format!(
                    "worker {worker} died while rendering frame {} ({how})",
                    lease.index
                )
            })
        })
    }

    /// At start-up: the embedded worker died with the previous daemon, so each frame it held
    /// counts a failed attempt, as if it had exited now; the worker is not to blame for it.
    /// Returns how many it held.
    pub fn count_leases_of_previous_run(&self) -> Result<usize, DaemonError> {
        let _scheduling = self.scheduling()?;
        let counted = self.count_embedded_leases_locked(false, |lease| {
            Some(format!(
                "worker {} died while rendering frame {} (the daemon stopped)",
                lease.worker, lease.index
            ))
        })?;
        if counted > 0 {
            tracing::warn!(
                counted,
                "the previous run's embedded worker held frames: each counts a failed attempt"
            );
        }
        Ok(counted)
    }

    /// Removes the embedded leases for which `reason` gives a reason, counting an attempt each
    /// (and a failed frame for the worker when it is to `blame`).
    fn count_embedded_leases_locked(
        &self,
        blame: bool,
        reason: impl Fn(&Lease) -> Option<String>,
    ) -> Result<usize, DaemonError> {
        let mut counted = 0;
        for lease in self.state.leases()? {
            let Some(reason) = lease.embedded.then(|| reason(&lease)).flatten() else {
                continue;
            };
            self.state.remove_lease(&lease.id)?;
            if self.is_wanted_locked(&lease)? {
                tracing::warn!(job = %lease.job_id, frame = lease.index, %reason, "frame lost");
                self.metrics.frame_failed();
                self.count_failed_attempt_locked(&lease, &reason, blame)?;
                counted += 1;
            }
        }
        self.state.flush()?;
        Ok(counted)
    }

    /// Puts the frames of expired leases back in the queue, counting the attempts. Returns how
    /// many leases expired. The server's sweep calls it on a timer, so it also probes a disk
    /// that refused writes and ends the outage when it takes them again.
    pub fn expire_leases(&self) -> Result<usize, DaemonError> {
        let _scheduling = self.scheduling()?;
        if self.state.outage().is_some() && !self.end_outage_locked()? {
            return Ok(0);
        }
        self.expire_leases_locked()
    }

    /// Ends a disk outage if the disk takes writes again (see `StateDb::end_outage`); every
    /// lease is renewed, since no holder could renew it meanwhile. Returns whether it ended.
    fn end_outage_locked(&self) -> Result<bool, DaemonError> {
        match self.state.end_outage() {
            Ok(true) => {}
            Ok(false) => return Ok(false),
            Err(e) => {
                tracing::debug!(error = %e, "the disk still refuses writes");
                return Ok(false);
            }
        }
        let renewed = now_unix_ms() + self.lease_timeout_ms();
        for mut lease in self.state.leases()? {
            if lease.expires_unix_ms < renewed {
                lease.expires_unix_ms = renewed;
                self.state.put_lease(&lease)?;
            }
        }
        self.state.flush()?;
        self.work.notify();
        Ok(true)
    }

    pub(super) fn expire_leases_locked(&self) -> Result<usize, DaemonError> {
        // No holder can renew while the disk refuses writes: nothing runs out meanwhile.
        if self.state.outage().is_some() {
            return Ok(0);
        }
        let now = now_unix_ms();
        let mut expired = 0;
        for lease in self.state.leases()? {
            if lease.expires_unix_ms >= now {
                continue;
            }
            self.state.remove_lease(&lease.id)?;
            // A lease of an ended job is kept until it runs out, so that its holder's
            // heartbeat learns why to stop; its expiry counts nothing.
            if self.is_wanted_locked(&lease)? {
                tracing::warn!(
                    job = %lease.job_id,
                    frame = lease.index,
                    worker = %lease.worker,
                    "lease expired: the worker was lost; the frame goes back to the queue"
                );
                self.metrics.lease_expired();
                self.metrics.frame_failed();
                self.count_failed_attempt_locked(
                    &lease,
                    &format!(
                        "worker {} stopped renewing its lease (no heartbeat for {:?})",
                        lease.worker, self.config.lease_timeout
                    ),
                    true,
                )?;
                expired += 1;
            }
        }
        Ok(expired)
    }
}

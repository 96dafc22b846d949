//! Gives back a frame leased for a long-polling `LeaseFrame` request that was abandoned (the
//! worker hung up or stopped) before the answer went out, instead of leaving it leased until
//! the lease expires and counting a failed attempt.

use std::sync::Arc;

use crate::lease::FrameTask;
use crate::service::Daemon;

/// Where a lease request keeps the lease it is about to answer with, so that a request
/// abandoned meanwhile (the worker hung up or stopped while long-polling) gives the frame back
/// instead of leaving it leased until the lease expires and counting a failed attempt.
#[derive(Default)]
pub(super) struct LeaseSlot(std::sync::Mutex<(bool, Option<String>)>);

impl LeaseSlot {
    /// Keeps `task`'s lease for the answer, or releases it at once if the request is gone.
    pub(super) fn keep(&self, daemon: &Daemon, task: FrameTask) -> Option<FrameTask> {
        let Ok(mut slot) = self.0.lock() else {
            return Some(task);
        };
        if slot.0 {
            drop(slot);
            let _ = daemon.release_frame(&task.lease.id);
            return None;
        }
        slot.1 = Some(task.lease.id.clone());
        Some(task)
    }
}

/// Releases the slot's lease when the request future is dropped before answering.
pub(super) struct LeaseGuard {
    daemon: Arc<Daemon>,
    pub(super) slot: Arc<LeaseSlot>,
    armed: bool,
}

impl LeaseGuard {
    pub(super) fn new(daemon: Arc<Daemon>) -> Self {
        Self {
            daemon,
            slot: Arc::default(),
            armed: true,
        }
    }

    pub(super) fn disarm(mut self) {
        self.armed = false;
    }
}

impl Drop for LeaseGuard {
    fn drop(&mut self) {
        if !self.armed {
            return;
        }
        let lease = match self.slot.0.lock() {
            Ok(mut slot) => {
                slot.0 = true;
                slot.1.take()
            }
            Err(_) => None,
        };
        if let Some(lease_id) = lease {
            tracing::info!(lease = %lease_id, "the lease request was abandoned; frame given back");
            let _ = self.daemon.release_frame(&lease_id);
        }
    }
}

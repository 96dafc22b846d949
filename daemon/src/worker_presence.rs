//! Which workers can render now, for health checking: the embedded worker while its process
//! runs and has called in, remote workers while they wait for frames or were heard from
//! within the lease timeout.

use std::sync::{Mutex, MutexGuard};
use std::time::{Duration, Instant};

#[derive(Default)]
struct State {
    embedded_running: bool,
    embedded_called_in: bool,
    remote_polls: usize,
    remote_last_seen: Option<Instant>,
}

/// The workers the daemon has heard from; the gRPC layer and the supervisor of the embedded
/// worker keep it up to date.
#[derive(Default)]
pub struct WorkerPresence {
    state: Mutex<State>,
    /// Woken on every change, so that health follows a worker's arrival at once.
    changed: tokio::sync::Notify,
}

/// A remote worker's lease request in progress: the worker counts as present until it ends.
pub struct PollGuard<'a> {
    presence: &'a WorkerPresence,
    remote: bool,
}

impl Drop for PollGuard<'_> {
    fn drop(&mut self) {
        if self.remote {
            let mut state = self.presence.state();
            state.remote_polls = state.remote_polls.saturating_sub(1);
            state.remote_last_seen = Some(Instant::now());
        }
    }
}

impl WorkerPresence {
    fn state(&self) -> MutexGuard<'_, State> {
        // The state is a handful of plain values, consistent after any panic.
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Completes at the next change (or at once if one happened since the last wait).
    pub async fn changed(&self) {
        self.changed.notified().await
    }

    /// A new embedded worker process is running; it counts once it calls in.
    pub fn embedded_started(&self) {
        let mut state = self.state();
        state.embedded_running = true;
        state.embedded_called_in = false;
        self.changed.notify_one();
    }

    pub fn embedded_exited(&self) {
        let mut state = self.state();
        state.embedded_running = false;
        state.embedded_called_in = false;
        self.changed.notify_one();
    }

    /// A worker called the daemon (a heartbeat, a finished or failed frame).
    pub fn heard_from(&self, embedded: bool) {
        let mut state = self.state();
        if embedded {
            // A call still on its way from a process that has exited does not count.
            state.embedded_called_in = state.embedded_running;
        } else {
            state.remote_last_seen = Some(Instant::now());
        }
        self.changed.notify_one();
    }

    /// A worker asks for a frame; a remote one counts as present while it waits.
    pub fn poll(&self, embedded: bool) -> PollGuard<'_> {
        self.heard_from(embedded);
        if !embedded {
            self.state().remote_polls += 1;
        }
        PollGuard {
            presence: self,
            remote: !embedded,
        }
    }

    /// Whether some worker can render: the embedded one is up, or a remote one waits for
    /// work or was heard from within `remote_timeout`.
    pub fn can_render(&self, remote_timeout: Duration) -> bool {
        let state = self.state();
        (state.embedded_running && state.embedded_called_in)
            || state.remote_polls > 0
            || state
                .remote_last_seen
                .is_some_and(|seen| seen.elapsed() <= remote_timeout)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_embedded_worker_counts_from_its_first_call_until_it_exits() {
        let presence = WorkerPresence::default();
        let timeout = Duration::from_secs(60);
        assert!(!presence.can_render(timeout));
        presence.embedded_started();
        assert!(
            !presence.can_render(timeout),
            "started but not yet connected"
        );
        presence.heard_from(true);
        assert!(presence.can_render(timeout));
        presence.embedded_exited();
        assert!(!presence.can_render(timeout));
        presence.heard_from(true);
        assert!(
            !presence.can_render(timeout),
            "a late call of the dead process"
        );
    }

    #[test]
    fn a_remote_worker_counts_while_it_polls_and_within_the_timeout_after() {
        let presence = WorkerPresence::default();
        let timeout = Duration::from_millis(100);
        let poll = presence.poll(false);
        std::thread::sleep(timeout * 2);
        assert!(presence.can_render(timeout), "waiting for work");
        drop(poll);
        assert!(presence.can_render(timeout));
        std::thread::sleep(timeout * 2);
        assert!(
            !presence.can_render(timeout),
            "not heard from within the timeout"
        );
    }
}

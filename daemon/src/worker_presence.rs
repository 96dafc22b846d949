//! Which workers can render now, for health checking: the embedded worker while its process
//! runs and has called in, remote workers while they wait for frames or were heard from
//! within the lease timeout; and how many there are, for the metrics.

use std::collections::{HashMap, HashSet};
use std::sync::{Mutex, MutexGuard};
use std::time::{Duration, Instant};

#[derive(Default)]
struct State {
    embedded_running: bool,
    embedded_called_in: bool,
    remote_polls: usize,
    remote_last_seen: Option<Instant>,
    /// When each remote worker, by name, last asked for a frame.
    remote_named: HashMap<String, Instant>,
}

/// A remote worker not heard of for this long is forgotten (it is long past any lease
/// timeout), so that names of workers that came and went do not pile up.
const FORGET_AFTER: Duration = Duration::from_secs(3600);

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

    /// The remote worker `name` asks for a frame.
    pub fn remote_named(&self, name: &str) {
        let now = Instant::now();
        let mut state = self.state();
        state
            .remote_named
            .retain(|_, seen| now.duration_since(*seen) <= FORGET_AFTER);
        state.remote_named.insert(name.to_owned(), now);
    }

    /// How many workers can render: the embedded one once it has called in, and the remote
    /// ones that hold a lease (`remote_holders`, by name) or asked for a frame within
    /// `remote_timeout`.
    pub fn connected<'a>(
        &self,
        remote_timeout: Duration,
        remote_holders: impl IntoIterator<Item = &'a str>,
    ) -> usize {
        let state = self.state();
        let mut remote: HashSet<&str> = remote_holders.into_iter().collect();
        remote.extend(
            state
                .remote_named
                .iter()
                .filter(|(_, seen)| seen.elapsed() <= remote_timeout)
                .map(|(name, _)| name.as_str()),
        );
        let embedded = state.embedded_running && state.embedded_called_in;
        usize::from(embedded) + remote.len()
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
    fn workers_are_counted_by_name_while_they_ask_for_frames_or_hold_leases() {
        let presence = WorkerPresence::default();
        let timeout = Duration::from_millis(100);
        assert_eq!(presence.connected(timeout, []), 0);
        presence.embedded_started();
        presence.heard_from(true);
        presence.remote_named("a");
        presence.remote_named("b");
        presence.remote_named("a");
        assert_eq!(presence.connected(timeout, ["a"]), 3);
        std::thread::sleep(timeout * 2);
        assert_eq!(
            presence.connected(timeout, ["b"]),
            2,
            "a is no longer heard from; b holds a lease"
        );
        presence.embedded_exited();
        assert_eq!(presence.connected(timeout, []), 0);
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

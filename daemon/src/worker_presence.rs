//! Which workers can render now, for health checking: the embedded worker while its process
//! runs and has called in, remote workers while they wait for frames or were heard from
//! within the lease timeout. Each worker that asked for frames is also known by name with the
//! capabilities it sent, so that a job no connected worker can render says why, and counted,
//! for the metrics.

use std::collections::{HashMap, HashSet};
use std::sync::{Mutex, MutexGuard};
use std::time::{Duration, Instant};

use crate::capabilities::WorkerCapabilities;

#[derive(Default)]
struct State {
    embedded_running: bool,
    embedded_called_in: bool,
    remote_polls: usize,
    remote_last_seen: Option<Instant>,
    /// The workers that asked for frames, by name.
    named: HashMap<String, Named>,
}

/// A worker known by name: what it last said it can do, and when it was last heard from.
struct Named {
    embedded: bool,
    capabilities: WorkerCapabilities,
    polls: usize,
    last_seen: Instant,
}

/// A worker connected now, as it last asked for frames.
#[derive(Debug, Clone, PartialEq)]
pub struct ConnectedWorker {
    pub name: String,
    pub embedded: bool,
    pub capabilities: WorkerCapabilities,
}

/// Names not heard from for this many times the timeout are forgotten.
const FORGET_AFTER_TIMEOUTS: u32 = 10;

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
    name: Option<String>,
}

impl Drop for PollGuard<'_> {
    fn drop(&mut self) {
        let mut state = self.presence.state();
        let now = Instant::now();
        if self.remote {
            state.remote_polls = state.remote_polls.saturating_sub(1);
            state.remote_last_seen = Some(now);
        }
        if let Some(named) = self.name.as_ref().and_then(|n| state.named.get_mut(n)) {
            named.polls = named.polls.saturating_sub(1);
            named.last_seen = now;
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
            name: None,
        }
    }

    /// The worker `name` asks for a frame, saying what it can render: as [`Self::poll`], and
    /// it is known by name, connected while it waits and within `timeout` after.
    pub fn poll_named(
        &self,
        embedded: bool,
        name: &str,
        capabilities: WorkerCapabilities,
        timeout: Duration,
    ) -> PollGuard<'_> {
        let mut guard = self.poll(embedded);
        let mut state = self.state();
        let now = Instant::now();
        let forget = timeout * FORGET_AFTER_TIMEOUTS;
        state
            .named
            .retain(|_, n| n.polls > 0 || now.duration_since(n.last_seen) <= forget);
        let named = state.named.entry(name.to_owned()).or_insert(Named {
            embedded,
            capabilities: WorkerCapabilities::default(),
            polls: 0,
            last_seen: now,
        });
        named.embedded = embedded;
        named.capabilities = capabilities;
        named.polls += 1;
        named.last_seen = now;
        guard.name = Some(name.to_owned());
        guard
    }

    /// The worker `name` called about a frame it holds (a heartbeat).
    pub fn heard_from_named(&self, name: &str) {
        if let Some(named) = self.state().named.get_mut(name) {
            named.last_seen = Instant::now();
        }
    }

    /// The workers known by name that are connected now: waiting for a frame, or heard from
    /// within `timeout` (the embedded one only while its process runs), by name.
    pub fn connected(&self, timeout: Duration) -> Vec<ConnectedWorker> {
        let state = self.state();
        let embedded_up = state.embedded_running && state.embedded_called_in;
        let mut connected: Vec<ConnectedWorker> = state
            .named
            .iter()
            .filter(|(_, n)| {
                let recent = n.polls > 0 || n.last_seen.elapsed() <= timeout;
                recent && (!n.embedded || embedded_up)
            })
            .map(|(name, n)| ConnectedWorker {
                name: name.clone(),
                embedded: n.embedded,
                capabilities: n.capabilities.clone(),
            })
            .collect();
        connected.sort_by(|a, b| a.name.cmp(&b.name));
        connected
    }

    /// How many workers are connected: those of [`Self::connected`] and the remote ones that
    /// hold a lease (`remote_holders`, by name) while rendering a long frame.
    pub fn connected_count<'a>(
        &self,
        timeout: Duration,
        remote_holders: impl IntoIterator<Item = &'a str>,
    ) -> usize {
        let mut names: HashSet<String> = self
            .connected(timeout)
            .into_iter()
            .map(|worker| worker.name)
            .collect();
        names.extend(remote_holders.into_iter().map(str::to_owned));
        names.len()
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
        assert_eq!(presence.connected_count(timeout, []), 0);
        presence.embedded_started();
        presence.heard_from(true);
        drop(presence.poll_named(true, "embedded", Default::default(), timeout));
        drop(presence.poll_named(false, "a", Default::default(), timeout));
        drop(presence.poll_named(false, "b", Default::default(), timeout));
        drop(presence.poll_named(false, "a", Default::default(), timeout));
        assert_eq!(presence.connected_count(timeout, ["a"]), 3);
        std::thread::sleep(timeout * 2);
        presence.heard_from_named("embedded");
        assert_eq!(
            presence.connected_count(timeout, ["b"]),
            2,
            "the embedded worker sent a heartbeat, b holds a lease, a is no longer heard from"
        );
        presence.embedded_exited();
        assert_eq!(presence.connected_count(timeout, []), 0);
    }

    #[test]
    fn named_workers_are_connected_while_they_poll_and_within_the_timeout_after() {
        let presence = WorkerPresence::default();
        let timeout = Duration::from_millis(100);
        let tagged = WorkerCapabilities {
            tags: ["a".to_string()].into(),
            ..WorkerCapabilities::default()
        };
        let poll = presence.poll_named(false, "w1", tagged.clone(), timeout);
        let embedded = presence.poll_named(true, "embedded", Default::default(), timeout);
        drop(embedded);
        let names = |p: &WorkerPresence| -> Vec<String> {
            p.connected(timeout).into_iter().map(|w| w.name).collect()
        };
        assert_eq!(
            names(&presence),
            vec!["w1"],
            "the embedded process is not running"
        );
        presence.embedded_started();
        presence.heard_from(true);
        assert_eq!(names(&presence), vec!["embedded", "w1"]);
        assert_eq!(presence.connected(timeout)[1].capabilities, tagged);
        std::thread::sleep(timeout * 2);
        assert_eq!(names(&presence), vec!["w1"], "w1 still waits for work");
        drop(poll);
        assert_eq!(names(&presence), vec!["w1"]);
        std::thread::sleep(timeout * 2);
        assert!(names(&presence).is_empty());
        // A heartbeat keeps a worker rendering a long frame connected.
        drop(presence.poll_named(false, "w2", Default::default(), timeout));
        std::thread::sleep(timeout * 2);
        presence.heard_from_named("w2");
        assert_eq!(names(&presence), vec!["w2"]);
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

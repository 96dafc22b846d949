//! Waits that double from a first one to a cap, and start again from the first.

use std::time::Duration;

/// A wait that doubles each time it is taken, up to its cap.
pub(crate) struct Backoff {
    wait: Duration,
    first: Duration,
    max: Duration,
}

impl Backoff {
    /// Between failed calls to the daemon: 250 ms doubling to 5 s.
    pub(crate) fn calls() -> Self {
        Self::from_to(Duration::from_millis(250), Duration::from_secs(5))
    }

    /// Between frames handed back one after another because the daemon builds their store (the
    /// daemon holds such frames, so this is for a frame leased as its build began): short at
    /// first, so a store that becomes ready soon (a camera-first part) costs its frames little
    /// idle time, and longer while a large build goes on.
    pub(crate) fn store_building() -> Self {
        Self::from_to(Duration::from_millis(100), Duration::from_secs(2))
    }

    fn from_to(first: Duration, max: Duration) -> Self {
        Self {
            wait: first,
            first,
            max,
        }
    }

    /// The wait to take now; the next one is twice as long, up to the cap.
    pub(crate) fn next(&mut self) -> Duration {
        let wait = self.wait;
        self.wait = (self.wait * 2).min(self.max);
        wait
    }

    pub(crate) fn reset(&mut self) {
        self.wait = self.first;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_store_building_wait_doubles_from_100_ms_to_2_s_and_starts_again_when_reset() {
        let mut backoff = Backoff::store_building();
        let waits: Vec<u128> = (0..7).map(|_| backoff.next().as_millis()).collect();
        assert_eq!(waits, [100, 200, 400, 800, 1600, 2000, 2000]);
        backoff.reset();
        assert_eq!(backoff.next(), Duration::from_millis(100));
    }

    #[test]
    fn a_failed_call_wait_doubles_from_250_ms_to_5_s() {
        let mut backoff = Backoff::calls();
        let waits: Vec<u128> = (0..6).map(|_| backoff.next().as_millis()).collect();
        assert_eq!(waits, [250, 500, 1000, 2000, 4000, 5000]);
    }
}

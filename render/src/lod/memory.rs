//! `MemoryMeter`: the builder's buffers reserve their bytes here before they allocate, so the
//! budget holds whatever the input size, and the peak can be reported and tested.

use std::sync::{Condvar, Mutex, MutexGuard};
use std::time::Duration;

use super::error::LodError;

#[derive(Debug)]
pub struct MemoryMeter {
    budget: u64,
    state: Mutex<MeterState>,
    freed: Condvar,
}

#[derive(Debug, Default)]
struct MeterState {
    used: u64,
    peak: u64,
    /// Bytes held for the whole build; no single reservation can ever use them.
    pinned: u64,
}

impl MeterState {
    /// Takes `bytes` if they fit beside what is held within `budget`.
    fn take_now(
        &mut self,
        budget: u64,
        bytes: u64,
        what: &'static str,
    ) -> Result<&mut Self, LodError> {
        if self.used + bytes > budget {
            return Err(LodError::BudgetTooSmall {
                budget: budget - self.used,
                needed: bytes,
                what,
            });
        }
        self.used += bytes;
        self.peak = self.peak.max(self.used);
        Ok(self)
    }
}

/// Bytes held under the budget until dropped.
#[derive(Debug)]
pub struct Reservation<'a> {
    meter: &'a MemoryMeter,
    bytes: u64,
}

impl MemoryMeter {
    pub fn new(budget: u64) -> Self {
        Self {
            budget,
            state: Mutex::new(MeterState::default()),
            freed: Condvar::new(),
        }
    }

    pub fn budget(&self) -> u64 {
        self.budget
    }

    /// The most bytes reserved at once so far.
    pub fn peak(&self) -> u64 {
        self.lock().peak
    }

    fn lock(&self) -> MutexGuard<'_, MeterState> {
        // A panic elsewhere cannot leave the counters half-updated: each update is one statement.
        self.state
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner())
    }

    /// The most one reservation can ever get: the budget less what is pinned.
    pub fn largest_possible(&self) -> u64 {
        self.budget - self.lock().pinned
    }

    fn check(&self, bytes: u64, what: &'static str) -> Result<(), LodError> {
        let largest = self.largest_possible();
        if bytes > largest {
            return Err(LodError::BudgetTooSmall {
                budget: largest,
                needed: bytes,
                what,
            });
        }
        Ok(())
    }

    /// Reserves `bytes` for as long as the meter lives (statistics kept for the whole build).
    pub fn pin(&self, bytes: u64, what: &'static str) -> Result<(), LodError> {
        self.lock().take_now(self.budget, bytes, what)?.pinned += bytes;
        Ok(())
    }

    /// Reserves `bytes` now, or fails if they do not fit beside what is already held.
    pub fn try_reserve(&self, bytes: u64, what: &'static str) -> Result<Reservation<'_>, LodError> {
        self.check(bytes, what)?;
        self.lock().take_now(self.budget, bytes, what)?;
        Ok(Reservation { meter: self, bytes })
    }

    /// Reserves `bytes`, waiting for other work to release enough; fails only if they exceed
    /// the whole budget. Waiting cannot deadlock: every holder releases without reserving more.
    pub fn reserve(&self, bytes: u64, what: &'static str) -> Result<Reservation<'_>, LodError> {
        self.check(bytes, what)?;
        let mut state = self.lock();
        while state.used + bytes > self.budget {
            state = self
                .freed
                .wait(state)
                .unwrap_or_else(|poisoned| poisoned.into_inner());
        }
        state.used += bytes;
        state.peak = state.peak.max(state.used);
        Ok(Reservation { meter: self, bytes })
    }
}

impl MemoryMeter {
    /// Reserves `bytes` if they fit now or once other work releases enough within `timeout`;
    /// `None` if they still do not fit then, so that the caller can do other work meanwhile.
    /// Fails only if they exceed the whole budget.
    pub fn reserve_within(
        &self,
        bytes: u64,
        what: &'static str,
        timeout: Duration,
    ) -> Result<Option<Reservation<'_>>, LodError> {
        self.check(bytes, what)?;
        let mut state = self.lock();
        if state.used + bytes > self.budget {
            state = self
                .freed
                .wait_timeout(state, timeout)
                .map(|(state, _)| state)
                .unwrap_or_else(|poisoned| poisoned.into_inner().0);
        }
        if state.used + bytes > self.budget {
            return Ok(None);
        }
        state.used += bytes;
        state.peak = state.peak.max(state.used);
        Ok(Some(Reservation { meter: self, bytes }))
    }

    /// Waits until a reservation is released, or `timeout` passes.
    pub fn wait_for_release(&self, timeout: Duration) {
        let state = self.lock();
        drop(self.freed.wait_timeout(state, timeout));
    }
}

impl Reservation<'_> {
    pub fn bytes(&self) -> u64 {
        self.bytes
    }

    /// Takes `other`'s bytes into this reservation, held until this one is dropped.
    pub fn absorb(&mut self, mut other: Reservation<'_>) {
        debug_assert!(std::ptr::eq(self.meter, other.meter));
        self.bytes += std::mem::take(&mut other.bytes);
    }

    /// Releases what this reservation holds beyond `bytes`.
    pub fn shrink_to(&mut self, bytes: u64) {
        if bytes >= self.bytes {
            return;
        }
        let released = self.bytes - bytes;
        self.bytes = bytes;
        self.meter.lock().used -= released;
        self.meter.freed.notify_all();
    }
}

impl Drop for Reservation<'_> {
    fn drop(&mut self) {
        let mut state = self.meter.lock();
        state.used -= self.bytes;
        drop(state);
        self.meter.freed.notify_all();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reservations_count_towards_the_peak_and_are_released() {
        let meter = MemoryMeter::new(100);
        let a = meter.try_reserve(60, "a").expect("fits");
        assert!(meter.try_reserve(50, "b").is_err());
        drop(a);
        let _b = meter.try_reserve(50, "b").expect("fits after release");
        assert_eq!(meter.peak(), 60);
        assert!(matches!(
            meter.reserve(101, "c"),
            Err(LodError::BudgetTooSmall { needed: 101, .. })
        ));
    }

    /// A reservation that does not fit waits at most its timeout, and gets the bytes once
    /// another thread releases them meanwhile.
    #[test]
    fn reserving_within_a_timeout_waits_for_a_release() {
        let meter = MemoryMeter::new(100);
        let held = meter.try_reserve(80, "a").expect("fits");
        let none = meter.reserve_within(30, "b", Duration::from_millis(20));
        assert!(matches!(none, Ok(None)));
        std::thread::scope(|scope| {
            scope.spawn(|| {
                std::thread::sleep(Duration::from_millis(20));
                drop(held);
            });
            let mut got = None;
            while got.is_none() {
                got = meter
                    .reserve_within(30, "b", Duration::from_secs(5))
                    .expect("within the budget");
            }
            assert_eq!(got.map(|r| r.bytes()), Some(30));
        });
        assert!(meter.reserve_within(101, "c", Duration::ZERO).is_err());
    }
}

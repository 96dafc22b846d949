//! `StoreBuildGate`: what tests hold store builds at.

use std::sync::{Arc, Mutex};

/// Holds every store build until opened, at its start or at its end before its store is
/// ready: what tests use to look at a daemon while a build is under way, without a build
/// slow enough to race.
#[derive(Clone, Default)]
pub struct StoreBuildGate(Arc<(Mutex<bool>, std::sync::Condvar)>);

impl std::fmt::Debug for StoreBuildGate {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let open = *self.0 .0.lock().unwrap_or_else(|e| e.into_inner());
        f.debug_struct("StoreBuildGate")
            .field("open", &open)
            .finish()
    }
}

impl StoreBuildGate {
    /// A closed gate: builds wait at it.
    pub fn closed() -> Self {
        Self::default()
    }

    /// Lets every build waiting, and every later one, go on.
    pub fn open(&self) {
        let (open, opened) = &*self.0;
        *open.lock().unwrap_or_else(|e| e.into_inner()) = true;
        opened.notify_all();
    }

    pub(super) fn wait(&self) {
        let (open, opened) = &*self.0;
        let mut is_open = open.lock().unwrap_or_else(|e| e.into_inner());
        while !*is_open {
            is_open = opened.wait(is_open).unwrap_or_else(|e| e.into_inner());
        }
    }
}

//! Counters of what the remote layer fetched, for reports and for tests that a read stayed small.

use std::sync::atomic::{AtomicU64, Ordering};

/// Requests issued and payload bytes received; retries inside object_store are not seen here.
#[derive(Debug, Default)]
pub(crate) struct FetchCounters {
    requests: AtomicU64,
    bytes: AtomicU64,
}

/// A snapshot of the counters.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct FetchCounts {
    /// Requests issued: a HEAD per open, a GET per coalesced range, one per listing.
    pub requests: u64,
    /// Payload bytes received.
    pub bytes: u64,
}

impl FetchCounters {
    pub(crate) fn add(&self, requests: u64, bytes: u64) {
        self.requests.fetch_add(requests, Ordering::Relaxed);
        self.bytes.fetch_add(bytes, Ordering::Relaxed);
    }

    pub(crate) fn snapshot(&self) -> FetchCounts {
        FetchCounts {
            requests: self.requests.load(Ordering::Relaxed),
            bytes: self.bytes.load(Ordering::Relaxed),
        }
    }
}

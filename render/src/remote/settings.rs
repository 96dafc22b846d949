//! `RemoteSettings`: every timeout, retry and coalescing number of the remote layer, with its
//! default, in one place.

use std::time::Duration;

/// How the remote layer talks to object storage and HTTP servers.
#[derive(Clone, Debug, PartialEq)]
pub struct RemoteSettings {
    /// Longest wait for a connection to open.
    pub connect_timeout: Duration,
    /// Longest one request may take, its body included; a stalled request is retried.
    pub request_timeout: Duration,
    /// Retries of a failed or stalled request before its error is returned.
    pub max_retries: usize,
    /// No retry starts later than this after the first attempt.
    pub retry_timeout: Duration,
    /// The first backoff between retries; it grows exponentially with jitter.
    pub initial_backoff: Duration,
    /// The longest backoff between retries.
    pub max_backoff: Duration,
    /// Redirects one request follows, each within the rule of [`super::RemoteClient`], before
    /// it fails.
    pub max_redirects: usize,
    /// Bound on one whole operation (an open, a set of ranges, a listing), whatever the
    /// retries do, so that a caller always gets an answer.
    pub operation_deadline: Duration,
    /// Ranges closer than this are fetched as one request.
    pub coalesce_gap: u64,
    /// Ranges of a sparse read (a preview's sampled records, tens of bytes each) closer than
    /// this are fetched as one request. Far below `coalesce_gap`, which would fetch a whole
    /// tile between its chunk starts: about what one request costs on priced object storage
    /// in bytes sent out, so a merge never costs more than the request it saves.
    pub sparse_gap: u64,
    /// A coalesced request grows no larger than this.
    pub max_coalesced_bytes: u64,
    /// Requests of one `read_ranges` in flight at once.
    pub parallel_requests: usize,
    /// The most bytes one read may return, checked before anything is allocated.
    pub max_read_bytes: u64,
    /// The most objects a listing returns before it is refused as too large.
    pub max_listed_objects: usize,
    /// The size of each part of a multipart upload (S3 takes 5 MiB to 5 GiB but for the
    /// last part).
    pub upload_part_bytes: usize,
    /// Parts of one upload sent at once; an upload holds at most this many parts in memory
    /// and one more being filled.
    pub upload_parts_in_flight: usize,
}

impl Default for RemoteSettings {
    fn default() -> Self {
        Self {
            connect_timeout: Duration::from_secs(5),
            request_timeout: Duration::from_secs(30),
            max_retries: 4,
            retry_timeout: Duration::from_secs(60),
            initial_backoff: Duration::from_millis(100),
            max_backoff: Duration::from_secs(5),
            max_redirects: 5,
            operation_deadline: Duration::from_secs(180),
            coalesce_gap: 1024 * 1024,
            sparse_gap: 4 * 1024,
            max_coalesced_bytes: 64 * 1024 * 1024,
            parallel_requests: 8,
            max_read_bytes: 1024 * 1024 * 1024,
            max_listed_objects: 100_000,
            upload_part_bytes: 8 * 1024 * 1024,
            upload_parts_in_flight: 4,
        }
    }
}

impl RemoteSettings {
    pub(crate) fn retry_config(&self) -> object_store::RetryConfig {
        object_store::RetryConfig {
            backoff: object_store::BackoffConfig {
                init_backoff: self.initial_backoff,
                max_backoff: self.max_backoff,
                base: 2.0,
            },
            max_retries: self.max_retries,
            retry_timeout: self.retry_timeout,
        }
    }

    /// The HTTP client's settings, as the configuration keys object_store's builders take, so
    /// that they add to what a builder reads from the environment instead of replacing it.
    pub(crate) fn client_config(&self) -> Vec<(object_store::ClientConfigKey, String)> {
        use object_store::ClientConfigKey;
        vec![
            (
                ClientConfigKey::ConnectTimeout,
                format!("{}ms", self.connect_timeout.as_millis()),
            ),
            (
                ClientConfigKey::Timeout,
                format!("{}ms", self.request_timeout.as_millis()),
            ),
        ]
    }
}

//! The stored record of a frame lease: which worker holds which frame of which job, until
//! when, and for a preview the version of the preview sample it is drawn from at least. The
//! state database keeps these; `lease` decides when they are made, renewed and dropped.

use rand::Rng;
use serde::{Deserialize, Serialize};

use crate::model::JobId;

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Lease {
    /// Random and unguessable ([`Lease::new_id`]): a worker's calls on its frame carry it, so
    /// only the worker it was handed to can renew, fail or complete the frame.
    pub id: String,
    pub job_id: JobId,
    pub index: u32,
    pub worker: String,
    /// Held by a worker thread of the daemon itself.
    pub embedded: bool,
    pub expires_unix_ms: i64,
    /// Set on a lease for a preview: the version of the preview sample the daemon's build was
    /// at when the frame was leased, which the preview handed in under it is kept with.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub preview_version: Option<u32>,
}

impl Lease {
    /// A new lease id: 128 bits from a cryptographically secure generator, so ids can be
    /// neither guessed nor derived from one another.
    pub fn new_id() -> String {
        let bytes: [u8; 16] = rand::rng().random();
        format!("lease-{}", crate::model::hex(&bytes))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lease_ids_are_random_and_fit_the_id_bound() {
        let ids: std::collections::HashSet<String> = (0..1000).map(|_| Lease::new_id()).collect();
        assert_eq!(ids.len(), 1000);
        for id in &ids {
            assert_eq!(id.len(), "lease-".len() + 32);
            assert!(id.len() <= crate::limits::MAX_ID_BYTES);
        }
    }
}

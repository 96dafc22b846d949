//! The stored record of a frame lease: which worker holds which frame of which job, until
//! when. The store keeps these; `lease` decides when they are made, renewed and dropped.

use serde::{Deserialize, Serialize};

use crate::model::JobId;

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Lease {
    pub id: String,
    pub job_id: JobId,
    pub index: u32,
    pub worker: String,
    /// Held by a worker thread of the daemon itself.
    pub embedded: bool,
    pub expires_unix_ms: i64,
}

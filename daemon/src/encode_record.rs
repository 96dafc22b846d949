//! The stored record of a job's video as it is made: who holds its encode lease, until when,
//! the attempts that failed, and the stored video's size. The job's record keeps it;
//! `encodes` decides when it changes.

use serde::{Deserialize, Serialize};

/// A job's video as it goes: who holds its encode, how many attempts failed, and once it is
/// stored, its size.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct EncodeState {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lease: Option<EncodeLease>,
    #[serde(default)]
    pub failed_attempts: u32,
    /// Set once the video is stored.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub video_size_bytes: Option<u64>,
}

/// The worker making a job's video, until when.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct EncodeLease {
    /// Random, as a frame lease's id (`Lease::new_id`); its holder's credential.
    pub id: String,
    pub worker: String,
    pub embedded: bool,
    pub expires_unix_ms: i64,
    /// When it was leased, for the time a video takes; 0 in records stored without it.
    #[serde(default)]
    pub leased_unix_ms: i64,
}

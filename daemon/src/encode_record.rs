//! The stored record of a job's video as it is made: who holds its encode lease, until when,
//! the attempts that failed, and the stored video's size; the same of its preview video. The job's record keeps it;
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
    /// The preview video of a job with previews, made of them once every frame has one.
    #[serde(default, skip_serializing_if = "PreviewVideoState::is_unstarted")]
    pub preview: PreviewVideoState,
}

/// A job's preview video as it goes; its failures never fail the job, they only end it.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct PreviewVideoState {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lease: Option<EncodeLease>,
    #[serde(default)]
    pub failed_attempts: u32,
    /// Set once the preview video is stored.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub video_size_bytes: Option<u64>,
}

impl PreviewVideoState {
    /// Nothing happened to it yet: what records stored before preview videos read as.
    pub fn is_unstarted(&self) -> bool {
        *self == Self::default()
    }
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

/// Which of a job's videos an encode lease makes: the final one, of its final frames, or the
/// preview one, of its previews.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum VideoKind {
    Final,
    Preview,
}

impl VideoKind {
    /// How logs and errors call it.
    pub fn name(self) -> &'static str {
        match self {
            VideoKind::Final => "video",
            VideoKind::Preview => "preview video",
        }
    }
}

impl EncodeState {
    /// The lease of the `kind` video.
    pub fn lease_of(&self, kind: VideoKind) -> Option<&EncodeLease> {
        match kind {
            VideoKind::Final => self.lease.as_ref(),
            VideoKind::Preview => self.preview.lease.as_ref(),
        }
    }

    /// The lease of the `kind` video, to change.
    pub fn lease_of_mut(&mut self, kind: VideoKind) -> &mut Option<EncodeLease> {
        match kind {
            VideoKind::Final => &mut self.lease,
            VideoKind::Preview => &mut self.preview.lease,
        }
    }

    /// The held leases and the video each makes.
    pub fn leases(&self) -> impl Iterator<Item = (VideoKind, &EncodeLease)> {
        [VideoKind::Final, VideoKind::Preview]
            .into_iter()
            .filter_map(|kind| self.lease_of(kind).map(|lease| (kind, lease)))
    }

    /// The failed attempts of the `kind` video.
    pub fn failed_attempts_of(&self, kind: VideoKind) -> u32 {
        match kind {
            VideoKind::Final => self.failed_attempts,
            VideoKind::Preview => self.preview.failed_attempts,
        }
    }
}

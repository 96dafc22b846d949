//! The stored record of a job's videos as they are made, the final one and the preview one
//! alike: who holds its encode lease, until when, the attempts that failed, and the stored
//! video's size. The job's record keeps it; `encodes` decides when it changes.

use serde::{Deserialize, Serialize};

/// A job's videos as they go: the final one, and the preview one of a job with previews.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct EncodeState {
    /// The final video; its fields stand at the top of the record, as they did before
    /// preview videos.
    #[serde(flatten)]
    pub video: VideoProgress,
    /// The preview video, made of the previews once every frame has one; its failures never
    /// fail the job, they only end it.
    #[serde(default, skip_serializing_if = "VideoProgress::is_unstarted")]
    pub preview: VideoProgress,
}

/// One video as it goes: who holds its encode, how many attempts failed, and once it is
/// stored, its size.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct VideoProgress {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lease: Option<EncodeLease>,
    #[serde(default)]
    pub failed_attempts: u32,
    /// Set once the video is stored.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub video_size_bytes: Option<u64>,
}

impl VideoProgress {
    /// Nothing happened to it yet: what records stored before preview videos read as.
    pub fn is_unstarted(&self) -> bool {
        *self == Self::default()
    }

    /// Its video is stored, `size_bytes` long; the lease that made it ends.
    pub fn stored(&mut self, size_bytes: u64) {
        self.lease = None;
        self.video_size_bytes = Some(size_bytes);
    }

    /// Its lease ended without a video, after `failed_attempts` failed attempts in all.
    pub fn failed(&mut self, failed_attempts: u32) {
        self.lease = None;
        self.failed_attempts = failed_attempts;
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
    /// The `kind` video.
    pub fn of(&self, kind: VideoKind) -> &VideoProgress {
        match kind {
            VideoKind::Final => &self.video,
            VideoKind::Preview => &self.preview,
        }
    }

    /// The `kind` video, to change.
    pub fn of_mut(&mut self, kind: VideoKind) -> &mut VideoProgress {
        match kind {
            VideoKind::Final => &mut self.video,
            VideoKind::Preview => &mut self.preview,
        }
    }

    /// The held leases and the video each makes.
    pub fn leases(&self) -> impl Iterator<Item = (VideoKind, &EncodeLease)> {
        [VideoKind::Final, VideoKind::Preview]
            .into_iter()
            .filter_map(|kind| self.of(kind).lease.as_ref().map(|lease| (kind, lease)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The final video's fields stay at the top of the stored record, beside `preview`, so
    /// records stored before preview videos read as they were written.
    #[test]
    fn the_final_video_is_stored_at_the_top_of_the_record() {
        let stored = r#"{"failed_attempts":2,"video_size_bytes":4096}"#;
        let state: EncodeState = serde_json::from_str(stored).expect("an older record reads");
        assert_eq!(state.video.failed_attempts, 2);
        assert_eq!(state.video.video_size_bytes, Some(4096));
        assert!(state.preview.is_unstarted());
        assert_eq!(serde_json::to_string(&state).expect("encodes"), stored);

        let mut both = state;
        both.preview.failed(1);
        let written = serde_json::to_value(&both).expect("encodes");
        assert_eq!(written["video_size_bytes"], 4096);
        assert_eq!(written["preview"]["failed_attempts"], 1);
    }
}

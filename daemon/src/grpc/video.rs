//! A job's video and its encode task, on the wire: checked on the way in with the render
//! crate's one set of containers, codecs, ranges and defaults.

use pointfarm_proto::v1 as pb;
use pointfarm_render::encode::video::{
    VideoCodec, VideoContainer, VideoPreset, VideoSettings, DEFAULT_VIDEO_FPS,
    DEFAULT_VIDEO_PRESET, DEFAULT_VIDEO_QUALITY,
};

use crate::encodes::EncodeTask;
use crate::error::DaemonError;

fn invalid(field: &str, message: impl Into<String>) -> DaemonError {
    DaemonError::invalid(field, message)
}

/// The video a submission asks for, checked; None when it asks for none. Each refusal names
/// its field (`video.container`, `video.codec`, `video.fps`, `video.quality`,
/// `video.preset`).
pub fn video_settings(spec: Option<&pb::VideoSpec>) -> Result<Option<VideoSettings>, DaemonError> {
    let Some(spec) = spec else {
        return Ok(None);
    };
    let refused = |e: pointfarm_render::encode::video::VideoError| {
        invalid(&format!("video.{}", e.field()), e.to_string())
    };
    if spec.container.is_empty() {
        return Err(invalid(
            "video.container",
            "is required: mp4, mov, mkv, webm or gif",
        ));
    }
    let container = VideoContainer::from_name(&spec.container).map_err(refused)?;
    let codec = match spec.codec.as_str() {
        "" => None,
        name => Some(name.parse::<VideoCodec>().map_err(refused)?),
    };
    let fps = match spec.fps {
        0 => DEFAULT_VIDEO_FPS,
        fps => fps,
    };
    let quality = spec.quality.unwrap_or(DEFAULT_VIDEO_QUALITY);
    let preset = match spec.preset.as_str() {
        "" => DEFAULT_VIDEO_PRESET,
        name => name
            .parse::<VideoPreset>()
            .map_err(|e| invalid("video.preset", e.to_string()))?,
    };
    VideoSettings::new(container, codec, fps, quality)
        .map(|settings| Some(settings.with_preset(preset)))
        .map_err(refused)
}

/// A checked video as the wire carries it, every option stated.
pub fn video_spec_message(video: &VideoSettings) -> pb::VideoSpec {
    pb::VideoSpec {
        container: video.container.extension().to_owned(),
        codec: video.codec.map(|c| c.name().to_owned()).unwrap_or_default(),
        fps: video.fps,
        quality: Some(video.quality),
        preset: video.preset.name().to_owned(),
    }
}

impl From<&EncodeTask> for pb::EncodeTask {
    fn from(task: &EncodeTask) -> Self {
        pb::EncodeTask {
            lease_id: task.lease_id.clone(),
            lease_expires_unix_ms: task.expires_unix_ms,
            lease_timeout_ms: task.lease_timeout.as_millis() as u32,
            job_id: task.job_id.clone(),
            frames: task.frames,
            width: task.width,
            height: task.height,
            video: Some(video_spec_message(&task.video)),
            failed_attempts: task.failed_attempts,
            max_video_bytes: task.max_video_bytes,
        }
    }
}

/// An encode task as a worker receives it, checked.
impl TryFrom<&pb::EncodeTask> for EncodeTask {
    type Error = DaemonError;

    fn try_from(task: &pb::EncodeTask) -> Result<Self, DaemonError> {
        let video =
            video_settings(task.video.as_ref())?.ok_or_else(|| invalid("video", "is required"))?;
        if task.frames == 0 {
            return Err(invalid("frames", "an encode needs a frame at least"));
        }
        Ok(EncodeTask {
            lease_id: task.lease_id.clone(),
            expires_unix_ms: task.lease_expires_unix_ms,
            lease_timeout: std::time::Duration::from_millis(u64::from(task.lease_timeout_ms)),
            job_id: task.job_id.clone(),
            frames: task.frames,
            width: task.width,
            height: task.height,
            video,
            failed_attempts: task.failed_attempts,
            max_video_bytes: task.max_video_bytes,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn spec(container: &str, codec: &str, fps: u32, quality: Option<u32>) -> pb::VideoSpec {
        pb::VideoSpec {
            container: container.into(),
            codec: codec.into(),
            fps,
            quality,
            preset: String::new(),
        }
    }

    #[test]
    fn a_video_spec_takes_the_shared_defaults() {
        let video = video_settings(Some(&spec(".MP4", "", 0, None)))
            .expect("valid")
            .expect("asked for");
        assert_eq!(video.container, VideoContainer::Mp4);
        assert_eq!(video.codec, Some(VideoCodec::H264));
        assert_eq!(
            (video.fps, video.quality, video.preset),
            (
                DEFAULT_VIDEO_FPS,
                DEFAULT_VIDEO_QUALITY,
                DEFAULT_VIDEO_PRESET
            )
        );
        let slow = pb::VideoSpec {
            preset: "Slow".into(),
            ..spec("mp4", "h265", 24, Some(28))
        };
        let slow = video_settings(Some(&slow)).expect("valid").expect("asked");
        assert_eq!(slow.preset, VideoPreset::Slow);
        assert_eq!(
            video_settings(Some(&video_spec_message(&slow))).expect("again"),
            Some(slow)
        );
        assert_eq!(video_settings(None).expect("none"), None);
        let back = video_spec_message(&video);
        assert_eq!(video_settings(Some(&back)).expect("again"), Some(video));
    }

    #[test]
    fn a_bad_video_spec_names_its_field() {
        let cases = [
            (spec("avi", "", 30, None), "video.container", "mp4, mov"),
            (spec("", "", 30, None), "video.container", "is required"),
            (
                spec("mp4", "mpeg2", 30, None),
                "video.codec",
                "unknown codec",
            ),
            (spec("webm", "h264", 30, None), "video.codec", "VP9 or AV1"),
            (spec("gif", "vp9", 30, None), "video.codec", "GIF"),
            (spec("mp4", "", 241, None), "video.fps", "1..=240"),
            (spec("mp4", "", 30, Some(52)), "video.quality", "0..=51"),
            (
                pb::VideoSpec {
                    preset: "placebo".into(),
                    ..spec("mp4", "", 30, None)
                },
                "video.preset",
                "veryfast",
            ),
        ];
        for (spec, field, says) in cases {
            let error = video_settings(Some(&spec)).expect_err(field).to_string();
            assert!(
                error.contains(field) && error.contains(says),
                "{spec:?}: {error}"
            );
        }
    }
}

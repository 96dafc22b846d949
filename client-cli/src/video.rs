//! Assembling a turntable's frames into a video with ffmpeg: checked before the first frame is
//! rendered (ffmpeg, its encoder, the output's folder), then fed exactly this render's frames,
//! in order, through a pipe, so other files in the folder never end up in the video. The
//! containers, codecs, ranges and the ffmpeg run are the render crate's
//! (`encode::video`), which a job's video made by a worker uses too.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use clap::builder::{PossibleValue, PossibleValuesParser, TypedValueParser};
use pointfarm_render::encode::video::{
    ffmpeg_encoders, frame_decoder, VideoCodec, VideoContainer, VideoEncoder, VideoError,
    VideoSettings,
};

/// `--video-codec`'s parser: the render crate's codecs, by name, each with its description.
pub fn codec_parser() -> impl TypedValueParser<Value = VideoCodec> {
    PossibleValuesParser::new(
        VideoCodec::ALL.map(|codec| PossibleValue::new(codec.name()).help(codec.description())),
    )
    .try_map(|name| name.parse::<VideoCodec>())
}

/// What `--video` asks for.
#[derive(Debug, Clone)]
pub struct VideoRequest {
    pub path: PathBuf,
    pub fps: u32,
    /// `None`: the container's usual codec (H.264, VP9 for .webm); ignored for .gif.
    pub codec: Option<VideoCodec>,
    pub quality: u32,
}

/// A video request checked against this machine's ffmpeg: ready to assemble.
#[derive(Debug, Clone)]
pub struct VideoPlan {
    path: PathBuf,
    settings: VideoSettings,
}

/// The flag that sets the option an error is about.
fn flag_words(error: &VideoError, path: &Path) -> String {
    match error {
        VideoError::UnknownContainer(_) => format!(
            "--video {}: give a file ending in .mp4, .mov, .mkv, .webm or .gif",
            path.display()
        ),
        VideoError::Fps(_) => format!("--fps {error}"),
        VideoError::Quality(_) => format!("--video-quality {error}"),
        VideoError::CodecForGif => {
            "--video-codec does not apply to a GIF, which has its own".into()
        }
        VideoError::UnknownCodec(_) | VideoError::CodecForWebm(_) => error.to_string(),
    }
}

impl VideoRequest {
    /// Checks everything that can stop the video before any frame is rendered: the
    /// extension, the codec against it, the frame rate and quality, the folder it goes to,
    /// and that ffmpeg is installed with the encoder.
    pub fn check(self) -> Result<VideoPlan> {
        let plan = self.check_output()?;
        check_ffmpeg(plan.settings.encoder())?;
        Ok(plan)
    }

    /// [`VideoRequest::check`] without this machine's ffmpeg: for a video a server makes,
    /// which is only downloaded here.
    pub fn check_output(self) -> Result<VideoPlan> {
        let settings = self.settings()?;
        let folder = self
            .path
            .parent()
            .filter(|p| !p.as_os_str().is_empty())
            .unwrap_or(Path::new("."));
        if !folder.is_dir() {
            bail!(
                "--video {}: the folder {} does not exist",
                self.path.display(),
                folder.display()
            );
        }
        if self.path.is_dir() {
            bail!("--video {} is a folder; give a file", self.path.display());
        }
        Ok(VideoPlan {
            path: self.path,
            settings,
        })
    }

    /// The video's settings, checked, without looking at this machine: what a server is
    /// asked to make.
    pub fn settings(&self) -> Result<VideoSettings> {
        let container = VideoContainer::of_path(&self.path)
            .map_err(|e| anyhow::anyhow!(flag_words(&e, &self.path)))?;
        VideoSettings::new(container, self.codec, self.fps, self.quality)
            .map_err(|e| anyhow::anyhow!(flag_words(&e, &self.path)))
    }
}

/// Fails unless ffmpeg runs and has `encoder`.
fn check_ffmpeg(encoder: &str) -> Result<()> {
    let encoders = ffmpeg_encoders().map_err(|reason| {
        anyhow::anyhow!(
            "{reason}, so no video can be made (or leave out --video); nothing was rendered"
        )
    })?;
    if !encoders.iter().any(|present| present == encoder) {
        bail!(
            "this ffmpeg has no {encoder} encoder; choose another --video-codec (or install an \
             ffmpeg built with it); nothing was rendered"
        );
    }
    Ok(())
}

impl VideoPlan {
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Encodes `frames`, in this order and no others, into the video.
    pub fn assemble(&self, frames: &[PathBuf]) -> Result<()> {
        let Some(first) = frames.first() else {
            bail!("no frames to make a video of");
        };
        // The frames' codec named, not probed: ffmpeg's probe of piped JPEGs rejected some of
        // the image crate's.
        let extension = first.extension().and_then(|e| e.to_str()).unwrap_or("");
        let Some(decoder) = frame_decoder(extension) else {
            bail!("{} frames cannot be piped to ffmpeg", first.display());
        };
        let mut encoder =
            VideoEncoder::start(&self.settings, decoder, &self.path).context("starting ffmpeg")?;
        for frame in frames {
            let bytes =
                std::fs::read(frame).with_context(|| format!("reading {}", frame.display()))?;
            if !encoder.write_frame(&bytes) {
                // ffmpeg stopped; its message says why.
                break;
            }
        }
        encoder
            .finish()
            .map_err(|said| anyhow::anyhow!("ffmpeg failed making {}: {said}", self.path.display()))
    }
}

#[cfg(test)]
mod tests {
    use pointfarm_render::encode::video::DEFAULT_VIDEO_QUALITY;

    use super::*;

    fn request(path: &Path) -> VideoRequest {
        VideoRequest {
            path: path.to_path_buf(),
            fps: 30,
            codec: None,
            quality: DEFAULT_VIDEO_QUALITY,
        }
    }

    #[test]
    fn a_video_that_cannot_be_made_is_refused_before_anything_renders() {
        let dir = tempfile::tempdir().expect("tempdir");
        let cases = [
            (request(&dir.path().join("turn.avi")), ".webm or .gif"),
            (
                request(&dir.path().join("absent/turn.mp4")),
                "does not exist",
            ),
            (request(dir.path()), "give a file ending"),
            (
                VideoRequest {
                    codec: Some(VideoCodec::H264),
                    ..request(&dir.path().join("turn.webm"))
                },
                "VP9 or AV1",
            ),
            (
                VideoRequest {
                    codec: Some(VideoCodec::Vp9),
                    ..request(&dir.path().join("turn.gif"))
                },
                "does not apply to a GIF",
            ),
            (
                VideoRequest {
                    quality: 60,
                    ..request(&dir.path().join("turn.mp4"))
                },
                "--video-quality",
            ),
            (
                VideoRequest {
                    fps: 0,
                    ..request(&dir.path().join("turn.mp4"))
                },
                "--fps",
            ),
        ];
        for (request, says) in cases {
            let shown = request.path.display().to_string();
            let error = request.check().expect_err(&shown);
            assert!(error.to_string().contains(says), "{shown}: {error}");
        }
    }
}

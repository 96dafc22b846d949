//! Assembling a turntable's frames into a video with ffmpeg: checked before the first frame is
//! rendered (ffmpeg, its encoder, the output's folder), then fed exactly this render's frames,
//! in order, through a pipe, so other files in the folder never end up in the video.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use anyhow::{bail, Context, Result};
use clap::ValueEnum;
use pointfarm_render::encode::FrameFormat;

/// Video codecs, by the ffmpeg encoder each uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum VideoCodec {
    /// H.264 (libx264): plays everywhere.
    H264,
    /// H.265/HEVC (libx265): about half the size at the same quality.
    H265,
    /// VP9 (libvpx-vp9): for .webm.
    Vp9,
    /// AV1 (libaom-av1): smallest, slowest to encode.
    Av1,
}

impl VideoCodec {
    fn encoder(self) -> &'static str {
        match self {
            Self::H264 => "libx264",
            Self::H265 => "libx265",
            Self::Vp9 => "libvpx-vp9",
            Self::Av1 => "libaom-av1",
        }
    }
}

/// Constant-quality level of the video codecs (ffmpeg's `-crf`): lower is better and larger.
pub const DEFAULT_VIDEO_QUALITY: u32 = 20;
/// The most `-crf` the codecs take in common (H.264/H.265 go to 51, VP9 and AV1 to 63).
pub const MAX_VIDEO_QUALITY: u32 = 51;

/// What `--video` asks for.
#[derive(Debug, Clone)]
pub struct VideoRequest {
    pub path: PathBuf,
    pub fps: u32,
    /// `None`: the container's usual codec (H.264, VP9 for .webm); ignored for .gif.
    pub codec: Option<VideoCodec>,
    pub quality: u32,
}

/// The containers written, by extension.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Container {
    /// .mp4, .mov, .mkv.
    Video { webm: bool },
    /// An animated GIF, with a palette made from the frames: for quick looks.
    Gif,
}

/// A video request checked against this machine's ffmpeg: ready to assemble.
#[derive(Debug, Clone)]
pub struct VideoPlan {
    request: VideoRequest,
    container: Container,
    codec: Option<VideoCodec>,
}

impl VideoRequest {
    /// Checks everything that can stop the video before any frame is rendered: the
    /// extension, the codec against it, the frame rate and quality, the folder it goes to,
    /// and that ffmpeg is installed with the encoder.
    pub fn check(self) -> Result<VideoPlan> {
        let extension = self
            .path
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase);
        let container = match extension.as_deref() {
            Some("mp4" | "mov" | "mkv") => Container::Video { webm: false },
            Some("webm") => Container::Video { webm: true },
            Some("gif") => Container::Gif,
            _ => bail!(
                "--video {}: give a file ending in .mp4, .mov, .mkv, .webm or .gif",
                self.path.display()
            ),
        };
        if !(1..=240).contains(&self.fps) {
            bail!("--fps must lie in 1..=240, got {}", self.fps);
        }
        if self.quality > MAX_VIDEO_QUALITY {
            bail!(
                "--video-quality must lie in 0..={MAX_VIDEO_QUALITY} (lower is better), got {}",
                self.quality
            );
        }
        let codec = match (container, self.codec) {
            (Container::Gif, Some(_)) => {
                bail!("--video-codec does not apply to a GIF, which has its own")
            }
            (Container::Gif, None) => None,
            (Container::Video { webm: true }, Some(c @ (VideoCodec::H264 | VideoCodec::H265))) => {
                bail!(
                    "a .webm video holds VP9 or AV1, not {}; use .mp4 or --video-codec vp9",
                    c.encoder()
                )
            }
            (Container::Video { webm }, codec) => Some(codec.unwrap_or(if webm {
                VideoCodec::Vp9
            } else {
                VideoCodec::H264
            })),
        };
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
        check_ffmpeg(codec.map_or("gif", VideoCodec::encoder))?;
        Ok(VideoPlan {
            request: self,
            container,
            codec,
        })
    }
}

/// Fails unless ffmpeg runs and has `encoder`.
fn check_ffmpeg(encoder: &str) -> Result<()> {
    let missing = || {
        "ffmpeg is not installed, so no video can be made (install it, e.g. apt-get install \
         ffmpeg, or leave out --video); nothing was rendered"
    };
    let output = Command::new("ffmpeg")
        .args(["-hide_banner", "-encoders"])
        .stdin(Stdio::null())
        .output()
        .map_err(|_| anyhow::anyhow!(missing()))?;
    let listed = String::from_utf8_lossy(&output.stdout);
    // Each encoder's line: " V....D libx264  description".
    let present = listed
        .lines()
        .any(|line| line.split_whitespace().nth(1) == Some(encoder));
    if !output.status.success() || !present {
        bail!(
            "this ffmpeg has no {encoder} encoder; choose another --video-codec (or install an \
             ffmpeg built with it); nothing was rendered"
        );
    }
    Ok(())
}

impl VideoPlan {
    pub fn path(&self) -> &Path {
        &self.request.path
    }

    /// Encodes `frames`, in this order and no others, into the video.
    pub fn assemble(&self, frames: &[PathBuf]) -> Result<()> {
        if frames.is_empty() {
            bail!("no frames to make a video of");
        }
        let request = &self.request;
        // The frames' codec named, not probed: ffmpeg's probe of piped JPEGs rejected some of
        // the image crate's.
        let decoder = match FrameFormat::from_path(&frames[0])? {
            FrameFormat::Png => "png",
            FrameFormat::Jpeg => "mjpeg",
            FrameFormat::WebP => "webp",
            FrameFormat::Tiff => bail!("TIFF frames cannot be piped to ffmpeg"),
        };
        let mut command = Command::new("ffmpeg");
        command
            .args(["-y", "-hide_banner", "-loglevel", "error"])
            .args(["-f", "image2pipe", "-framerate", &request.fps.to_string()])
            .args(["-c:v", decoder, "-i", "-"]);
        match (self.container, self.codec) {
            (Container::Gif, _) => {
                command.args([
                    "-vf",
                    "split[a][b];[a]palettegen=stats_mode=diff[p];[b][p]paletteuse",
                    "-loop",
                    "0",
                ]);
            }
            (Container::Video { .. }, codec) => {
                let codec = codec.unwrap_or(VideoCodec::H264);
                // Even dimensions and yuv420p: what every player accepts.
                command
                    .args(["-vf", "pad=ceil(iw/2)*2:ceil(ih/2)*2"])
                    .args(["-c:v", codec.encoder(), "-pix_fmt", "yuv420p"])
                    .args(["-crf", &request.quality.to_string()]);
                if matches!(codec, VideoCodec::Vp9 | VideoCodec::Av1) {
                    // Constant quality for these needs the bitrate unbounded.
                    command.args(["-b:v", "0"]);
                }
            }
        }
        command
            .arg(&request.path)
            .stdin(Stdio::piped())
            .stdout(Stdio::null())
            .stderr(Stdio::piped());
        let mut child = command.spawn().context("starting ffmpeg")?;
        let mut stdin = child.stdin.take().context("ffmpeg's input")?;
        let frames = frames.to_vec();
        // Written from a thread while ffmpeg's errors are read, so neither pipe fills up.
        let feeder = std::thread::spawn(move || -> Result<()> {
            for frame in &frames {
                let bytes =
                    std::fs::read(frame).with_context(|| format!("reading {}", frame.display()))?;
                if stdin.write_all(&bytes).is_err() {
                    // ffmpeg stopped; its message says why.
                    break;
                }
            }
            Ok(())
        });
        let output = child.wait_with_output().context("running ffmpeg")?;
        let fed = feeder
            .join()
            .map_err(|_| anyhow::anyhow!("feeding ffmpeg panicked"))?;
        if !output.status.success() {
            bail!(
                "ffmpeg failed making {}: {}",
                request.path.display(),
                String::from_utf8_lossy(&output.stderr).trim()
            );
        }
        fed
    }
}

#[cfg(test)]
mod tests {
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

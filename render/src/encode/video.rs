//! A sequence of frames made into a video by ffmpeg: the containers and codecs, the options'
//! defaults and ranges, and the ffmpeg run that frames are piped into in order. The CLI's
//! local `--video` and a job's video made by a worker both use this, so what either accepts
//! and makes is the same.

use std::io::{Read, Write};
use std::path::Path;
use std::process::{Child, ChildStdin, Command, Stdio};
use std::sync::{Arc, Mutex, MutexGuard};
use std::thread::JoinHandle;
use std::time::Duration;

use serde::{Deserialize, Serialize};

/// Constant-quality level of the video codecs (ffmpeg's `-crf`): lower is better and larger.
pub const DEFAULT_VIDEO_QUALITY: u32 = 20;
/// The most `-crf` the codecs take in common (H.264/H.265 go to 51, VP9 and AV1 to 63).
pub const MAX_VIDEO_QUALITY: u32 = 51;
/// Frames per second when none is asked for.
pub const DEFAULT_VIDEO_FPS: u32 = 30;
/// The frame rates a video may have.
pub const VIDEO_FPS_RANGE: std::ops::RangeInclusive<u32> = 1..=240;
/// The encoder speed when none is asked for: the fastest of the x264 presets whose video at
/// the same quality is no larger than `medium`'s, measured in docs/perf/farm-videos.md.
pub const DEFAULT_VIDEO_PRESET: VideoPreset = VideoPreset::Veryfast;

/// How much time libx264 and libx265 spend finding a smaller video at the same quality
/// (their `-preset`): each step slower takes more CPU time for a somewhat smaller file.
/// VP9, AV1 and GIF have no presets and take none.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum VideoPreset {
    Ultrafast,
    Superfast,
    Veryfast,
    Faster,
    Fast,
    Medium,
    Slow,
    Slower,
    Veryslow,
}

impl VideoPreset {
    /// Fastest first.
    pub const ALL: [VideoPreset; 9] = [
        Self::Ultrafast,
        Self::Superfast,
        Self::Veryfast,
        Self::Faster,
        Self::Fast,
        Self::Medium,
        Self::Slow,
        Self::Slower,
        Self::Veryslow,
    ];

    /// The name users give, which is also x264's and x265's.
    pub fn name(self) -> &'static str {
        match self {
            Self::Ultrafast => "ultrafast",
            Self::Superfast => "superfast",
            Self::Veryfast => "veryfast",
            Self::Faster => "faster",
            Self::Fast => "fast",
            Self::Medium => "medium",
            Self::Slow => "slow",
            Self::Slower => "slower",
            Self::Veryslow => "veryslow",
        }
    }
}

impl std::fmt::Display for VideoPreset {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl Default for VideoPreset {
    fn default() -> Self {
        DEFAULT_VIDEO_PRESET
    }
}

/// The one of `all` that `name_of` calls `given`, in any case.
fn named<T: Copy, const N: usize>(
    all: [T; N],
    name_of: fn(T) -> &'static str,
    given: &str,
) -> Option<T> {
    all.into_iter()
        .find(|&item| name_of(item).eq_ignore_ascii_case(given))
}

/// A preset name that is none of [`VideoPreset::ALL`].
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error(
    "unknown preset {0:?}: give ultrafast, superfast, veryfast, faster, fast, medium, slow, \
     slower or veryslow (faster makes larger videos)"
)]
pub struct UnknownPreset(pub String);

impl std::str::FromStr for VideoPreset {
    type Err = UnknownPreset;

    fn from_str(name: &str) -> Result<Self, UnknownPreset> {
        named(Self::ALL, Self::name, name).ok_or_else(|| UnknownPreset(name.to_owned()))
    }
}

/// Video codecs, by the ffmpeg encoder each uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum VideoCodec {
    H264,
    H265,
    Vp9,
    Av1,
}

impl VideoCodec {
    pub const ALL: [VideoCodec; 4] = [Self::H264, Self::H265, Self::Vp9, Self::Av1];

    /// The name users give: `h264`, `h265`, `vp9`, `av1`.
    pub fn name(self) -> &'static str {
        match self {
            Self::H264 => "h264",
            Self::H265 => "h265",
            Self::Vp9 => "vp9",
            Self::Av1 => "av1",
        }
    }

    /// What the codec is for, in a sentence.
    pub fn description(self) -> &'static str {
        match self {
            Self::H264 => "H.264 (libx264): plays everywhere",
            Self::H265 => "H.265/HEVC (libx265): about half the size at the same quality",
            Self::Vp9 => "VP9 (libvpx-vp9): for .webm",
            Self::Av1 => "AV1 (libaom-av1): smallest, slowest to encode",
        }
    }

    /// The ffmpeg encoder.
    pub fn encoder(self) -> &'static str {
        match self {
            Self::H264 => "libx264",
            Self::H265 => "libx265",
            Self::Vp9 => "libvpx-vp9",
            Self::Av1 => "libaom-av1",
        }
    }
}

impl std::str::FromStr for VideoCodec {
    type Err = VideoError;

    fn from_str(name: &str) -> Result<Self, VideoError> {
        named(Self::ALL, Self::name, name).ok_or_else(|| VideoError::UnknownCodec(name.to_owned()))
    }
}

/// The containers written.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum VideoContainer {
    Mp4,
    Mov,
    Mkv,
    Webm,
    /// An animated GIF, with a palette made from the frames: for quick looks.
    Gif,
}

impl VideoContainer {
    pub const ALL: [VideoContainer; 5] = [Self::Mp4, Self::Mov, Self::Mkv, Self::Webm, Self::Gif];

    /// The media type a browser plays it by.
    pub fn media_type(self) -> &'static str {
        match self {
            Self::Mp4 => "video/mp4",
            Self::Mov => "video/quicktime",
            Self::Mkv => "video/x-matroska",
            Self::Webm => "video/webm",
            Self::Gif => "image/gif",
        }
    }

    /// Its name, which is also its file's extension.
    pub fn extension(self) -> &'static str {
        match self {
            Self::Mp4 => "mp4",
            Self::Mov => "mov",
            Self::Mkv => "mkv",
            Self::Webm => "webm",
            Self::Gif => "gif",
        }
    }

    /// The container named `name` (`mp4`, `.mp4`, any case).
    pub fn from_name(name: &str) -> Result<Self, VideoError> {
        let bare = name.strip_prefix('.').unwrap_or(name);
        named(Self::ALL, Self::extension, bare)
            .ok_or_else(|| VideoError::UnknownContainer(name.to_owned()))
    }

    /// The container of a file named `path`, by its extension.
    pub fn of_path(path: &Path) -> Result<Self, VideoError> {
        path.extension()
            .and_then(|e| e.to_str())
            .and_then(|e| Self::from_name(e).ok())
            .ok_or_else(|| VideoError::UnknownContainer(path.display().to_string()))
    }

    /// The codec used when none is asked for; None for a GIF, which has its own.
    pub fn usual_codec(self) -> Option<VideoCodec> {
        match self {
            Self::Gif => None,
            Self::Webm => Some(VideoCodec::Vp9),
            Self::Mp4 | Self::Mov | Self::Mkv => Some(VideoCodec::H264),
        }
    }
}

/// Why a video cannot be made as asked.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum VideoError {
    #[error("{0}: give a container (a file ending) of mp4, mov, mkv, webm or gif")]
    UnknownContainer(String),
    #[error("unknown codec {0:?}: give h264, h265, vp9 or av1")]
    UnknownCodec(String),
    #[error("must lie in 1..=240, got {0}")]
    Fps(u32),
    #[error("must lie in 0..={MAX_VIDEO_QUALITY} (lower is better), got {0}")]
    Quality(u32),
    #[error("a codec does not apply to a GIF, which has its own")]
    CodecForGif,
    #[error("a .webm video holds VP9 or AV1, not {}; use .mp4 or codec vp9", .0.encoder())]
    CodecForWebm(VideoCodec),
}

impl VideoError {
    /// The option at fault: `container`, `codec`, `fps` or `quality`.
    pub fn field(&self) -> &'static str {
        match self {
            Self::UnknownContainer(_) => "container",
            Self::UnknownCodec(_) | Self::CodecForGif | Self::CodecForWebm(_) => "codec",
            Self::Fps(_) => "fps",
            Self::Quality(_) => "quality",
        }
    }
}

/// A video asked for, checked: a container, the codec it holds, the frame rate and quality.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct VideoSettings {
    pub container: VideoContainer,
    /// None only for a GIF.
    pub codec: Option<VideoCodec>,
    pub fps: u32,
    pub quality: u32,
    /// The x264/x265 preset; unused by the other codecs. Records stored without one read as
    /// the default.
    #[serde(default)]
    pub preset: VideoPreset,
}

impl VideoSettings {
    /// Checks a video's options: `codec` None takes the container's usual one, and the preset
    /// is [`DEFAULT_VIDEO_PRESET`] until [`Self::with_preset`].
    pub fn new(
        container: VideoContainer,
        codec: Option<VideoCodec>,
        fps: u32,
        quality: u32,
    ) -> Result<Self, VideoError> {
        if !VIDEO_FPS_RANGE.contains(&fps) {
            return Err(VideoError::Fps(fps));
        }
        if quality > MAX_VIDEO_QUALITY {
            return Err(VideoError::Quality(quality));
        }
        let codec = match (container, codec) {
            (VideoContainer::Gif, Some(_)) => return Err(VideoError::CodecForGif),
            (VideoContainer::Webm, Some(c @ (VideoCodec::H264 | VideoCodec::H265))) => {
                return Err(VideoError::CodecForWebm(c))
            }
            (container, codec) => codec.or(container.usual_codec()),
        };
        Ok(Self {
            container,
            codec,
            fps,
            quality,
            preset: DEFAULT_VIDEO_PRESET,
        })
    }

    /// These settings with the x264/x265 `preset`.
    pub fn with_preset(self, preset: VideoPreset) -> Self {
        Self { preset, ..self }
    }

    /// Whether the codec takes a preset (H.264 and H.265).
    pub fn takes_preset(&self) -> bool {
        matches!(self.codec, Some(VideoCodec::H264 | VideoCodec::H265))
    }

    /// The ffmpeg encoder this video needs (`gif` for a GIF).
    pub fn encoder(&self) -> &'static str {
        self.codec.map_or("gif", VideoCodec::encoder)
    }

    /// The ffmpeg arguments that read frames of `decoder` (`png`, `mjpeg`, `webp`) from
    /// standard input and write this video to the path that follows them.
    fn ffmpeg_args(&self, decoder: &str) -> Vec<String> {
        let mut args: Vec<String> = ["-y", "-hide_banner", "-loglevel", "error"]
            .into_iter()
            .map(String::from)
            .collect();
        let fps = self.fps.to_string();
        args.extend(["-f", "image2pipe", "-framerate", &fps].map(String::from));
        args.extend(["-c:v", decoder, "-i", "-"].map(String::from));
        match self.codec {
            None => args.extend(
                [
                    "-vf",
                    "split[a][b];[a]palettegen=stats_mode=diff[p];[b][p]paletteuse",
                    "-loop",
                    "0",
                    "-f",
                    "gif",
                ]
                .map(String::from),
            ),
            Some(codec) => {
                let crf = self.quality.to_string();
                // Even dimensions and yuv420p: what every player accepts.
                args.extend(["-vf", "pad=ceil(iw/2)*2:ceil(ih/2)*2"].map(String::from));
                args.extend(["-c:v", codec.encoder(), "-pix_fmt", "yuv420p"].map(String::from));
                args.extend(["-crf", &crf].map(String::from));
                if self.takes_preset() {
                    args.extend(["-preset", self.preset.name()].map(String::from));
                }
                if matches!(codec, VideoCodec::Vp9 | VideoCodec::Av1) {
                    // Constant quality for these needs the bitrate unbounded.
                    args.extend(["-b:v", "0"].map(String::from));
                }
                let format = match self.container {
                    VideoContainer::Mkv => "matroska",
                    other => other.extension(),
                };
                args.extend(["-f", format].map(String::from));
            }
        }
        args
    }
}

/// The encoders of [`VideoCodec`] and `gif` that this machine's ffmpeg has; an error saying
/// why when ffmpeg does not run.
pub fn ffmpeg_encoders() -> Result<Vec<String>, String> {
    let missing = "ffmpeg is not installed (install it, e.g. apt-get install ffmpeg)";
    let version = Command::new("ffmpeg")
        .arg("-version")
        .stdin(Stdio::null())
        .stderr(Stdio::null())
        .output()
        .map_err(|_| missing.to_owned())?;
    if !version.status.success() {
        return Err(format!("ffmpeg -version failed ({})", version.status));
    }
    let output = Command::new("ffmpeg")
        .args(["-hide_banner", "-encoders"])
        .stdin(Stdio::null())
        .stderr(Stdio::null())
        .output()
        .map_err(|_| missing.to_owned())?;
    let listed = String::from_utf8_lossy(&output.stdout);
    // Each encoder's line: " V....D libx264  description".
    let wanted: Vec<&str> = VideoCodec::ALL
        .iter()
        .map(|c| c.encoder())
        .chain(["gif"])
        .collect();
    Ok(listed
        .lines()
        .filter_map(|line| line.split_whitespace().nth(1))
        .filter(|name| wanted.contains(name))
        .map(str::to_owned)
        .collect())
}

/// The ffmpeg decoder of frames in files ending in `extension`; None for frames ffmpeg cannot
/// be piped (TIFF).
pub fn frame_decoder(extension: &str) -> Option<&'static str> {
    match extension.to_ascii_lowercase().as_str() {
        "png" => Some("png"),
        "jpg" | "jpeg" => Some("mjpeg"),
        "webp" => Some("webp"),
        _ => None,
    }
}

/// How often [`VideoEncoder::finish`] looks whether ffmpeg has exited, so that an
/// [`EncoderStop`] can end it meanwhile.
const FINISH_POLL: Duration = Duration::from_millis(20);

/// A running ffmpeg that frames are written into, in order, and that writes the video.
pub struct VideoEncoder {
    /// Shared with its [`EncoderStop`]s.
    child: Arc<Mutex<Child>>,
    stdin: Option<ChildStdin>,
    /// ffmpeg's errors, read while it runs so that the pipe never fills.
    stderr: Option<JoinHandle<String>>,
}

impl VideoEncoder {
    /// Starts ffmpeg writing `settings`' video of frames of `decoder` to `output`.
    pub fn start(settings: &VideoSettings, decoder: &str, output: &Path) -> std::io::Result<Self> {
        let mut child = Command::new("ffmpeg")
            .args(settings.ffmpeg_args(decoder))
            .arg(output)
            .stdin(Stdio::piped())
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()?;
        let stdin = child.stdin.take();
        let stderr = child.stderr.take().map(|mut pipe| {
            std::thread::spawn(move || {
                let mut text = String::new();
                let _ = pipe.read_to_string(&mut text);
                text
            })
        });
        Ok(Self {
            child: Arc::new(Mutex::new(child)),
            stdin,
            stderr,
        })
    }

    /// A handle that ends this encoder's ffmpeg from elsewhere, even while
    /// [`Self::finish`] waits for it.
    pub fn stopper(&self) -> EncoderStop {
        EncoderStop(self.child.clone())
    }

    /// Writes one frame's bytes. False when ffmpeg stopped reading: [`Self::finish`] says why.
    pub fn write_frame(&mut self, bytes: &[u8]) -> bool {
        self.stdin
            .as_mut()
            .is_some_and(|stdin| stdin.write_all(bytes).is_ok())
    }

    /// Ends the input and waits for ffmpeg; the error is ffmpeg's own words.
    pub fn finish(mut self) -> Result<(), String> {
        drop(self.stdin.take());
        let status = loop {
            let exited = lock(&self.child)
                .try_wait()
                .map_err(|e| format!("waiting for ffmpeg: {e}"))?;
            match exited {
                Some(status) => break status,
                None => std::thread::sleep(FINISH_POLL),
            }
        };
        let stderr = self
            .stderr
            .take()
            .and_then(|reader| reader.join().ok())
            .unwrap_or_default();
        if status.success() {
            Ok(())
        } else {
            let said = stderr.trim();
            Err(if said.is_empty() {
                format!("ffmpeg failed ({status})")
            } else {
                said.to_owned()
            })
        }
    }
}

impl Drop for VideoEncoder {
    fn drop(&mut self) {
        // An encoder dropped before it finished leaves no ffmpeg behind.
        if self.stdin.is_some() {
            let mut child = lock(&self.child);
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}

/// Ends a [`VideoEncoder`]'s ffmpeg: its video is not made, and `finish` says ffmpeg failed.
#[derive(Clone)]
pub struct EncoderStop(Arc<Mutex<Child>>);

impl EncoderStop {
    pub fn stop(&self) {
        // An ffmpeg that has exited already is left as it is.
        let _ = lock(&self.0).kill();
    }
}

/// The child, whether or not a thread panicked holding it: it is only killed and waited on.
fn lock(child: &Mutex<Child>) -> MutexGuard<'_, Child> {
    child.lock().unwrap_or_else(|e| e.into_inner())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn settings_are_checked_and_take_the_containers_codec() {
        let mp4 = VideoSettings::new(VideoContainer::Mp4, None, 30, 20).expect("mp4");
        assert_eq!(mp4.codec, Some(VideoCodec::H264));
        let webm = VideoSettings::new(VideoContainer::Webm, None, 24, 30).expect("webm");
        assert_eq!(webm.encoder(), "libvpx-vp9");
        let gif = VideoSettings::new(VideoContainer::Gif, None, 10, 0).expect("gif");
        assert_eq!(gif.encoder(), "gif");
        let refused = [
            (VideoContainer::Mp4, None, 0, 20, "fps"),
            (VideoContainer::Mp4, None, 241, 20, "fps"),
            (VideoContainer::Mp4, None, 30, 52, "quality"),
            (VideoContainer::Gif, Some(VideoCodec::Vp9), 30, 20, "codec"),
            (
                VideoContainer::Webm,
                Some(VideoCodec::H265),
                30,
                20,
                "codec",
            ),
        ];
        for (container, codec, fps, quality, field) in refused {
            let error = VideoSettings::new(container, codec, fps, quality).expect_err(field);
            assert_eq!(error.field(), field, "{error}");
        }
    }

    #[test]
    fn containers_and_codecs_are_read_by_name() {
        assert_eq!(VideoContainer::from_name(".MP4"), Ok(VideoContainer::Mp4));
        assert_eq!(
            VideoContainer::of_path(Path::new("spin.webm")),
            Ok(VideoContainer::Webm)
        );
        assert!(VideoContainer::from_name("avi").is_err());
        assert_eq!("AV1".parse::<VideoCodec>(), Ok(VideoCodec::Av1));
        let unknown = "mpeg2".parse::<VideoCodec>().expect_err("unknown");
        assert!(unknown.to_string().contains("h264, h265, vp9 or av1"));
        assert_eq!("VeryFast".parse::<VideoPreset>(), Ok(VideoPreset::Veryfast));
        let unknown = "placebo".parse::<VideoPreset>().expect_err("unknown");
        assert!(
            unknown.to_string().contains("ultrafast, superfast"),
            "{unknown}"
        );
    }

    #[test]
    fn the_preset_reaches_x264_and_x265_only() {
        let preset_of = |settings: &VideoSettings| {
            let args = settings.ffmpeg_args("png");
            args.iter()
                .position(|a| a == "-preset")
                .map(|at| args[at + 1].clone())
        };
        let mp4 = VideoSettings::new(VideoContainer::Mp4, None, 30, 20).expect("mp4");
        assert_eq!(
            preset_of(&mp4).as_deref(),
            Some(DEFAULT_VIDEO_PRESET.name())
        );
        let slow = VideoSettings::new(VideoContainer::Mkv, Some(VideoCodec::H265), 30, 20)
            .expect("mkv")
            .with_preset(VideoPreset::Slow);
        assert_eq!(preset_of(&slow).as_deref(), Some("slow"));
        for container in [VideoContainer::Webm, VideoContainer::Gif] {
            let settings = VideoSettings::new(container, None, 30, 20).expect("no preset");
            assert!(!settings.takes_preset());
            assert_eq!(preset_of(&settings.with_preset(VideoPreset::Slow)), None);
        }
    }

    #[test]
    fn settings_stored_without_a_preset_read_with_the_default() {
        let stored = r#"{"container":"Mp4","codec":"H264","fps":30,"quality":20}"#;
        let settings: VideoSettings = serde_json::from_str(stored).expect("reads");
        assert_eq!(settings.preset, DEFAULT_VIDEO_PRESET);
    }
}

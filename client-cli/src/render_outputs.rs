//! Where a render's frames, depth images, video and legend go, checked before anything is
//! rendered, here or through a server (`remote_render`), and written as the frames come.
//!
//! `--out` is one file for a still, or a folder or a numbered pattern
//! (`frames/frame_{:05}.png`) for a sequence, in the image format the extension names; each
//! depth image, and the sidecar that turns it back into distances, goes beside its frame. TIFF
//! frames of an orthographic top view are placed on the ground in the sources' CRS. A video is
//! checked before the first frame (ffmpeg, its encoder, the output's folder), then fed exactly
//! this render's frames, in order, through a pipe, so other files in the folder never end up
//! in it; its containers, codecs, ranges and the ffmpeg run are the render crate's
//! (`encode::video`), which a job's video made by a worker uses too.

use std::cell::Cell;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use pointfarm_render::camera::Camera;
use pointfarm_render::color::{ColorMode, ColorRange, Coloring};
use pointfarm_render::encode::geotiff::{GeoCrs, GeoTransform, Georeference};
use pointfarm_render::encode::video::{
    ffmpeg_encoders, frame_decoder, VideoCodec, VideoContainer, VideoEncoder, VideoError,
    VideoPreset, VideoSettings,
};
use pointfarm_render::encode::{self, FrameFormat};
use pointfarm_render::ingest::dataset_files;
use pointfarm_render::legend::Legend;
use pointfarm_render::raster::{Frame, FrameSettings};
use pointfarm_render::request::RenderRequest;

use crate::output::Reporter;
use crate::render_args::RenderArgs;
use crate::render_json::CameraJson;

/// Where a render's frames and video go, checked before anything is rendered.
pub(crate) struct Outputs {
    pub files: FrameFiles,
    pub video: Option<VideoPlan>,
    /// Where `--legend` goes, checked.
    legend: Option<PathBuf>,
    /// The sources' CRS, read when TIFF frames are rendered here, where each frame's camera
    /// is known.
    crs: Option<GeoCrs>,
    /// Whether each frame's depth image is written beside it.
    depth: bool,
    /// Whether the line saying why the TIFF frames are not placed on the ground was said.
    told_unplaced: Cell<bool>,
    reporter: Reporter,
}

impl Outputs {
    pub fn check(args: &RenderArgs, request: &RenderRequest, reporter: Reporter) -> Result<Self> {
        let files = if args.is_sequence() {
            FrameFiles::sequence(&args.out)?
        } else {
            FrameFiles::still(&args.out)?
        };
        files.check_background(request.render.background)?;
        let video_request = VideoRequest::of(args);
        if video_request.is_some() && !args.is_sequence() {
            bail!(
                "--video needs frames to make a video of: add --turntable N or --camera-path FILE"
            );
        }
        if video_request.is_some() && files.format() == FrameFormat::Tiff {
            // ffmpeg reads piped frames in order and cannot seek back in a TIFF.
            bail!("--video is made from PNG, JPEG or WebP frames; TIFF frames cannot be piped to ffmpeg");
        }
        // Through a server the video is made there, so this machine needs no ffmpeg.
        let through_server = args.server.is_some() && !args.local;
        let video = video_request
            .map(|video| match through_server {
                true => video.check_output(),
                false => video.check(),
            })
            .transpose()?;
        let legend = args.legend.clone();
        if let Some(path) = &legend {
            let mode = request.render.color_mode;
            if !(mode.is_ramped()
                || matches!(mode, ColorMode::Classification | ColorMode::ReturnNumber))
            {
                bail!(
                    "--legend shows the colors of elevation, intensity, classification and \
                     return; --color {} has none to show",
                    mode.name()
                );
            }
            let png = path
                .extension()
                .is_some_and(|e| e.eq_ignore_ascii_case("png"));
            if !png {
                bail!("--legend {}: the legend is a .png file", path.display());
            }
        }
        let renders_here = (args.server.is_none() || args.local) && args.dataset.is_none();
        let tiff = files.format() == FrameFormat::Tiff;
        let crs = if tiff && renders_here {
            Some(GeoCrs::of_files(&dataset_files(&args.inputs)?)?)
        } else {
            None
        };
        if tiff && !renders_here {
            reporter.say(
                "note: TIFF frames rendered by a server are not georeferenced: it sends each \
                 frame as a PNG image without its camera",
            );
        }
        Ok(Self {
            files,
            video,
            legend,
            crs,
            depth: request.render.depth,
            told_unplaced: Cell::new(false),
            reporter,
        })
    }

    /// Writes frame `index`, drawn with `settings`, in the frames' format, a TIFF placed on
    /// the ground where it can be ([`Outputs::georeference`]), and beside it its depth image
    /// where the request asks for one, placed as its frame is; the frame's path.
    pub fn save(&self, index: u32, frame: &mut Frame, settings: &FrameSettings) -> Result<PathBuf> {
        let path = self.files.frame(index);
        let camera = &settings.camera;
        let georeference = self.georeference(frame, camera);
        let placed = georeference.as_ref();
        let format = self.files.format();
        encode::save_georeferenced_frame(frame, &path, format, placed)
            .with_context(|| format!("writing {}", path.display()))?;
        if !self.depth {
            return Ok(path);
        }
        // A 16-bit TIFF beside a TIFF frame, a 16-bit PNG beside any other.
        let depth = self.files.depth(index);
        let (near, far) = (camera.near, camera.far);
        match format {
            FrameFormat::Tiff => encode::save_depth_tiff16(frame, &depth, near, far, placed),
            _ => encode::save_depth_png16(frame, &depth, near, far),
        }
        .with_context(|| format!("writing {}", depth.display()))?;
        write_depth_sidecar(&depth, frame.image.dimensions(), camera)?;
        Ok(path)
    }

    /// Writes the legend `--legend` asks for, of `coloring` over `range` (called only then);
    /// the line that says so, or none without `--legend`.
    pub fn write_legend(
        &self,
        coloring: Coloring,
        range: impl FnOnce() -> Option<ColorRange>,
    ) -> Result<Option<String>> {
        let Some(path) = &self.legend else {
            return Ok(None);
        };
        let legend = Legend::of(coloring, range())
            .context("--legend: the dataset has nothing to color by in this mode")?;
        legend.write(path)?;
        let (width, height) = legend.size();
        Ok(Some(format!(
            "legend: {} ({width}x{height})",
            path.display()
        )))
    }

    /// Where a TIFF frame seen by `camera` lies in the sources' CRS: only an orthographic view
    /// from straight above has one place on the ground. The first frame that cannot be placed,
    /// or only without a CRS, says why once.
    fn georeference(&self, frame: &Frame, camera: &Camera) -> Option<Georeference> {
        let crs = self.crs.as_ref()?;
        let (width, height) = frame.image.dimensions();
        let placed =
            GeoTransform::of_top_view(camera, width, height).map(|transform| Georeference {
                transform,
                crs: crs.clone(),
            });
        let note = match (&placed, crs) {
            (None, _) => Some(
                "TIFF frames are not georeferenced: only an orthographic view from straight \
                 above (--view top --ortho) has one place on the ground"
                    .to_owned(),
            ),
            (Some(_), GeoCrs::Unknown(why)) => Some(format!(
                "TIFF frames are placed in the sources' coordinates without a CRS: {why}"
            )),
            (Some(_), _) => None,
        };
        if let Some(note) = note.filter(|_| !self.told_unplaced.replace(true)) {
            self.reporter.say(format_args!("note: {note}"));
        }
        placed
    }
}

/// The file name of a turntable's frames when `--out` is a folder.
const FOLDER_PATTERN: &str = "frame_{:05}.png";

/// The frame files of one render.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameFiles {
    /// The folder the frames go to (created before the first frame).
    dir: PathBuf,
    /// The file name before the frame number, and after it (with the extension).
    prefix: String,
    suffix: String,
    /// Digits of the frame number, zero-padded; `None` for a still's one file.
    digits: Option<usize>,
    format: FrameFormat,
}

impl FrameFiles {
    /// The one file of a still: `out` must name a file in a known format.
    pub fn still(out: &Path) -> Result<Self> {
        let text = out.to_string_lossy();
        // A name ending in a separator is a folder, made or not.
        if out.is_dir() || text.ends_with('/') || text.ends_with(std::path::MAIN_SEPARATOR) {
            bail!(
                "{} is a folder; give an image file such as frame.png (or use --turntable N)",
                out.display()
            );
        }
        let name = file_name(out)?;
        if name.contains('{') {
            bail!(
                "{} is a pattern of numbered frames, which a still does not have; give one \
                 file such as frame.png",
                out.display()
            );
        }
        Ok(Self {
            dir: parent(out),
            prefix: name.to_string(),
            suffix: String::new(),
            digits: None,
            format: FrameFormat::from_path(out)?,
        })
    }

    /// The numbered files of a turntable: `out` is a folder (one that exists, one ending in
    /// `/`, or a name without an extension) for `frame_00000.png, ...`, or a pattern whose
    /// file name holds `{}` or `{:0N}` where the number goes. A file name is refused: the
    /// frames would overwrite it.
    pub fn sequence(out: &Path) -> Result<Self> {
        let text = out.to_string_lossy();
        let is_folder = out.is_dir()
            || text.ends_with(std::path::MAIN_SEPARATOR)
            || text.ends_with('/')
            || (out.extension().is_none() && !text.contains('{'));
        let (dir, name) = if is_folder {
            (out.to_path_buf(), FOLDER_PATTERN.to_string())
        } else {
            (parent(out), file_name(out)?.to_string())
        };
        let Some((prefix, digits, suffix)) = split_pattern(&name) else {
            if dir.to_string_lossy().contains('{') {
                bail!(
                    "{}: the frame number goes in the file name, not in a folder's",
                    out.display()
                );
            }
            bail!(
                "{} names one file, but a turntable or camera path writes many frames: give \
                 a folder (frames/) or a pattern with the frame number \
                 (frames/frame_{{:05}}.png)",
                out.display()
            );
        };
        let format = FrameFormat::from_path(&dir.join(&name))?;
        Ok(Self {
            dir,
            prefix,
            suffix,
            digits: Some(digits),
            format,
        })
    }

    pub fn format(&self) -> FrameFormat {
        self.format
    }

    /// The folder the frames go to.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Creates the folder of the frames, if need be.
    pub fn create_dir(&self) -> Result<()> {
        std::fs::create_dir_all(&self.dir)
            .with_context(|| format!("creating {}", self.dir.display()))
    }

    /// The file of frame `index`.
    pub fn frame(&self, index: u32) -> PathBuf {
        let name = match self.digits {
            None => self.prefix.clone(),
            Some(digits) => format!("{}{index:0digits$}{}", self.prefix, self.suffix),
        };
        self.dir.join(name)
    }

    /// The 16-bit depth image of frame `index`: the frame's file with `.depth.png` for its
    /// extension, or `.depth.tif` beside a TIFF frame, beside the frame.
    pub fn depth(&self, index: u32) -> PathBuf {
        let extension = match self.format {
            FrameFormat::Tiff => "depth.tif",
            _ => "depth.png",
        };
        self.frame(index).with_extension(extension)
    }

    /// Refuses what this format cannot hold of the frames: a transparent background in JPEG.
    pub fn check_background(&self, background: [u8; 4]) -> Result<()> {
        if background[3] < 255 && !self.format.has_alpha() {
            bail!(
                "JPEG has no alpha channel, so a transparent --background would be lost: \
                 write .png, .webp or .tif, or give an opaque background"
            );
        }
        Ok(())
    }

    /// Moves a PNG frame fetched from a server to frame `index`'s file, converting it where
    /// this render's format is not PNG.
    pub fn place_png(&self, png: &Path, index: u32) -> Result<PathBuf> {
        let path = self.frame(index);
        if self.format == FrameFormat::Png {
            std::fs::rename(png, &path).with_context(|| format!("writing {}", path.display()))?;
        } else {
            let image = image::open(png)
                .with_context(|| format!("reading the fetched frame {}", png.display()))?
                .to_rgba8();
            encode::save_image(&image, &path, self.format)
                .with_context(|| format!("writing {}", path.display()))?;
            std::fs::remove_file(png).ok();
        }
        Ok(path)
    }
}

/// Writes the sidecar JSON (`.depth.json`) of the depth image `depth`, of `width` x
/// `height` pixels seen by `camera`: the near and far distances its grey levels span, the
/// camera and the image size, so that a pixel's value `v` (1 to 65535; 0 where no point
/// landed) is the distance `near + (v - 1) / 65534 * (far - near)` along the viewing
/// direction, in the dataset's units.
fn write_depth_sidecar(depth: &Path, (width, height): (u32, u32), camera: &Camera) -> Result<()> {
    let sidecar = depth.with_extension("json");
    let json = serde_json::json!({
        "image": depth.file_name().map(|n| n.to_string_lossy().into_owned()),
        "width": width,
        "height": height,
        "near": camera.near,
        "far": camera.far,
        "encoding": "16-bit grey, linear: 0 = no point; v in 1..65535 is the distance \
                     near + (v - 1) / 65534 * (far - near) along the viewing direction",
        "camera": CameraJson::of(camera),
    });
    let text = serde_json::to_string_pretty(&json).context("encoding the depth sidecar")?;
    std::fs::write(&sidecar, text + "\n").with_context(|| format!("writing {}", sidecar.display()))
}

fn parent(out: &Path) -> PathBuf {
    out.parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."))
        .to_path_buf()
}

fn file_name(out: &Path) -> Result<&str> {
    out.file_name()
        .and_then(|n| n.to_str())
        .with_context(|| format!("{} names no file", out.display()))
}

/// Splits `name` at its one placeholder, `{}` (no padding) or `{:0N}` (N digits, zero-padded):
/// the text before, the digits and the text after. `None` without exactly one.
fn split_pattern(name: &str) -> Option<(String, usize, String)> {
    let start = name.find('{')?;
    let end = start + name[start..].find('}')?;
    let (prefix, rest) = (&name[..start], &name[end + 1..]);
    if rest.contains(['{', '}']) || prefix.contains('}') {
        return None;
    }
    let digits = match &name[start + 1..end] {
        "" => 0,
        spec => spec.strip_prefix(":0")?.parse().ok().filter(|&d| d <= 12)?,
    };
    Some((prefix.to_string(), digits, rest.to_string()))
}

/// What `--video` asks for.
#[derive(Debug, Clone)]
pub struct VideoRequest {
    pub path: PathBuf,
    pub fps: u32,
    /// `None`: the container's usual codec (H.264, VP9 for .webm); ignored for .gif.
    pub codec: Option<VideoCodec>,
    pub quality: u32,
    pub preset: VideoPreset,
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
    /// The video `--video` asks for, unchecked.
    fn of(args: &RenderArgs) -> Option<Self> {
        args.video.clone().map(|path| Self {
            path,
            fps: args.fps,
            codec: args.video_codec,
            quality: args.video_quality,
            preset: args.video_preset,
        })
    }

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
    fn settings(&self) -> Result<VideoSettings> {
        let container = VideoContainer::of_path(&self.path)
            .map_err(|e| anyhow::anyhow!(flag_words(&e, &self.path)))?;
        VideoSettings::new(container, self.codec, self.fps, self.quality)
            .map(|settings| settings.with_preset(self.preset))
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

    /// What a server is asked to make.
    pub fn settings(&self) -> VideoSettings {
        self.settings
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
mod tests;

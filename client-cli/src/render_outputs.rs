//! Where a render's frames, video and legend go: checked before anything is rendered, here
//! or through a server (`remote_render`), and the legend written; TIFF frames of an
//! orthographic top view placed on the ground in the sources' CRS.

use std::cell::Cell;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use pointfarm_render::camera::Camera;
use pointfarm_render::color::ColorMode;
use pointfarm_render::encode::geotiff::{GeoCrs, GeoTransform, Georeference};
use pointfarm_render::encode::{self, FrameFormat};
use pointfarm_render::ingest::dataset_files;
use pointfarm_render::legend::Legend;
use pointfarm_render::raster::{Frame, FrameSettings};
use pointfarm_render::request::RenderRequest;

use crate::frame_files::{save_depth, FrameFiles};
use crate::render_args::RenderArgs;
use crate::video::VideoPlan;

/// Where a render's frames and video go, checked before anything is rendered.
pub(crate) struct Outputs {
    pub files: FrameFiles,
    pub video: Option<VideoPlan>,
    /// Where `--legend` goes, checked.
    pub legend: Option<PathBuf>,
    /// The sources' CRS, read when TIFF frames are rendered here, where each frame's camera
    /// is known.
    crs: Option<GeoCrs>,
    /// Whether the line saying why the TIFF frames are not placed on the ground was said.
    told_unplaced: Cell<bool>,
    json: bool,
}

impl Outputs {
    pub fn check(args: &RenderArgs, request: &RenderRequest) -> Result<Self> {
        let files = if args.is_sequence() {
            FrameFiles::sequence(&args.out)?
        } else {
            FrameFiles::still(&args.out)?
        };
        files.check_background(request.render.background)?;
        if args.video_request().is_some() && !args.is_sequence() {
            bail!(
                "--video needs frames to make a video of: add --turntable N or --camera-path FILE"
            );
        }
        if args.video_request().is_some() && files.format() == FrameFormat::Tiff {
            // ffmpeg reads piped frames in order and cannot seek back in a TIFF.
            bail!("--video is made from PNG, JPEG or WebP frames; TIFF frames cannot be piped to ffmpeg");
        }
        // Through a server the video is made there, so this machine needs no ffmpeg.
        let through_server = args.server.is_some() && !args.local;
        let video = args
            .video_request()
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
            crate::output::say(
                args.json,
                "note: TIFF frames rendered by a server are not georeferenced: it sends each \
                 frame as a PNG image without its camera"
                    .to_owned(),
            );
        }
        Ok(Self {
            files,
            video,
            legend,
            crs,
            told_unplaced: Cell::new(false),
            json: args.json,
        })
    }

    /// Writes `frame`, seen by `camera`, to `path` in the frames' format, a TIFF placed on the
    /// ground where it can be ([`Outputs::georeference`]).
    pub fn save_frame(&self, frame: &mut Frame, path: &Path, camera: &Camera) -> Result<()> {
        let georeference = self.georeference(frame, camera);
        encode::save_georeferenced_frame(frame, path, self.files.format(), georeference.as_ref())
            .with_context(|| format!("writing {}", path.display()))
    }

    /// Writes frame `index`'s depth image and its sidecar beside the frame, a TIFF beside a
    /// TIFF frame, placed as its frame is.
    pub fn save_depth(&self, index: u32, frame: &Frame, settings: &FrameSettings) -> Result<()> {
        let georeference = self.georeference(frame, &settings.camera);
        save_depth(&self.files, index, frame, settings, georeference.as_ref())?;
        Ok(())
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
            crate::output::say(self.json, format!("note: {note}"));
        }
        placed
    }
}

/// Writes `legend` to `path`; the line that says so.
pub(crate) fn write_legend(path: &Path, legend: Option<Legend>) -> Result<String> {
    let legend = legend.context("--legend: the dataset has nothing to color by in this mode")?;
    legend.write(path)?;
    let (width, height) = legend.size();
    Ok(format!("legend: {} ({width}x{height})", path.display()))
}

//! Where a render's frames, video and legend go: checked before anything is rendered, here
//! or through a server (`remote_render`), and the legend written.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use pointfarm_render::color::ColorMode;
use pointfarm_render::encode::FrameFormat;
use pointfarm_render::legend::Legend;
use pointfarm_render::request::RenderRequest;

use crate::frame_files::FrameFiles;
use crate::render_args::RenderArgs;
use crate::video::{VideoPlan, VideoRequest};

/// Where a render's frames and video go, checked before anything is rendered.
pub(crate) struct Outputs {
    pub files: FrameFiles,
    pub video: Option<VideoPlan>,
    /// Where `--legend` goes, checked.
    pub legend: Option<PathBuf>,
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
        if args.video_request().is_some() && files.format() == FrameFormat::Tiff16 {
            // ffmpeg reads piped frames in order and cannot seek back in a TIFF.
            bail!("--video is made from PNG, JPEG or WebP frames; 16-bit TIFF frames cannot be piped to ffmpeg");
        }
        let video = args.video_request().map(VideoRequest::check).transpose()?;
        let legend = args.legend.clone();
        if let Some(path) = &legend {
            let mode = request.render.color_mode;
            if !(mode.is_ramped()
                || matches!(mode, ColorMode::Classification | ColorMode::ReturnNumber))
            {
                bail!(
                    "--legend shows the colours of elevation, intensity, classification and \
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
        Ok(Self {
            files,
            video,
            legend,
        })
    }
}

/// Writes `legend` to `path`; the line that says so.
pub(crate) fn write_legend(path: &Path, legend: Option<Legend>) -> Result<String> {
    let legend = legend.context("--legend: the dataset has nothing to colour by in this mode")?;
    legend.write(path)?;
    let (width, height) = legend.size();
    Ok(format!("legend: {} ({width}x{height})", path.display()))
}

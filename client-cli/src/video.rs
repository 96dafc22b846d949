//! Assembling turntable frames into a video with ffmpeg, when it is installed.

use std::path::Path;
use std::process::Command;

use anyhow::{bail, Context, Result};

/// Encodes `dir/frame_00000.png, ...` as H.264 at `fps` into `video`.
pub fn assemble(dir: &Path, video: &Path, fps: u32) -> Result<()> {
    if Command::new("ffmpeg").arg("-version").output().is_err() {
        bail!(
            "ffmpeg is not installed, so no video was made; the frames are in {} \
             (install ffmpeg, e.g. apt-get install ffmpeg, and run again)",
            dir.display()
        );
    }
    let output = Command::new("ffmpeg")
        .args([
            "-y",
            "-loglevel",
            "error",
            "-framerate",
            &fps.to_string(),
            "-i",
        ])
        .arg(dir.join("frame_%05d.png"))
        // Even dimensions and yuv420p: what every player accepts.
        .args([
            "-vf",
            "pad=ceil(iw/2)*2:ceil(ih/2)*2",
            "-c:v",
            "libx264",
            "-pix_fmt",
            "yuv420p",
        ])
        .arg(video)
        .output()
        .context("running ffmpeg")?;
    if !output.status.success() {
        bail!(
            "ffmpeg failed: {}",
            String::from_utf8_lossy(&output.stderr).trim()
        );
    }
    Ok(())
}

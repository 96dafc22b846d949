//! Where `render` writes its frames: `--out` as one file for a still, or as a folder or a
//! numbered pattern (`frames/frame_{:05}.png`) for a turntable, in the image format the
//! extension names; each depth image, and the sidecar that turns it back into distances,
//! beside its frame.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use pointfarm_render::encode::geotiff::Georeference;
use pointfarm_render::encode::{self, FrameFormat};
use pointfarm_render::raster::FrameSettings;

use crate::render_json::CameraJson;

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
        if out.is_dir() {
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

/// Writes frame `index`'s depth image and its sidecar JSON (`.depth.json`): the near and far
/// distances its grey levels span, the camera and the image size, so that a pixel's value `v`
/// (1 to 65535; 0 where no point landed) is the distance `near + (v - 1) / 65534 * (far - near)`
/// along the viewing direction, in the dataset's units.
/// Beside a TIFF frame the depth image is a TIFF too, placed by `georeference` as its frame is.
pub fn save_depth(
    files: &FrameFiles,
    index: u32,
    frame: &pointfarm_render::raster::Frame,
    settings: &FrameSettings,
    georeference: Option<&Georeference>,
) -> Result<PathBuf> {
    let camera = &settings.camera;
    let path = files.depth(index);
    match files.format {
        FrameFormat::Tiff => {
            encode::save_depth_tiff16(frame, &path, camera.near, camera.far, georeference)
        }
        _ => encode::save_depth_png16(frame, &path, camera.near, camera.far),
    }
    .with_context(|| format!("writing {}", path.display()))?;
    let sidecar = path.with_extension("json");
    let json = serde_json::json!({
        "image": path.file_name().map(|n| n.to_string_lossy().into_owned()),
        "width": frame.image.width(),
        "height": frame.image.height(),
        "near": camera.near,
        "far": camera.far,
        "encoding": "16-bit grey, linear: 0 = no point; v in 1..65535 is the distance \
                     near + (v - 1) / 65534 * (far - near) along the viewing direction",
        "camera": CameraJson::of(camera),
    });
    let text = serde_json::to_string_pretty(&json).context("encoding the depth sidecar")?;
    std::fs::write(&sidecar, text + "\n")
        .with_context(|| format!("writing {}", sidecar.display()))?;
    Ok(path)
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_turntable_writes_into_a_folder_or_a_pattern_never_over_one_file() {
        let folder = FrameFiles::sequence(Path::new("out/frames/")).expect("folder");
        assert_eq!(folder.frame(7), Path::new("out/frames/frame_00007.png"));
        assert_eq!(
            folder.depth(7),
            Path::new("out/frames/frame_00007.depth.png")
        );
        let bare = FrameFiles::sequence(Path::new("frames")).expect("no extension");
        assert_eq!(bare.frame(0), Path::new("frames/frame_00000.png"));
        let jpeg = FrameFiles::sequence(Path::new("shots/orbit_{:03}.JPG")).expect("pattern");
        assert_eq!(jpeg.frame(12), Path::new("shots/orbit_012.JPG"));
        assert_eq!(jpeg.format(), FrameFormat::Jpeg);
        let plain = FrameFiles::sequence(Path::new("t{}.webp")).expect("unpadded");
        assert_eq!(plain.frame(123), Path::new("./t123.webp"));

        for (out, says) in [
            ("foo.png", "names one file"),
            ("a/{:05}/f.png", "not in a folder's"),
            ("f_{:05}_{}.png", "names one file"),
            ("f_{:x}.png", "names one file"),
            ("f_{:05}.gif", "not an image format"),
        ] {
            let error = FrameFiles::sequence(Path::new(out)).expect_err(out);
            assert!(format!("{error:#}").contains(says), "{out}: {error:#}");
        }
    }

    #[test]
    fn a_still_is_one_file_in_the_format_its_extension_names() {
        let still = FrameFiles::still(Path::new("views/top.webp")).expect("still");
        assert_eq!(still.frame(0), Path::new("views/top.webp"));
        assert_eq!(still.depth(0), Path::new("views/top.depth.png"));
        assert_eq!(still.format(), FrameFormat::WebP);
        let error = FrameFiles::still(Path::new("f_{:05}.png")).expect_err("pattern");
        assert!(error.to_string().contains("pattern"), "{error}");
        let jpeg = FrameFiles::still(Path::new("a.jpg")).expect("jpeg");
        assert!(jpeg.check_background([0, 0, 0, 0]).is_err());
        assert!(jpeg.check_background([0, 0, 0, 255]).is_ok());
    }
}

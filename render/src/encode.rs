//! Encoding rendered frames: a frame's image as PNG bytes, or as a PNG, JPEG, WebP or 16-bit
//! TIFF file chosen by its extension, and its depth image as a 16-bit grey PNG.
//!
//! The renderer returns pixels; encoding them is the caller's choice, and is timed as the
//! frame's "encode" stage so that it still shows in the frame's timings.

use std::fs::File;
use std::io::{BufWriter, Cursor, Write};
use std::path::Path;
use std::time::Instant;

use image::codecs::jpeg::JpegEncoder;
use image::codecs::webp::WebPEncoder;
use image::{
    DynamicImage, ExtendedColorType, ImageBuffer, ImageError, ImageFormat, Luma, RgbaImage,
};

use crate::raster::{Clock, Frame, Stage};

/// Why a frame could not be encoded. Callers name the file they were writing.
#[derive(Debug, thiserror::Error)]
pub enum EncodeError {
    /// A depth PNG was asked of a frame rendered without [`FrameSettings::read_depth`].
    ///
    /// [`FrameSettings::read_depth`]: crate::raster::FrameSettings::read_depth
    #[error("the frame was rendered without its depth image (read_depth)")]
    NoDepthImage,
    /// The encoder or the file system failed.
    #[error("encoding the image: {0}")]
    Image(#[from] ImageError),
    /// The file's extension names no format a frame is written in.
    #[error("{0}: give a file ending in {exts}", exts = FrameFormat::EXTENSIONS)]
    UnknownFormat(String),
}

/// The file formats a frame's image is written in, chosen by the file's extension.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FrameFormat {
    Png,
    /// Baseline JPEG at [`JPEG_QUALITY`]; no alpha channel.
    Jpeg,
    /// Lossless WebP.
    WebP,
    /// RGBA at 16 bits a channel (the frame's 8-bit channels widened, `v * 257`), for tools
    /// that take only 16-bit rasters.
    Tiff16,
}

/// JPEG quality (1 to 100) of [`FrameFormat::Jpeg`]: high enough that the points' edges do
/// not ring.
pub const JPEG_QUALITY: u8 = 92;

impl FrameFormat {
    /// The extensions accepted, for messages.
    pub const EXTENSIONS: &'static str = ".png, .jpg/.jpeg, .webp or .tif/.tiff";

    /// The format a file named `path` is written in, from its extension (any case).
    pub fn from_path(path: &Path) -> Result<Self, EncodeError> {
        let extension = path
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase);
        match extension.as_deref() {
            Some("png") => Ok(Self::Png),
            Some("jpg" | "jpeg") => Ok(Self::Jpeg),
            Some("webp") => Ok(Self::WebP),
            Some("tif" | "tiff") => Ok(Self::Tiff16),
            Some(other) => Err(EncodeError::UnknownFormat(format!(
                "{} is not an image format pointfarm writes (.{other})",
                path.display()
            ))),
            None => Err(EncodeError::UnknownFormat(format!(
                "{} has no extension to choose an image format by",
                path.display()
            ))),
        }
    }

    /// Whether the format keeps a transparent background.
    pub fn has_alpha(self) -> bool {
        self != Self::Jpeg
    }

    /// The usual extension, without the dot.
    pub fn extension(self) -> &'static str {
        match self {
            Self::Png => "png",
            Self::Jpeg => "jpg",
            Self::WebP => "webp",
            Self::Tiff16 => "tif",
        }
    }
}

/// Encodes the frame's image as PNG bytes and records the time in its "encode" stage.
pub fn png_bytes(frame: &mut Frame) -> Result<Vec<u8>, EncodeError> {
    timed_encode(frame, |image| {
        let mut png = Vec::new();
        image.write_to(&mut Cursor::new(&mut png), ImageFormat::Png)?;
        Ok(png)
    })
}

/// Writes the frame's image as a file in `format` and records the time in its "encode" stage.
pub fn save_frame(frame: &mut Frame, path: &Path, format: FrameFormat) -> Result<(), EncodeError> {
    timed_encode(frame, |image| write_image(image, path, format))
}

/// Writes an image (a frame's, or one fetched from a server) as a file in `format`.
pub fn save_image(image: &RgbaImage, path: &Path, format: FrameFormat) -> Result<(), EncodeError> {
    Ok(write_image(image, path, format)?)
}

fn write_image(image: &RgbaImage, path: &Path, format: FrameFormat) -> Result<(), ImageError> {
    match format {
        FrameFormat::Png => image.save_with_format(path, ImageFormat::Png),
        FrameFormat::Jpeg => {
            let rgb = DynamicImage::ImageRgba8(image.clone()).into_rgb8();
            let mut file = BufWriter::new(File::create(path)?);
            JpegEncoder::new_with_quality(&mut file, JPEG_QUALITY).encode_image(&rgb)?;
            Ok(file.flush()?)
        }
        FrameFormat::WebP => {
            let mut file = BufWriter::new(File::create(path)?);
            WebPEncoder::new_lossless(&mut file).encode(
                image.as_raw(),
                image.width(),
                image.height(),
                ExtendedColorType::Rgba8,
            )?;
            Ok(file.flush()?)
        }
        FrameFormat::Tiff16 => DynamicImage::ImageRgba8(image.clone())
            .into_rgba16()
            .save_with_format(path, ImageFormat::Tiff),
    }
}

/// Writes the frame's depth image as a 16-bit grey PNG: linear depth from `near` (1) to `far`
/// (65535); 0 where no point landed. Needs [`FrameSettings::read_depth`].
///
/// [`FrameSettings::read_depth`]: crate::raster::FrameSettings::read_depth
pub fn save_depth_png16(
    frame: &Frame,
    path: &Path,
    near: f64,
    far: f64,
) -> Result<(), EncodeError> {
    let Some(depth) = &frame.depth else {
        return Err(EncodeError::NoDepthImage);
    };
    let span = (far - near).max(f64::MIN_POSITIVE);
    let pixels: Vec<u16> = depth
        .iter()
        .map(|&d| {
            if d.is_finite() {
                1 + (((d as f64 - near) / span).clamp(0.0, 1.0) * 65534.0).round() as u16
            } else {
                0
            }
        })
        .collect();
    let image = ImageBuffer::<Luma<u16>, Vec<u16>>::from_raw(
        frame.image.width(),
        frame.image.height(),
        pixels,
    )
    .ok_or_else(|| {
        ImageError::Parameter(image::error::ParameterError::from_kind(
            image::error::ParameterErrorKind::DimensionMismatch,
        ))
    })?;
    Ok(image.save_with_format(path, ImageFormat::Png)?)
}

/// Runs `encode` on the frame's image, timing it as the frame's "encode" stage.
fn timed_encode<T>(
    frame: &mut Frame,
    encode: impl FnOnce(&RgbaImage) -> Result<T, ImageError>,
) -> Result<T, EncodeError> {
    let started = Instant::now();
    let encoded = encode(&frame.image)?;
    frame.timings.push(
        Stage::Encode,
        started.elapsed().as_secs_f64() * 1e3,
        Clock::Host,
    );
    Ok(encoded)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::raster::{AtomicsPath, StageTimings};

    fn gradient_frame() -> Frame {
        let image = RgbaImage::from_fn(64, 48, |x, y| {
            image::Rgba([
                (x * 4) as u8,
                (y * 5) as u8,
                128,
                if x < 4 { 0 } else { 255 },
            ])
        });
        Frame {
            image,
            depth: None,
            timings: StageTimings::default(),
            atomics: AtomicsPath::Atomic64,
        }
    }

    #[test]
    fn every_format_reads_back_as_the_frame_it_was_written_from() {
        let dir = tempfile::tempdir().expect("tempdir");
        for (name, format) in [
            ("f.png", FrameFormat::Png),
            ("f.WEBP", FrameFormat::WebP),
            ("f.tiff", FrameFormat::Tiff16),
            ("f.jpeg", FrameFormat::Jpeg),
        ] {
            let path = dir.path().join(name);
            assert_eq!(FrameFormat::from_path(&path).expect("known"), format);
            let mut frame = gradient_frame();
            save_frame(&mut frame, &path, format).expect("written");
            assert!(frame.timings.get(Stage::Encode).is_some(), "{name}: timed");
            let read = image::open(&path).expect("readable");
            if format == FrameFormat::Tiff16 {
                let wide = read.as_rgba16().expect("16-bit RGBA");
                let narrow = gradient_frame().image;
                assert!(wide.pixels().zip(narrow.pixels()).all(|(w, n)| w
                    .0
                    .iter()
                    .zip(n.0)
                    .all(|(&w, n)| w == u16::from(n) * 257)));
            } else if format == FrameFormat::Jpeg {
                // Lossy and opaque: close in colour, alpha dropped.
                let rgb = read.to_rgb8();
                let worst = rgb
                    .pixels()
                    .zip(gradient_frame().image.pixels())
                    .flat_map(|(a, e)| a.0.into_iter().zip(e.0).map(|(a, e)| a.abs_diff(e)))
                    .max();
                assert!(worst.is_some_and(|w| w <= 12), "{name}: {worst:?}");
            } else {
                assert_eq!(read.to_rgba8(), gradient_frame().image, "{name}");
            }
        }
    }

    #[test]
    fn a_file_without_a_known_extension_is_refused_naming_the_formats() {
        for name in ["frame.bmp", "frame", "frames/"] {
            let error = FrameFormat::from_path(Path::new(name)).expect_err(name);
            let message = error.to_string();
            assert!(message.contains(".jpg/.jpeg"), "{message}");
        }
    }
}

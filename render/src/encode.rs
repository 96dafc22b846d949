//! Encoding rendered frames as PNG: a frame's image as PNG bytes or a file, and its depth
//! image as a 16-bit grey PNG.
//!
//! The renderer returns pixels; encoding them is the caller's choice, and is timed as the
//! frame's "encode" stage so that it still shows in the frame's timings.

use std::io::Cursor;
use std::path::Path;
use std::time::Instant;

use image::{ImageBuffer, ImageError, ImageFormat, Luma, RgbaImage};

use crate::raster::{Clock, Frame, Stage};

/// Why a frame could not be encoded. Callers name the file they were writing.
#[derive(Debug, thiserror::Error)]
pub enum EncodeError {
    /// A depth PNG was asked of a frame rendered without [`FrameSettings::read_depth`].
    ///
    /// [`FrameSettings::read_depth`]: crate::raster::FrameSettings::read_depth
    #[error("the frame was rendered without its depth image (read_depth)")]
    NoDepthImage,
    /// The PNG encoder or the file system failed.
    #[error("encoding the PNG: {0}")]
    Image(#[from] ImageError),
}

/// Encodes the frame's image as PNG bytes and records the time in its "encode" stage.
pub fn png_bytes(frame: &mut Frame) -> Result<Vec<u8>, EncodeError> {
    timed_encode(frame, |image| {
        let mut png = Vec::new();
        image.write_to(&mut Cursor::new(&mut png), ImageFormat::Png)?;
        Ok(png)
    })
}

/// Writes the frame's image as a PNG file and records the time in its "encode" stage.
pub fn save_png(frame: &mut Frame, path: &Path) -> Result<(), EncodeError> {
    timed_encode(frame, |image| {
        image.save_with_format(path, ImageFormat::Png)
    })
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

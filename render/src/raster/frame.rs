use std::time::Instant;

use image::RgbaImage;

use super::{AtomicsPath, Clock, Stage, StageTimings};

#[derive(Debug, Clone)]
pub struct Frame {
    pub image: RgbaImage,
    /// Linear depth per pixel, row-major; +infinity where no point landed. Present when
    /// [`FrameSettings::read_depth`] was set.
    pub depth: Option<Vec<f32>>,
    pub timings: StageTimings,
    pub atomics: AtomicsPath,
}

impl Frame {
    /// Writes the depth image as a 16-bit grey PNG: linear depth from `near` (1) to `far`
    /// (65535); 0 where no point landed. Needs [`FrameSettings::read_depth`].
    pub fn save_depth_png16(
        &self,
        path: &std::path::Path,
        near: f64,
        far: f64,
    ) -> Result<(), image::ImageError> {
        let Some(depth) = &self.depth else {
            return Err(image::ImageError::Parameter(
                image::error::ParameterError::from_kind(image::error::ParameterErrorKind::Generic(
                    "the frame was rendered without its depth image".into(),
                )),
            ));
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
        let image = image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::from_raw(
            self.image.width(),
            self.image.height(),
            pixels,
        )
        .ok_or_else(|| {
            image::ImageError::Parameter(image::error::ParameterError::from_kind(
                image::error::ParameterErrorKind::DimensionMismatch,
            ))
        })?;
        image.save_with_format(path, image::ImageFormat::Png)
    }

    /// Writes the image as PNG and records the time in the frame's "encode" stage.
    pub fn save_png(&mut self, path: &std::path::Path) -> Result<(), image::ImageError> {
        let started = Instant::now();
        self.image.save_with_format(path, image::ImageFormat::Png)?;
        self.timings.push(
            Stage::Encode,
            started.elapsed().as_secs_f64() * 1e3,
            Clock::Host,
        );
        Ok(())
    }
}
